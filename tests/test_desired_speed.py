"""Each driver's desired speed as a policy input: estimated from the track in training data, given by the simulator
host online (SUMO, highway-env, the free-road probe), embedded so that adding it to a trained model starts from the
same logits, and carried through caches, collation, the packed training forward and the rollout cache."""

import numpy as np
import pytest
import torch

from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.packed import loss_mask
from r1sim_sumo.model.policy import TrafficPolicy
from r1sim_sumo.model.synthetic import synthetic_batch, synthetic_vocab
from r1sim_sumo.scenario import AgentTracks
from r1sim_sumo.tokens.batch import collate
from r1sim_sumo.tokens.matching import hindsight_speed, match_agents
from r1sim_sumo.tokens.motion_vocab import MotionVocab
from r1sim_sumo.train.pretrain import drop_desired_speed, load_init_weights


def _model(desired: bool, seed=0, gap: bool = False):
    torch.manual_seed(seed)
    cfg = PolicyConfig.preset("nano", agent_k=8, map_agent_k=8, map_k=8, dropout=0.0, agent_layers=2,
                              desired_speed_input=desired, speed_gap_input=gap)
    voc = synthetic_vocab(cfg.vocab_sizes)
    return TrafficPolicy(cfg, voc).eval(), voc


def _added_input_keeps_the_logits(base, new, prefix: str, voc):
    """Load ``base`` into ``new`` (which adds an input whose parameters start with ``prefix``); both give the same
    finite logits on a synthetic batch. Returns the batch, ``base``'s logits and their finite mask."""
    added = load_init_weights(new, _Ckpt(base), "base")
    assert added and all(k.startswith(prefix) for k in added)
    b = synthetic_batch(voc, num_scenes=2, num_agents=12, num_map_tokens=200, seed=3)
    with torch.no_grad():
        ref, got = base(b), new(b)
    fin = torch.isfinite(ref)
    assert torch.equal(got[fin], ref[fin])
    return b, ref, fin


class _Ckpt:  # what load_init_weights reads of a loaded checkpoint
    def __init__(self, model):
        self.model, self.config = model, model.config


def _straight_tracks(speeds_mps, n_steps=31):
    """One vehicle per row driving east at the given piecewise speeds [m/s] (one speed per 0.1 s step)."""
    v = np.asarray(speeds_mps, np.float64)
    A = v.shape[0]
    tr = AgentTracks.empty(A, n_steps)
    x = np.concatenate([np.zeros((A, 1)), np.cumsum(v * 0.1, 1)], 1)[:, :n_steps]
    tr.x_m[:] = x
    tr.speed_mps[:] = np.concatenate([v[:, :1], v], 1)[:, :n_steps]
    tr.vx_mps[:] = tr.speed_mps
    tr.valid[:] = True
    return tr


def test_hindsight_speed_is_the_fastest_half_second_and_nan_without_two_valid_poses():
    x = np.array([[0.0, 5.0, 15.0, 20.0], [0.0, 4.0, 8.0, 100.0]])
    valid = np.array([[True, True, True, True], [True, True, True, False]])
    got = hindsight_speed(x, np.zeros_like(x), valid)
    assert got == pytest.approx([20.0, 8.0])  # 10 m in 0.5 s; the jump to an invalid pose does not count
    lone = hindsight_speed(np.zeros((1, 3)), np.zeros((1, 3)), np.array([[False, True, False]]))
    assert np.isnan(lone).all()


def test_matching_takes_the_hosts_desired_speed_and_estimates_the_unknown_ones():
    voc = MotionVocab.from_traj({i: t.numpy() for i, t in enumerate(synthetic_vocab((64, 16, 16)))})
    speeds = np.concatenate([np.full((2, 15), 8.0), np.full((2, 15), 12.0)], 1)  # 8 m/s, then 12 m/s
    tr = _straight_tracks(speeds)
    est = match_agents(tr, voc).desired_speed()
    assert est == pytest.approx([12.0, 12.0], abs=1e-4)
    tr.desired_speed_mps = np.array([30.0, np.nan], np.float32)
    got = match_agents(tr, voc).desired_speed()
    assert got == pytest.approx([30.0, 12.0], abs=1e-4)
    assert match_agents(tr, voc).select([1]).desired_speed() == pytest.approx([12.0], abs=1e-4)


