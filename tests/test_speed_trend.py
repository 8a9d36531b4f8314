"""The speed-trend input (``PolicyConfig.speed_trend_input``): each node also sees its previous token's mean speed
minus the mean speed of the token before it. It starts at zero output (adding it to a trained model keeps the
logits), and the padded forward, the packed training forward, the cached rollout step and an online decision over
remembered features (``before_token``) give the same logits."""

import torch

from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.packed import loss_mask
from r1sim_sumo.model.policy import TrafficPolicy
from r1sim_sumo.model.synthetic import synthetic_batch, synthetic_vocab
from r1sim_sumo.train.pretrain import load_init_weights


def _model(trend: bool, seed=0):
    torch.manual_seed(seed)
    cfg = PolicyConfig.preset("nano", agent_k=8, map_agent_k=8, map_k=8, dropout=0.0, agent_layers=2,
                              desired_speed_input=True, speed_trend_input=trend)
    voc = synthetic_vocab(cfg.vocab_sizes)
    return TrafficPolicy(cfg, voc).eval(), voc


class _Ckpt:
    def __init__(self, model):
        self.model, self.config = model, model.config


def _batch(voc, seed=4):
    b = synthetic_batch(voc, num_scenes=2, num_agents=12, num_map_tokens=200, seed=seed)
    g = torch.Generator().manual_seed(0)
    return b._replace(map_pos=b.map_pos + torch.rand(b.map_pos.shape, generator=g) * 0.01)


def test_adding_the_trend_input_keeps_a_trained_models_logits():
    base, voc = _model(False)
    new, _ = _model(True, seed=1)
    added = load_init_weights(new, _Ckpt(base), "base")
    assert added and all(k.startswith("speed_trend_emb.") for k in added)
    b = _batch(voc, seed=3)
    with torch.no_grad():
        ref, got = base(b), new(b)
    fin = torch.isfinite(ref)
    assert torch.equal(got[fin], ref[fin])


def test_trend_is_the_same_in_every_forward_and_changes_the_logits():
    model, voc = _model(True)
    torch.nn.init.normal_(model.speed_trend_emb.lin2.weight, std=0.5)
    b = _batch(voc)
    mask = loss_mask(b)
    tok = torch.where(b.agent_token_valid.bool(), b.agent_token, -1)
    with torch.no_grad():
        ref = model(b)
        got = model(b, out_mask=mask)
        fin = torch.isfinite(ref[mask])
        assert (got[fin] - ref[mask][fin]).abs().max() < 1e-4
        # the cached rollout keeps the last input token's speed itself
        cache = model.init_rollout(b, num_rollouts=2, upto_step=4)
        step4 = model.step(cache, 4, tok[:, :, 3].repeat(2, 1), b.pose_xy[:, :, 4].repeat(2, 1, 1),
                           b.pose_yaw[:, :, 4].repeat(2, 1), b.pose_valid[:, :, 4].bool().repeat(2, 1))
        ok = mask[:, :, 4] & torch.isfinite(ref[:, :, 4]).all(-1)
        assert ok.any()
        assert (step4[:2][ok] - ref[:, :, 4][ok]).abs().max() < 1e-3
        # a fresh cache (no step 3 run: an online decision) gets the token before from the caller
        fresh = model.init_rollout(b, num_rollouts=1, upto_step=4)
        fresh.prev_speed = torch.full_like(fresh.prev_speed, float("nan"))
        blind = model.step(fresh, 4, tok[:, :, 3], b.pose_xy[:, :, 4], b.pose_yaw[:, :, 4], b.pose_valid[:, :, 4].bool())
        fresh = model.init_rollout(b, num_rollouts=1, upto_step=4)
        told = model.step(fresh, 4, tok[:, :, 3], b.pose_xy[:, :, 4], b.pose_yaw[:, :, 4], b.pose_valid[:, :, 4].bool(),
                          before_token=tok[:, :, 2])
        assert (told[ok] - ref[:, :, 4][ok]).abs().max() < 1e-3
        speed = lambda t: model.token_speed[model._token_index(t.unsqueeze(-1), b.agent_type)][..., 0]  # noqa: E731
        moved = ok & (speed(tok[:, :, 3]) != speed(tok[:, :, 2]))
        assert moved.any()
        assert (blind[moved] - told[moved]).abs().amax(-1).min() > 1e-4  # without the token before: another input
    # the trend is read from the token speeds: equal consecutive tokens give the trend-0 embedding
    zero = model.speed_trend_emb(torch.zeros(1, 1))
    model2, _ = _model(True)
    model2.load_state_dict(model.state_dict())
    with torch.no_grad():
        model2.speed_trend_emb.lin2.bias.sub_(zero[0])  # now trend 0 adds nothing
        same = tok.clone()
        same[:, :, 1:] = same[:, :, :1].expand_as(same[:, :, 1:])  # every token the first one again: no trend
        b_same = b._replace(agent_token=same.clamp_min(0), agent_token_valid=(same >= 0) & b.agent_token_valid.bool())
        plain, _ = _model(False)
        plain.load_state_dict({k: v for k, v in model2.state_dict().items() if not k.startswith("speed_trend_emb.")})
        a, p = model2(b_same), plain(b_same)
    f = torch.isfinite(p)
    assert (a[f] - p[f]).abs().max() < 1e-4


def test_an_online_decision_over_remembered_features_sees_the_same_trend():
    """PolicyDriver's memory mode runs one step over remembered features in a fresh cache: it must hand the model
    the token before (``before_token``) and so equal the teacher-forced forward over the whole past."""
    from r1sim_sumo.model.untrained import untrained_policy
    from r1sim_sumo.sim.policy_driver import PolicyDriver
    from tests.test_policy_driver import (
        _road,
        _slice,
        _token_chained_history,
        capture_decision_logits,
        teacher_forced_batch,
    )

    policy = untrained_policy(seed=0, speed_trend_input=True)
    torch.nn.init.normal_(policy.model.speed_trend_emb.lin2.weight, std=1.0)
    full = _token_chained_history(policy)
    mem = PolicyDriver(policy, _road(), sampler="greedy", seed=0, memory=True)
    mem.plan(_slice(full, 0, 11))
    captured = capture_decision_logits(mem)
    mem.plan(_slice(full, 5, 16))
    assert mem.last_known == 5
    batch = teacher_forced_batch(policy, mem, full, 16)
    with torch.no_grad():
        ref = policy.model(batch)[0, :, 3]
        cut = policy.model.speed_trend_emb.lin2.weight.clone()
        policy.model.speed_trend_emb.lin2.weight.zero_()
        no_trend = policy.model(batch)[0, :, 3]
        policy.model.speed_trend_emb.lin2.weight.copy_(cut)
    assert (ref - no_trend).abs().max() > 1e-3  # the trend matters for these agents
    torch.testing.assert_close(captured["logits"][0], ref, atol=1e-4, rtol=1e-4)