def test_collate_pads_desired_speeds_with_nan():
    voc = MotionVocab.from_traj({i: t.numpy() for i, t in enumerate(synthetic_vocab((64, 16, 16)))})
    from r1sim_sumo.tokens.batch import TokenizedScene
    from r1sim_sumo.tokens.map_tokens import MapTokens

    no_map = MapTokens(pts=np.zeros((0, 11, 2), np.float32), pos=np.zeros((0, 2), np.float32), yaw=np.zeros(0, np.float32),
                       kind=np.zeros(0, np.int64), speed_limit_mps=np.zeros(0, np.float32), tl=np.zeros((0, 19), np.int64),
                       polyline=np.zeros(0, np.int64))

    def scene(n):
        tr = _straight_tracks(np.full((n, 90), 10.0), n_steps=91)
        tr.desired_speed_mps = np.full(n, 25.0, np.float32)
        return TokenizedScene(match_agents(tr, voc), no_map, np.arange(n).astype(str), np.arange(n), "s")

    b = collate([scene(3), scene(1)])
    assert b.agent_desired_speed.shape == (2, 3)
    assert torch.equal(torch.isnan(b.agent_desired_speed), ~b.agent_mask)
    assert (b.agent_desired_speed[b.agent_mask] == 25.0).all()


def test_added_input_starts_at_the_init_models_logits_and_then_matters():
    base, voc = _model(False)
    new, _ = _model(True, seed=1)
    b, ref, fin = _added_input_keeps_the_logits(base, new, "desired_speed_emb.", voc)
    with torch.no_grad():
        torch.nn.init.normal_(new.desired_speed_emb.lin2.weight, std=0.5)  # as after training
        fast = new(b._replace(agent_desired_speed=torch.full_like(b.agent_desired_speed, 33.0)))
        slow = new(b._replace(agent_desired_speed=torch.full_like(b.agent_desired_speed, 5.0)))
        unknown = new(b._replace(agent_desired_speed=torch.full_like(b.agent_desired_speed, float("nan"))))
    assert (fast[fin] - slow[fin]).abs().max() > 1e-3
    assert torch.equal(unknown[fin], ref[fin])  # NaN = no contribution: the init model's logits


def test_init_weights_load_into_a_model_that_searches_neighbours_farther():
    """A run may widen the neighbour radii of its init checkpoint (they pick the k nearest nodes, no weight depends on
    them): the weights load unchanged, and on a scene whose agents lie farther apart than 60 m the logits change
    (the wider model sees agents the narrower one does not)."""
    base, voc = _model(False)
    wide = TrafficPolicy(PolicyConfig.preset("nano", agent_k=8, map_agent_k=8, map_k=8, dropout=0.0, agent_layers=2,
                                             agent_radius_m=150.0), voc).eval()
    assert load_init_weights(wide, _Ckpt(base), "base") == []
    assert all(torch.equal(p, q) for p, q in zip(base.state_dict().values(), wide.state_dict().values(), strict=True))
    b = synthetic_batch(voc, num_scenes=2, num_agents=12, num_map_tokens=200, seed=3)
    with torch.no_grad():
        ref, got = base(b), wide(b)
    assert not torch.equal(ref[torch.isfinite(ref)], got[torch.isfinite(ref)])  # farther agents are seen now


def test_init_weights_refuse_another_model():
    base, _ = _model(False)
    other = TrafficPolicy(PolicyConfig.preset("nano", agent_k=8, map_agent_k=8, map_k=8, dropout=0.0, agent_layers=3,
                                              desired_speed_input=True), synthetic_vocab((2048, 512, 512)))
    with pytest.raises(ValueError, match="init_checkpoint"):
        load_init_weights(other, _Ckpt(base), "base")


def test_packed_forward_and_rollout_cache_see_the_desired_speed():
    model, voc = _model(True)
    torch.nn.init.normal_(model.desired_speed_emb.lin2.weight, std=0.5)
    b = synthetic_batch(voc, num_scenes=2, num_agents=12, num_map_tokens=200, seed=4)
    g = torch.Generator().manual_seed(0)
    b = b._replace(map_pos=b.map_pos + torch.rand(b.map_pos.shape, generator=g) * 0.01)
    mask = loss_mask(b)
    with torch.no_grad():
        ref = model(b)[mask]
        got = model(b, out_mask=mask)
        fin = torch.isfinite(ref)
        assert (got[fin] - ref[fin]).abs().max() < 1e-4
        cache = model.init_rollout(b, num_rollouts=1, upto_step=3)
        plain = model._agent_static(b.agent_type, b.agent_size, torch.full_like(b.agent_desired_speed, float("nan")))  # noqa: SLF001
    assert not torch.allclose(cache.agent_static, plain)


def test_drop_desired_speed_draws_nothing_at_zero_and_hides_a_share():
    _, voc = _model(True)
    b = synthetic_batch(voc, num_scenes=2, num_agents=40, num_map_tokens=100, seed=5)
    g = torch.Generator().manual_seed(0)
    assert drop_desired_speed(b, 0.0, g) is b
    assert torch.equal(g.get_state(), torch.Generator().manual_seed(0).get_state())
    out = drop_desired_speed(b, 0.5, g)
    hidden = torch.isnan(out.agent_desired_speed) & ~torch.isnan(b.agent_desired_speed)
    assert 0.2 < hidden.float().mean() < 0.8


def test_the_model_asks_for_desired_speeds_it_needs():
    model, voc = _model(True)
    b = synthetic_batch(voc, num_scenes=1, num_agents=5, num_map_tokens=50, seed=6)
    fields = {k: v for k, v in b._asdict().items() if k != "agent_desired_speed"}
    from collections import namedtuple

    Old = namedtuple("Old", list(fields))
    with pytest.raises(ValueError, match="agent_desired_speed"):
        model(Old(**fields))


def test_speed_gap_input_starts_at_the_init_models_logits_and_needs_the_desired_speed():
    base, voc = _model(True)
    torch.nn.init.normal_(base.desired_speed_emb.lin2.weight, std=0.5)
    new, _ = _model(True, seed=1, gap=True)
    _added_input_keeps_the_logits(base, new, "speed_gap_emb.", voc)
    with pytest.raises(ValueError, match="speed_gap_input needs desired_speed_input"):
        PolicyConfig.preset("nano", speed_gap_input=True)


def test_speed_gap_is_desired_minus_the_previous_tokens_speed_in_every_forward():
    """The padded forward, the packed training forward and the cached rollout step give the same logits; the gap
    is measured from the previous token's mean speed, so an agent's logits change with its desired speed step by
    step, and not at all where the desired speed is unknown."""
    model, voc = _model(True, gap=True)
    torch.nn.init.normal_(model.speed_gap_emb.lin2.weight, std=0.5)
    b = synthetic_batch(voc, num_scenes=2, num_agents=12, num_map_tokens=200, seed=4)
    g = torch.Generator().manual_seed(0)
    b = b._replace(map_pos=b.map_pos + torch.rand(b.map_pos.shape, generator=g) * 0.01)
    # the token speed table: mean speed over the token [m/s]; start tokens unknown
    v_total = sum(model.config.vocab_sizes)
    tr0 = torch.as_tensor(voc[0])
    assert torch.allclose(model.token_speed[:3], tr0[:3, -1, :2].norm(dim=-1) / 0.5)
    assert torch.isnan(model.token_speed[v_total:]).all()
    mask = loss_mask(b)
    with torch.no_grad():
        ref = model(b)
        got = model(b, out_mask=mask)
        fin = torch.isfinite(ref[mask])
        assert (got[fin] - ref[mask][fin]).abs().max() < 1e-4
        cache = model.init_rollout(b, num_rollouts=2, upto_step=4)  # runs steps 0..3 through `step`
        tok = torch.where(b.agent_token_valid.bool(), b.agent_token, -1)
        step4 = model.step(cache, 4, tok[:, :, 3].repeat(2, 1), b.pose_xy[:, :, 4].repeat(2, 1, 1),
                           b.pose_yaw[:, :, 4].repeat(2, 1), b.pose_valid[:, :, 4].bool().repeat(2, 1))
        ok = mask[:, :, 4] & torch.isfinite(ref[:, :, 4]).all(-1)
        assert (step4[:2][ok] - ref[:, :, 4][ok]).abs().max() < 1e-3
        unknown = model(b._replace(agent_desired_speed=torch.full_like(b.agent_desired_speed, float("nan"))))
        other = model(b._replace(agent_desired_speed=b.agent_desired_speed + 10.0))
    plain, _ = _model(True)
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("speed_gap_emb.")})
    with torch.no_grad():
        no_gap = plain.eval()(b._replace(agent_desired_speed=torch.full_like(b.agent_desired_speed, float("nan"))))
    f = torch.isfinite(ref)
    assert torch.equal(unknown[f], no_gap[f])  # unknown desired speed: neither input contributes
    assert (other[f] - ref[f]).abs().max() > 1e-3
