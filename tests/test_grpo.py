"""GRPO fine-tuning: rewards, advantages, the clipped/KL loss, the learner on toy scenes, SFT, finetune + resume."""

import copy
import math
from pathlib import Path

import pytest
import torch

from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.policy import TrafficPolicy
from r1sim_sumo.rollout.engine import RolloutResult, rollout
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.tokens.batch import SceneBatch
from r1sim_sumo.tokens.motion_vocab import MotionVocab
from r1sim_sumo.train.grpo import (
    LOG_FIELDS,
    GRPOConfig,
    GRPOLearner,
    TensorSource,
    finetune,
    group_advantages,
    grpo_loss,
    rebuild_batch,
    token_logp,
)
from r1sim_sumo.train.rewards import RewardConfig, compute_rewards, token_collisions
from r1sim_sumo.train.sft import closed_loop_targets

torch.set_num_threads(1)


# ---------------------------------------------------------------------------- toy world


def straight_vocab(speeds_mps=(0.0, 10.0)) -> MotionVocab:
    """Straight constant-speed tokens (token 0 = standing still) for every type."""
    t = torch.arange(6, dtype=torch.float32) * 0.1
    def traj(sp):
        tr = torch.zeros(len(sp), 6, 3)
        tr[:, :, 0] = torch.tensor(sp)[:, None] * t
        return tr.numpy()
    return MotionVocab.from_traj({0: traj(speeds_mps), 1: traj((0.0, 1.0)), 2: traj((0.0, 1.0))})


def toy_batch(xy0, yaw0, ref_speed_mps=None, n_scenes=1) -> SceneBatch:
    """Vehicles standing still for the history at ``xy0``/``yaw0``; the reference future moves straight at
    ``ref_speed_mps`` (default: stands still). A straight road of 5 m map tokens along x."""
    A = len(xy0)
    ref = torch.zeros(A) if ref_speed_mps is None else torch.tensor(ref_speed_mps, dtype=torch.float32)
    xy = torch.tensor(xy0, dtype=torch.float32)[:, None, :].repeat(1, 19, 1)
    yaw = torch.tensor(yaw0, dtype=torch.float32)[:, None].repeat(1, 19)
    steps = torch.clamp(torch.arange(19) - 2, min=0).float() * 0.5  # [s] after now
    d = ref[:, None] * steps  # [A, 19]
    xy = xy + torch.stack([d * yaw.cos(), d * yaw.sin()], -1)
    M = 12
    pts = torch.zeros(M, 11, 2)
    pts[:, :, 0] = torch.linspace(0, 5, 11)
    one = dict(
        agent_token=torch.zeros(A, 18, dtype=torch.long), agent_token_valid=torch.ones(A, 18, dtype=torch.bool),
        pose_xy=xy, pose_yaw=yaw, pose_valid=torch.ones(A, 19, dtype=torch.bool), agent_type=torch.zeros(A, dtype=torch.long),
        agent_size=torch.tensor([[4.8, 2.0]]).repeat(A, 1), agent_mask=torch.ones(A, dtype=torch.bool),
        agent_desired_speed=torch.full((A,), float("nan")),
        map_pts=pts, map_pos=torch.stack([torch.arange(M) * 5.0 - 20, torch.zeros(M)], -1), map_yaw=torch.zeros(M),
        map_kind=torch.zeros(M, dtype=torch.long), map_speed=torch.full((M,), 13.9), map_tl=torch.zeros(M, 19, dtype=torch.long),
        map_mask=torch.ones(M, dtype=torch.bool),
    )
    return SceneBatch(**{k: v.unsqueeze(0).repeat(n_scenes, *([1] * v.dim())) for k, v in one.items()})


def toy_model(vocab: MotionVocab, seed: int = 0) -> TrafficPolicy:
    torch.manual_seed(seed)
    cfg = PolicyConfig.preset("nano", vocab_sizes=vocab.sizes, agent_layers=2, map_layers=1)
    return TrafficPolicy(cfg, [torch.as_tensor(vocab.traj[i]) for i in range(3)]).eval()


class Pol:
    def __init__(self, model, vocab):
        self.model, self.vocab = model, vocab


def hand_result(xy_10hz, yaw_10hz=None, valid=None, sim_mask=None) -> RolloutResult:
    """A RolloutResult ``[1, 1, A, F]`` from hand-built 10 Hz states ``[A, 5F+1, 2]``."""
    xy = torch.as_tensor(xy_10hz, dtype=torch.float32)[None, None]
    A, N = xy.shape[2], xy.shape[3]
    F = (N - 1) // 5
    yaw = torch.zeros(1, 1, A, N) if yaw_10hz is None else torch.as_tensor(yaw_10hz, dtype=torch.float32)[None, None]
    v = torch.ones(1, 1, A, F + 1, dtype=torch.bool) if valid is None else torch.as_tensor(valid)[None, None]
    sm = torch.ones(1, A, dtype=torch.bool) if sim_mask is None else torch.as_tensor(sim_mask)[None]
    z = torch.zeros(1, 1, A, F)
    return RolloutResult(token=torch.zeros(1, 1, A, F, dtype=torch.long), logp=z, logp_full=z, entropy=z,
                         k=torch.ones(1, 1, A, F, dtype=torch.long), pose_xy=xy[..., ::5, :], pose_yaw=yaw[..., ::5],
                         xy_10hz=xy, yaw_10hz=yaw, valid=v, sim_mask=sm)


def line(x0, x1, n=6, y=0.0):
    return [[x0 + (x1 - x0) * i / (n - 1), y] for i in range(n)]


def ref_batch_for(result: RolloutResult, ref_xy, ref_valid=None) -> SceneBatch:
    """A batch whose reference boundary poses 2.. are ``ref_xy [A, F+1, 2]``."""
    A, F1 = len(ref_xy), len(ref_xy[0])
    b = toy_batch([[0.0, 0.0]] * A, [0.0] * A)
    pxy = b.pose_xy.clone()
    pxy[0, :, 2 : 2 + F1] = torch.tensor(ref_xy, dtype=torch.float32)
    pv = b.pose_valid.clone()
    if ref_valid is not None:
        pv[0, :, 2 : 2 + F1] = torch.tensor(ref_valid)
    return b._replace(pose_xy=pxy, pose_valid=pv)


# ---------------------------------------------------------------------------- rewards


def test_collision_flags_states_vs_end():
    # agent 0 drives 0 -> 10 m through agent 1 parked at x = 5; at the end pose they no longer overlap
    r = hand_result([line(0, 10), line(5, 5)])
    size = torch.tensor([[[4.8, 2.0], [4.8, 2.0]]])
    states = token_collisions(r.xy_10hz, r.yaw_10hz, r.valid_10hz(), size, "states")
    end = token_collisions(r.xy_10hz, r.yaw_10hz, r.valid_10hz(), size, "end")
    assert states[0, 0, :, 0].tolist() == [True, True]
    assert end[0, 0, :, 0].tolist() == [False, False]
    # side by side with 3 m lateral gap: no overlap; invalid partner: no collision
    far = hand_result([line(0, 5), line(0, 5, y=3.0)])
    assert not token_collisions(far.xy_10hz, far.yaw_10hz, far.valid_10hz(), size).any()
    inval = hand_result([line(0, 10), line(5, 5)], valid=[[True, True], [False, False]], sim_mask=[True, False])
    assert not token_collisions(inval.xy_10hz, inval.yaw_10hz, inval.valid_10hz(), size).any()


def test_reward_values_each_variant():
    alpha = 0.5
    # agent 0: collides (passes through parked agent 1), ends 2 m from its reference; agent 1 at its reference
    r = hand_result([line(0, 10), line(5, 5)])
    b = ref_batch_for(r, [[[0, 0], [8, 0]], [[5, 0], [5, 0]]])
    e2 = math.exp(-alpha * 2.0)
    vals = {}
    for kind in ("spr", "apr", "or", "ahr", "shr", "gated"):
        out = compute_rewards(r, b, RewardConfig(kind=kind, alpha=alpha))
        assert out.mask.all() and out.collision.all()
        assert torch.allclose(out.distance_m[0, 0, :, 0], torch.tensor([2.0, 0.0]))
        vals[kind] = out.reward[0, 0, :, 0].tolist()
    assert vals["spr"] == pytest.approx([-e2, -1.0])
    assert vals["apr"] == pytest.approx([-1 + e2, 0.0])
    assert vals["or"] == pytest.approx([-e2, -1.0])  # one step: outcome = process
    assert vals["shr"] == pytest.approx([-e2, -1.0])
    assert vals["ahr"] == pytest.approx([-1 + e2, 0.0])
    assert vals["gated"] == pytest.approx([0.0, 0.0])
    g = compute_rewards(r, b, RewardConfig(kind="gated", collision_reward=-1.0))
    assert g.reward[0, 0, :, 0].tolist() == [-1.0, -1.0]
    # the paper's SPR quirk the gated variant fixes: colliding far from the reference beats colliding near it
    assert vals["spr"][0] > vals["spr"][1]


def test_reward_safe_near_far_and_masks():
    # two agents far apart: no collision; near (0.5 m) vs far (10 m) from the reference
    r = hand_result([line(0, 5), line(0, 5, y=20.0)])
    b = ref_batch_for(r, [[[0, 0], [5.5, 0]], [[0, 20], [15, 20]]])
    out = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.2))
    assert not out.collision.any()
    assert out.reward[0, 0, :, 0].tolist() == pytest.approx([math.exp(-0.1), math.exp(-2.0)])
    # reference invalid for agent 1: masked, reward 0 ... unless safety_without_reference
    b2 = ref_batch_for(r, [[[0, 0], [5.5, 0]], [[0, 20], [15, 20]]], ref_valid=[[True, True], [True, False]])
    out2 = compute_rewards(r, b2, RewardConfig(kind="spr", alpha=0.2))
    assert out2.mask[0, 0, :, 0].tolist() == [True, False] and float(out2.reward[0, 0, 1, 0]) == 0.0
    out3 = compute_rewards(r, b2, RewardConfig(kind="spr", alpha=0.2, safety_without_reference=True))
    assert out3.mask[0, 0, 1, 0] and float(out3.reward[0, 0, 1, 0]) == 1.0
    # agents not driven by the policy get no reward
    r4 = hand_result([line(0, 5), line(0, 5, y=20.0)], sim_mask=[True, False])
    assert compute_rewards(r4, b, RewardConfig()).mask[0, 0, :, 0].tolist() == [True, False]


def test_speed_kernel_rewards_a_token_that_speeds_up_like_the_reference_behind_it():
    # two tokens; the reference drives 10 then 14 m/s (5 m, then 7 m). Agent 0 lags 5 m after its first token and
    # speeds up like the reference in the second; agent 1 lags 5 m too but keeps its speed (2.5 m per token).
    lag_fast = line(0, 0, n=6) + line(0, 7, n=6)[1:]  # stands, then 7 m in 0.5 s (14 m/s)
    lag_slow = line(0, 0, n=6) + line(0, 2.5, n=6)[1:]
    r = hand_result([lag_fast, [[x, 20.0] for x, _ in lag_slow]])
    b = ref_batch_for(r, [[[0, 0], [5, 0], [12, 0]], [[0, 20], [5, 20], [12, 20]]])
    plain = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.2))
    mixed = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.2, speed_weight=0.5, speed_alpha=0.5))
    # the position kernel alone: agent 0's second token ends 5 m behind (exp(-1)), agent 1's 9.5 m behind
    assert plain.reward[0, 0, :, 1].tolist() == pytest.approx([math.exp(-1.0), math.exp(-1.9)])
    # with the speed kernel: agent 0's token speed equals the reference's (14 m/s) -> + 0.5 * 1
    assert float(mixed.reward[0, 0, 0, 1]) == pytest.approx(0.5 * math.exp(-1.0) + 0.5)
    assert float(mixed.reward[0, 0, 1, 1]) == pytest.approx(0.5 * math.exp(-1.9) + 0.5 * math.exp(-0.5 * 9.0))
    # first token: both stand (0 m/s) while the reference does 10 m/s
    assert float(mixed.reward[0, 0, 0, 0]) == pytest.approx(0.5 * math.exp(-1.0) + 0.5 * math.exp(-5.0))
    # an invalid reference boundary keeps the position kernel alone (and its mask)
    b2 = ref_batch_for(r, [[[0, 0], [5, 0], [12, 0]], [[0, 20], [5, 20], [12, 20]]],
                       ref_valid=[[True, False, True], [True, True, True]])
    m2 = compute_rewards(r, b2, RewardConfig(kind="spr", alpha=0.2, speed_weight=0.5))
    assert float(m2.reward[0, 0, 0, 1]) == pytest.approx(math.exp(-1.0))
    with pytest.raises(ValueError, match="speed_weight"):
        RewardConfig(speed_weight=1.5)


def test_speed_up_weight_scales_the_rewards_of_agents_whose_reference_speeds_up():
    # agent 0's reference goes 10 then 14 m/s (gain 4 m/s), agent 1's 10 then 10.5 m/s (gain 1 m/s, under 2)
    r = hand_result([line(0, 5) + line(5, 10)[1:], [[x, 20.0] for x, _ in line(0, 5) + line(5, 10)[1:]]])
    b = ref_batch_for(r, [[[0, 0], [5, 0], [12, 0]], [[0, 20], [5, 20], [10.25, 20]]])
    plain = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.2))
    weighted = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.2, speed_up_weight=3.0, speed_up_gain=2.0))
    assert torch.equal(plain.mask, weighted.mask)
    assert torch.allclose(weighted.reward[0, 0, 0], 3.0 * plain.reward[0, 0, 0])
    assert torch.equal(weighted.reward[0, 0, 1], plain.reward[0, 0, 1])
    # a lower threshold takes agent 1 in too
    low = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.2, speed_up_weight=3.0, speed_up_gain=0.5))
    assert torch.allclose(low.reward[0, 0, 1], 3.0 * plain.reward[0, 0, 1])
    # one valid token is no speed-up
    b1 = ref_batch_for(r, [[[0, 0], [5, 0], [12, 0]], [[0, 20], [5, 20], [12, 20]]],
                       ref_valid=[[True, True, False], [True, True, True]])
    one = compute_rewards(r, b1, RewardConfig(kind="spr", alpha=0.2, speed_up_weight=3.0))
    assert float(one.reward[0, 0, 0, 0]) == pytest.approx(float(compute_rewards(r, b1, RewardConfig(kind="spr", alpha=0.2)).reward[0, 0, 0, 0]))
    assert torch.allclose(one.reward[0, 0, 1], 3.0 * compute_rewards(r, b1, RewardConfig(kind="spr", alpha=0.2)).reward[0, 0, 1])
    with pytest.raises(ValueError, match="speed_up_weight"):
        RewardConfig(speed_up_weight=0.0)
    with pytest.raises(ValueError, match="speed_up_gain"):
        RewardConfig(speed_up_gain=-1.0)


def test_collision_flags_equal_the_all_pairs_sat_test():
    """The bounding-circle prefilter of :func:`token_collisions` changes no flag: random boxes of mixed sizes and
    headings, far from the origin, some invalid, against the plain all-pairs separating-axis test."""
    from r1sim_sumo.geometry import boxes_overlap

    g = torch.Generator().manual_seed(0)
    G, B, A, N = 3, 2, 40, 11
    xy = 5000.0 + torch.rand(G, B, A, N, 2, generator=g) * 200.0
    yaw = torch.rand(G, B, A, N, generator=g) * 6.3
    valid = torch.rand(G, B, A, N, generator=g) > 0.1
    size = torch.stack([2.0 + torch.rand(B, A, generator=g) * 14.0, 0.6 + torch.rand(B, A, generator=g) * 2.0], -1)
    got = token_collisions(xy, yaw, valid, size)
    x, y, a, v = xy[..., 1:, 0].movedim(2, -1), xy[..., 1:, 1].movedim(2, -1), yaw[..., 1:].movedim(2, -1), valid[..., 1:].movedim(2, -1)
    L, W = size[None, :, None, :, 0], size[None, :, None, :, 1]
    ov = boxes_overlap(x.unsqueeze(-1), y.unsqueeze(-1), a.unsqueeze(-1), L.unsqueeze(-1), W.unsqueeze(-1),
                       x.unsqueeze(-2), y.unsqueeze(-2), a.unsqueeze(-2), L.unsqueeze(-2), W.unsqueeze(-2))
    ok = v.unsqueeze(-1) & v.unsqueeze(-2) & ~torch.eye(A, dtype=torch.bool)
    want = (ov & ok).any(-1).reshape(G, B, 2, 5, A).any(3).movedim(2, -1)
    assert want.sum() > 50 and (~want).sum() > 50  # both outcomes occur
    assert torch.equal(got, want)


def one_lane_map(width_m: float = 3.2):
    """One straight lane along +x at y = 0 (x from -50 to 50 m), ``width_m`` wide: drivable |y| <= width/2."""
    import numpy as np

    from r1sim_sumo.scenario import MapPolylines

    return MapPolylines.from_lists([np.stack([np.linspace(-50, 50, 21), np.zeros(21)], 1)], [0], ["e_0"], [13.9], [width_m])


def test_offroad_reward_flags_the_token_that_leaves_the_lane_and_is_unsafe():
    """With ``RewardConfig.offroad`` a token whose box (4.8 x 2 m) has a corner outside the drivable area (a 3.2 m lane,
    |y| <= 1.6 m) gets r_safe = -1 like a collision; the same rollout without the flag is not penalised."""
    # agent 0 drifts sideways from y = 0 to y = 3 m over two tokens (corner leaves |y| <= 1.6 once y > 0.6 m);
    # agent 1 drives straight on the lane centre 30 m away
    xs = [i * 1.0 for i in range(11)]
    a0 = [[x, 0.0 if i <= 5 else 3.0 * (i - 5) / 5] for i, x in enumerate(xs)]
    a1 = [[x - 30.0, 0.0] for x in xs]
    r = hand_result([a0, a1])
    b = ref_batch_for(r, [[[0, 0], [5, 0], [10, 0]], [[-30, 0], [-25, 0], [-20, 0]]])
    lane = one_lane_map()
    on = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.2, offroad=True), maps=[lane])
    off = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.2))
    assert not on.collision.any()
    assert on.offroad[0, 0].tolist() == [[False, True], [False, False]]
    assert not off.offroad.any()
    e = math.exp(-0.2 * 3.0)
    assert float(on.reward[0, 0, 0, 1]) == pytest.approx(-e) and float(off.reward[0, 0, 0, 1]) == pytest.approx(e)
    assert torch.equal(on.reward[0, 0, 1], off.reward[0, 0, 1])  # the agent on the lane is unaffected
    # a wider lane (10 m: |y| <= 5) keeps the same drift on the road
    assert not compute_rewards(r, b, RewardConfig(offroad=True), maps=[one_lane_map(10.0)]).offroad.any()
    with pytest.raises(ValueError, match="maps"):
        compute_rewards(r, b, RewardConfig(offroad=True))


def test_outcome_reward_broadcast_over_steps():
    # 2 tokens; agent 0 collides only in token 1; OR penalises both tokens, SPR only token 1
    xy0 = line(0, 0, 6) + line(0, 10, 6)[1:]
    r = hand_result([xy0, line(7, 7, 11)])
    b = ref_batch_for(r, [[[0, 0], [0, 0], [10, 0]], [[7, 0], [7, 0], [7, 0]]])
    spr = compute_rewards(r, b, RewardConfig(kind="spr", alpha=0.0)).reward[0, 0, 0]
    orr = compute_rewards(r, b, RewardConfig(kind="or", alpha=0.0)).reward[0, 0, 0]
    assert spr.tolist() == [1.0, -1.0] and orr.tolist() == [-1.0, -1.0]


# ---------------------------------------------------------------------------- advantages and loss


def test_group_advantages_with_and_without_std():
    r = torch.tensor([1.0, 0.0, -1.0, 2.0]).view(4, 1)
    m = torch.ones(4, 1, dtype=torch.bool)
    a = group_advantages(r, m)
    assert a.view(-1).tolist() == pytest.approx([0.5, -0.5, -1.5, 1.5])
    s = group_advantages(r, m, std_normalise=True, std_eps=0.0)
    std = torch.tensor([1.0, 0.0, -1.0, 2.0]).std()
    assert s.view(-1).tolist() == pytest.approx((torch.tensor([0.5, -0.5, -1.5, 1.5]) / std).tolist(), rel=1e-5)
    # masked members neither get an advantage nor enter the mean
    m2 = torch.tensor([True, True, False, True]).view(4, 1)
    a2 = group_advantages(r, m2)
    assert a2.view(-1).tolist() == pytest.approx([0.0, -1.0, 0.0, 1.0])
    # reward-to-go: [1, 1] and [0, 1] over 2 steps -> returns [2, 1] and [1, 1]
    rtg = group_advantages(torch.tensor([[1.0, 1.0], [0.0, 1.0]]), torch.ones(2, 2, dtype=torch.bool), reward_to_go=True)
    assert rtg.flatten().tolist() == pytest.approx([0.5, 0.0, -0.5, 0.0])


def test_clipping_active_and_zero_gradient_for_clipped_terms():
    ratio = torch.tensor([1.5, 0.5, 1.1, 0.9, 1.5])
    adv = torch.tensor([1.0, -1.0, 1.0, -1.0, -1.0])
    new = ratio.log().clone().requires_grad_(True)
    old, mask = torch.zeros(5), torch.ones(5, dtype=torch.bool)
    loss, st = grpo_loss(new, old, new.detach(), adv, mask, eps_low=0.2, eps_high=0.2, beta_kl=0.0)
    loss.backward()
    assert st["clip_frac"] == pytest.approx(2 / 5)
    g = new.grad
    assert g[0] == 0 and g[1] == 0  # clipped: rho > 1 + eps with A > 0, rho < 1 - eps with A < 0
    assert (g[2:] != 0).all()  # inside the range, or rho > 1 + eps with A < 0 (pessimistic branch)
    # asymmetric clip: eps_high = 0.6 lets token 0 through
    new.grad = None
    _, st2 = grpo_loss(new, old, new.detach(), adv, mask, eps_low=0.2, eps_high=0.6, beta_kl=0.0)
    assert st2["clip_frac"] == pytest.approx(1 / 5)


def test_kl_zero_when_policy_equals_reference_and_positive_otherwise():
    lp = torch.log_softmax(torch.randn(10, 4), -1)[:, 0]
    mask = torch.ones(10, dtype=torch.bool)
    _, st = grpo_loss(lp, lp, lp, torch.zeros(10), mask, 0.2, 0.2, 1.0)
    assert st["kl"] == 0.0
    _, st2 = grpo_loss(lp, lp, lp - 0.3, torch.zeros(10), mask, 0.2, 0.2, 1.0)
    assert st2["kl"] > 0


def test_truncated_logp_matches_sampler():
    logits = torch.randn(50, 40)
    s = parse_sampler("topk:7@0.8")(logits, torch.Generator().manual_seed(0))
    lp = token_logp(logits, s.token, "truncated", s.k, 0.8)
    assert torch.allclose(lp, s.logp, atol=1e-5)
    full = token_logp(logits, s.token, "full")
    assert torch.allclose(full, torch.log_softmax(logits, -1).gather(-1, s.token[:, None])[:, 0])


# ---------------------------------------------------------------------------- the learner on toy scenes


@pytest.fixture(scope="module")
def head_on():
    """Two vehicles 8 m apart facing each other; token 1 (10 m/s) collides, token 0 (stand still) is safe."""
    vocab = straight_vocab((0.0, 10.0))
    return vocab, toy_model(vocab), toy_batch([[0.0, 0.0], [8.0, 0.0]], [0.0, math.pi])


def _p_still(model, batch) -> float:
    with torch.no_grad():
        return float(torch.softmax(model(batch)[:, :, 2].float(), -1)[..., 0].mean())


@pytest.mark.parametrize("logp_kind", ["full", "truncated"])
def test_ratio_one_on_first_minibatch_and_kl_zero_without_update(head_on, logp_kind):
    vocab, model, batch = head_on
    cfg = GRPOConfig(num_rollouts=6, sampler="full", num_steps=3, freeze="none", lr=1e-2, logp_kind=logp_kind,
                     num_minibatches=2, ppo_epochs=2)
    st = GRPOLearner(copy.deepcopy(model), copy.deepcopy(model), vocab, cfg).iteration(batch, torch.Generator().manual_seed(0))
    assert st["first_ratio_dev"] < 1e-5 and st["ratio_dev_max"] > 1e-4  # later minibatches see moved weights
    frozen = GRPOLearner(copy.deepcopy(model), copy.deepcopy(model), vocab, cfg.__class__(**{**cfg.__dict__, "lr": 0.0}))
    st0 = frozen.iteration(batch, torch.Generator().manual_seed(0))
    assert st0["kl"] == 0.0 and st0["ratio_dev_max"] < 1e-5


def test_rebuilt_batch_reproduces_rollout_logprobs(head_on):
    vocab, model, batch = head_on
    r = rollout(model, vocab, batch, num_rollouts=3, sampler=parse_sampler("full"), generator=torch.Generator().manual_seed(1))
    rb = rebuild_batch(batch, r.token, r.pose_xy, r.pose_yaw, r.valid)
    assert rb.agent_token.shape[0] == 3
    with torch.no_grad():
        lp = token_logp(model(rb)[:, :, 2:18], r.token.reshape(3, 2, 16))
    assert torch.allclose(lp, r.logp_full.reshape(3, 2, 16), atol=1e-4)


def test_grpo_raises_probability_of_safe_token(head_on):
    vocab, model, batch = head_on
    model = copy.deepcopy(model)
    cfg = GRPOConfig(num_rollouts=8, sampler="full", num_steps=1, freeze="none", lr=3e-3, beta_kl=0.0,
                     reward=RewardConfig(kind="spr", alpha=0.0), ppo_epochs=2, num_minibatches=2)
    learner = GRPOLearner(model, copy.deepcopy(model), vocab, cfg)
    p0 = _p_still(model, batch)
    colls = []
    for i in range(8):
        colls.append(learner.iteration(batch, torch.Generator().manual_seed(i))["collision_rate"])
    p1 = _p_still(model, batch)
    assert p1 > p0 + 0.2, (p0, p1)
    assert p1 > 0.8 and colls[-1] <= colls[0]


def test_grpo_with_offroad_reward_learns_to_stay_on_the_road(tmp_path):
    """A vehicle (4.8 m long) standing across a 6 m lane whose logged future drives off it (10 m/s along its heading): the distance kernel
    alone teaches the policy to follow the log off the road; with ``reward.offroad`` the same GRPO run learns to stay
    (token 0). ``finetune`` feeds the maps from the scene source and logs ``offroad_rate``; a source without maps is
    refused with the config field named."""
    vocab = straight_vocab((0.0, 10.0))
    batch = toy_batch([[0.0, 0.0]], [math.pi / 2], ref_speed_mps=[10.0])
    lane = one_lane_map(6.0)  # standing: corners at |y| <= 2.4 m, on; one 10 m/s token: y = 5 m, off

    class MapSource(TensorSource):
        def maps(self, indices):
            return [lane] * len(indices)

    p = {}
    for offroad in (False, True):
        model = toy_model(vocab, seed=1)
        p0 = _p_still(model, batch)
        cfg = GRPOConfig(num_rollouts=8, batch_scenes=1, sampler="full", num_steps=1, freeze="none", lr=3e-3, beta_kl=0.0,
                         reward=RewardConfig(kind="spr", alpha=0.2, offroad=offroad), ppo_epochs=2, num_minibatches=2,
                         max_iters=8, threads=1, out_dir=str(tmp_path / f"off{offroad}"))
        final = finetune(cfg, progress=False, policy=Pol(model, vocab), source=MapSource(batch))
        from r1sim_sumo import load_policy

        p[offroad] = _p_still(load_policy(final).model.float(), batch)
    assert p[True] > p0 + 0.2 and p[True] > 0.8, (p0, p)
    assert p[False] < p0, (p0, p)
    log = (tmp_path / "offTrue" / "log.csv").read_text().splitlines()
    rates = [float(r.split(",")[LOG_FIELDS.index("offroad_rate")]) for r in log[1:]]
    assert rates[0] > 0 and rates[-1] < rates[0]
    plain = (tmp_path / "offFalse" / "log.csv").read_text().splitlines()[1:]
    assert all(r.split(",")[LOG_FIELDS.index("offroad_rate")] == "" for r in plain)  # not measured, not logged as 0
    with pytest.raises(ValueError, match="reward.offroad"):
        finetune(GRPOConfig(reward=RewardConfig(offroad=True), max_iters=1, out_dir=str(tmp_path / "x")), progress=False,
                 policy=Pol(toy_model(vocab), vocab), source=TensorSource(batch))


@pytest.mark.parametrize("logp_kind", ["truncated", "full"])
def test_grpo_trains_through_truncated_entropy_guided_sampler(logp_kind):
    """The paper's path: entropy-guided K_t (here 5 of 6 tokens, so the sampled distribution is truncated) with the
    truncated log-probabilities in the ratio (and the full-softmax option). Two cars 14 m apart face each other: one
    fast car alone is safe, both fast collide; GRPO must learn to stand still."""
    vocab = straight_vocab((0.0, 10.0, 10.5, 11.0, 11.5, 12.0))
    model = toy_model(vocab)
    batch = toy_batch([[0.0, 0.0], [14.0, 0.0]], [0.0, math.pi])
    cfg = GRPOConfig(num_rollouts=8, sampler="entropy:4,5", num_steps=1, freeze="none", lr=3e-3, beta_kl=0.0,
                     reward=RewardConfig(kind="spr", alpha=0.0), logp_kind=logp_kind, ppo_epochs=2, num_minibatches=2)
    learner = GRPOLearner(copy.deepcopy(model), copy.deepcopy(model), vocab, cfg)
    r = rollout(model, vocab, batch, 8, parse_sampler(cfg.sampler), generator=torch.Generator().manual_seed(0), num_steps=1)
    assert (r.k == 5).all() and (r.logp > r.logp_full).all()  # truncated: renormalised over 5 of 6 tokens
    p0 = _p_still(learner.model, batch)
    rows = [learner.iteration(batch, torch.Generator().manual_seed(i)) for i in range(10)]
    assert rows[0]["k_mean"] == 5.0 and rows[0]["first_ratio_dev"] < 1e-5
    assert rows[0]["collision_rate"] > 0.3 and rows[-1]["collision_rate"] == 0.0
    assert _p_still(learner.model, batch) > max(0.8, p0 + 0.5)


def test_freeze_paper_trains_only_last_layers(head_on):
    vocab, model, _ = head_on
    m = copy.deepcopy(model)
    GRPOLearner(m, None, vocab, GRPOConfig(freeze="paper", method="sft"))
    def module_of(name: str) -> str:
        top, sub = name.split(".")[:2]
        return f"{top}.{sub}" if top.endswith("_blocks") else top

    trainable = {module_of(n) for n, p in m.named_parameters() if p.requires_grad}
    L = m.config.agent_layers - 1
    assert trainable == {"map_blocks.0", "map_norm", f"t_blocks.{L}", f"m_blocks.{L}", f"a_blocks.{L}", "head"}


def test_sft_lowers_distance_to_reference():
    vocab = straight_vocab((0.0, 2.0, 4.0, 6.0, 8.0, 10.0))
    model = toy_model(vocab, seed=1)
    batch = toy_batch([[0.0, 0.0], [0.0, 10.0]], [0.0, 0.0], ref_speed_mps=[6.0, 6.0])
    cfg = GRPOConfig(method="sft", num_steps=4, freeze="none", lr=3e-3, sft_top_k=3)
    learner = GRPOLearner(model, None, vocab, cfg)

    def greedy_dist() -> float:
        r = rollout(model, vocab, batch, 1, parse_sampler("greedy"), num_steps=4)
        return float((r.pose_xy[0, :, :, 1:] - batch.pose_xy[:, :, 3:7]).norm(dim=-1).mean())

    tg = closed_loop_targets(model, vocab, batch, top_k=6, num_steps=4)
    assert (tg.token[tg.target_ok] == 3).all() and float(tg.dist_m.max()) < 1e-4  # the 6 m/s token is recovered
    assert torch.equal(tg.label, tg.token)  # on the reference, the label is the token that stays on it
    d0 = greedy_dist()
    for i in range(10):
        learner.iteration(batch, torch.Generator().manual_seed(i))
    d1 = greedy_dist()
    assert d1 < 0.5 * d0 and d1 < 1.0, (d0, d1)


def test_sft_packed_loss_equals_padded_loss_and_gradients():
    from r1sim_sumo.train.rollout_batch import rebuild_batch
    from r1sim_sumo.train.sft import rollout_loss

    vocab = straight_vocab((0.0, 2.0, 4.0, 6.0, 8.0, 10.0))
    model = toy_model(vocab, seed=2)
    batch = toy_batch([[0.0, 0.0], [0.0, 10.0], [30.0, 3.5]], [0.0, 0.0, math.pi], ref_speed_mps=[6.0, 4.0, 8.0])
    tg = closed_loop_targets(model, vocab, batch, top_k=2, num_steps=6)
    assert tg.target_ok.sum() > 6
    rb = rebuild_batch(batch, tg.token[None], tg.pose_xy[None], tg.pose_yaw[None], tg.valid[None])
    grads = []
    for packed in (False, True):
        model.zero_grad()
        loss = rollout_loss(model, rb, tg, 0.1, packed=packed)
        loss.backward()
        grads.append((loss.detach(), [p.grad.clone() for p in model.parameters() if p.grad is not None]))
    torch.testing.assert_close(grads[0][0], grads[1][0], atol=1e-5, rtol=1e-5)
    assert len(grads[0][1]) == len(grads[1][1]) > 0
    for a, b in zip(grads[0][1], grads[1][1], strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)


class _Biased:
    """A policy whose step logits get ``bias [V]`` added (forces the top-K set in closed-loop SFT)."""

    def __init__(self, model, bias):
        self.model, self.bias = model, bias

    def eval(self):
        return self

    def init_rollout(self, *a, **kw):
        return self.model.init_rollout(*a, **kw)

    def step(self, *a, **kw):
        return self.model.step(*a, **kw) + self.bias


def test_sft_topk_smaller_than_vocab_rolls_out_within_topk_and_labels_over_whole_vocab():
    """top_k=2 of 6 tokens; the policy's top-2 are {still, 10 m/s}, the reference moves 3 m per token (6 m/s).
    Rollout (input) tokens stay inside the top-2 (closest among them); the CAT-K label is the nearest token over the
    whole vocabulary from the rolled-out pose to the reference at the next step, outside the top-2 here."""
    vocab = straight_vocab((0.0, 2.0, 4.0, 6.0, 8.0, 10.0))  # metres per token: 0, 1, 2, 3, 4, 5
    model = toy_model(vocab, seed=1)
    bias = torch.zeros(6)
    bias[[0, 5]] = 100.0
    batch = toy_batch([[0.0, 0.0]], [0.0], ref_speed_mps=[6.0])
    tg = closed_loop_targets(_Biased(model, bias), vocab, batch, top_k=2, num_steps=3)
    # step 0: at 0 m, ref 3 m: pick 10 m/s (2 m off) over still (3 m off) -> 5 m; label 6 m/s (token 3)
    # step 1: at 5 m, ref 6 m: pick still (1 m) -> 5 m; label 2 m/s (token 1)
    # step 2: at 5 m, ref 9 m: pick 10 m/s (1 m) -> 10 m; label 8 m/s (token 4)
    assert tg.token[0, 0].tolist() == [5, 0, 5]
    assert tg.label[0, 0].tolist() == [3, 1, 4]
    assert tg.pose_xy[0, 0, :, 0].tolist() == pytest.approx([0.0, 5.0, 5.0, 10.0], abs=1e-4)
    assert tg.target_ok.all()


def test_sft_label_uses_box_corners_and_heading():
    """From a pose turned 90 degrees away from the reference heading, the label is the token whose end box best
    overlaps the reference box (mean corner distance), not the one whose centre is nearest: a rotated 4.8 m box
    adds corner distance that a pure centre distance ignores."""
    import numpy as np

    from r1sim_sumo.train.sft import nearest_token_labels

    t = np.arange(6) * 0.1
    tr = np.zeros((2, 6, 3), np.float32)
    tr[0, :, 0] = 3.0 * t / 0.5  # straight 3 m, no turn: centre exactly on the reference
    tr[1, :, 0] = 2.0 * t / 0.5  # 2 m ahead turning by 90 degrees: centre 1 m short, heading right
    tr[1, :, 2] = (np.pi / 2) * t / 0.5
    small = np.zeros((2, 6, 3), np.float32)
    vocab = MotionVocab.from_traj({0: tr, 1: small, 2: small})
    # reference 3 m ahead of the pose, heading +90 degrees from the pose
    lab = nearest_token_labels(vocab, torch.zeros(1, 2), torch.zeros(1), torch.zeros(1, dtype=torch.long),
                               torch.tensor([[3.0, 0.0]]), torch.tensor([math.pi / 2]))
    assert lab.tolist() == [1]
    lab = nearest_token_labels(vocab, torch.zeros(1, 2), torch.zeros(1), torch.zeros(1, dtype=torch.long),
                               torch.tensor([[3.0, 0.0]]), torch.tensor([0.0]))
    assert lab.tolist() == [0]


def test_sft_trains_towards_catk_labels_outside_topk():
    """The SFT update raises the probability of the CAT-K label even when it lies outside the rollout's top-K."""
    vocab = straight_vocab((0.0, 2.0, 4.0, 6.0, 8.0, 10.0))
    model = toy_model(vocab, seed=1)
    batch = toy_batch([[0.0, 0.0], [0.0, 10.0]], [0.0, 0.0], ref_speed_mps=[6.0, 6.0])
    cfg = GRPOConfig(method="sft", num_steps=2, freeze="none", lr=3e-3, sft_top_k=2)
    learner = GRPOLearner(model, None, vocab, cfg)
    tg = closed_loop_targets(model, vocab, batch, top_k=2, num_steps=2)
    lab0 = int(tg.label[0, 0, 0])
    assert lab0 == 3  # from the current pose, 6 m/s is exactly the reference

    def p_label() -> float:
        from r1sim_sumo.rollout.engine import CURRENT_POSE

        with torch.no_grad():
            lg = model(batch)[0, 0, CURRENT_POSE]
        return float(torch.softmax(lg.float(), -1)[lab0])

    p0 = p_label()
    for i in range(6):
        learner.iteration(batch, torch.Generator().manual_seed(i))
    assert p_label() > p0 + 0.2, (p0, p_label())


def test_finetune_resume_identical(tmp_path, head_on):
    from safetensors.torch import load_file

    vocab, model, batch = head_on
    batch2 = SceneBatch(*(torch.cat([t, t]) for t in batch))
    src = TensorSource(batch2)
    common = dict(num_rollouts=4, batch_scenes=1, sampler="entropy:1,2", num_steps=2, freeze="paper", lr=1e-3,
                  ppo_epochs=2, num_minibatches=2, ckpt_every=1, threads=1)
    full = GRPOConfig(**common, max_iters=3, keep_every=2, out_dir=str(tmp_path / "a"))
    fa = finetune(full, progress=False, policy=Pol(model, vocab), source=src)
    kept = sorted(p.name for p in (tmp_path / "a").glob("ckpt-*"))
    assert kept == ["ckpt-000002"]  # the snapshot for learning curves; iteration 3 is only the final export
    w2 = load_file(str(tmp_path / "a" / "ckpt-000002" / "model.safetensors"))
    assert any(not torch.equal(w2[k], load_file(str(fa / "model.safetensors"))[k]) for k in w2)
    part = GRPOConfig(**common, max_iters=1, out_dir=str(tmp_path / "b"))
    finetune(part, progress=False, policy=Pol(model, vocab), source=src)
    with pytest.raises(FileExistsError):
        finetune(part, progress=False, policy=Pol(model, vocab), source=src)
    fb = finetune(GRPOConfig(**{**part.__dict__, "max_iters": 3}), resume=True, progress=False, policy=Pol(model, vocab), source=src)
    wa, wb = load_file(str(fa / "model.safetensors")), load_file(str(fb / "model.safetensors"))
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    w0 = model.state_dict()
    assert any(not torch.equal(wa["model." + k], w0[k]) for k in w0)  # it did train
    rows = (tmp_path / "b" / "log.csv").read_text().splitlines()
    assert len(rows) == 4  # header + 3 iterations, no duplicates after the resume


@pytest.mark.parametrize("kind", ["truncated", "full"])
def test_rollout_logp_packed_equals_padded(kind):
    from r1sim_sumo.train.grpo import rollout_logp
    from r1sim_sumo.train.rewards import RewardConfig, compute_rewards
    from r1sim_sumo.train.rollout_batch import rebuild_batch

    vocab = straight_vocab((0.0, 2.0, 4.0, 6.0, 8.0, 10.0))
    model = toy_model(vocab, seed=3)
    batch = toy_batch([[0.0, 0.0], [0.0, 10.0], [30.0, 3.5]], [0.0, 0.0, math.pi], ref_speed_mps=[6.0, 4.0, 8.0])
    res = rollout(model, vocab, batch, 4, parse_sampler("topk:3"), generator=torch.Generator().manual_seed(0), num_steps=5)
    mask = compute_rewards(res, batch, RewardConfig()).mask  # [G, B, A, F]
    G, B, A, F = res.token.shape
    rb = rebuild_batch(batch, res.token, res.pose_xy, res.pose_yaw, res.valid)
    flat = lambda t: t.reshape(G * B, *t.shape[2:])  # noqa: E731
    m, tok, k = flat(mask), flat(res.token), flat(res.k)
    assert m.sum() > 10
    outs = []
    for packed in (False, True):
        model.zero_grad()
        lp = rollout_logp(model, rb, m, tok, kind, k, 1.0, packed=packed)
        lp[m].sum().backward()
        outs.append((lp.detach(), [p.grad.clone() for p in model.parameters() if p.grad is not None]))
    torch.testing.assert_close(outs[0][0], outs[1][0], atol=1e-5, rtol=1e-5)
    assert float(outs[1][0][~m].abs().sum()) == 0.0
    for a, b in zip(outs[0][1], outs[1][1], strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)


def test_default_ratio_is_the_truncated_sampling_distribution(head_on):
    """Issue 16 item 10: by default the ratio uses the log-probabilities of the distribution the tokens were drawn
    from (top-K_t), in the dataclass and in configs/grpo.yaml; on a truncated sampler the first minibatch's ratio is 1
    with these log-probs (old = RolloutResult.logp, new recomputed under the same K_t)."""
    from pathlib import Path

    from r1sim_sumo.config import load_config

    assert GRPOConfig().logp_kind == "truncated"
    cfg_file = Path(__file__).resolve().parents[1] / "configs" / "grpo.yaml"
    assert load_config(GRPOConfig, str(cfg_file), []).logp_kind == "truncated"
    vocab = straight_vocab((0.0, 10.0, 10.5, 11.0, 11.5, 12.0))
    model = toy_model(vocab)
    batch = toy_batch([[0.0, 0.0], [14.0, 0.0]], [0.0, math.pi])
    cfg = GRPOConfig(num_rollouts=4, sampler="entropy:4,5", num_steps=2, freeze="none", lr=1e-2, ppo_epochs=1, num_minibatches=1)
    st = GRPOLearner(copy.deepcopy(model), copy.deepcopy(model), vocab, cfg).iteration(batch, torch.Generator().manual_seed(0))
    assert st["k_mean"] == 5.0 and st["first_ratio_dev"] < 1e-5


def test_dataset_source_draws_from_the_extra_datasets_after_the_main_one(tmp_path):
    """``extra_train_data``: scene indices past the main dataset's length come from the extra datasets in order, so the
    epoch permutation samples uniformly over all scenes; a GRPO config refuses extra data with SUMO-in-the-loop rollouts."""
    from r1sim_sumo.train.grpo import DatasetSource, GRPOConfig, finetune

    main, rings, more = [f"m{i}" for i in range(5)], [f"r{i}" for i in range(3)], ["x0"]
    src = DatasetSource(main, [rings, more])
    assert len(src) == 9
    assert [src.scene(i) for i in range(9)] == main + rings + more
    with pytest.raises(ValueError, match="extra_train_data"):
        cfg = GRPOConfig(rollout_source="sumo", extra_train_data=["data/generated/rings/train"], out_dir=str(tmp_path / "run"))
        finetune(cfg, policy=None, source=src)


def test_steady_start_prob_is_checked_and_runs(tmp_path, head_on):
    with pytest.raises(ValueError, match="steady_start_prob must be in"):
        GRPOConfig(steady_start_prob=1.5)
    with pytest.raises(ValueError, match="steady_start_prob needs rollout_source=model"):
        GRPOConfig(steady_start_prob=0.5, rollout_source="sumo")
    vocab, model, batch = head_on
    cfg = GRPOConfig(num_rollouts=2, batch_scenes=1, sampler="entropy:1,2", num_steps=2, max_iters=1, threads=1,
                     steady_start_prob=1.0, out_dir=str(tmp_path / "s"))
    assert (finetune(cfg, progress=False, policy=Pol(model, vocab), source=TensorSource(batch)) / "model.safetensors").exists()


def test_grpo_refuses_the_intent_and_median_samplers():
    """``intent`` draws a side, not a token of a top-K set: GRPO's ratio would have no distribution to recompute."""
    with pytest.raises(ValueError, match="intent draws a side"):
        GRPOConfig(sampler="intent:0.25")
    with pytest.raises(ValueError, match="median decoding is deterministic"):  # the drop-in's default, not GRPO's
        GRPOConfig(sampler="median:0.1")
    assert GRPOConfig(sampler="topk:5").sampler == "topk:5"


def test_a_folder_listed_twice_is_opened_once_and_drawn_twice(tmp_path):
    """``extra_train_data`` listing a folder n times weights its scenes n times (DatasetSource joins the lists) while
    the folder is opened (read, tokenized) once; a different path to the same folder counts as the same folder."""
    from r1sim_sumo.train.grpo import DatasetSource, open_once

    (tmp_path / "ph").mkdir()
    (tmp_path / "rings").mkdir()
    opened = []

    def open_folder(k, folder):
        opened.append((k, folder))
        return [f"{Path(folder).name}{i}" for i in range(2)]

    folders = [str(tmp_path / "ph"), str(tmp_path / "rings"), str(tmp_path / "rings" / ".." / "ph")]
    parts = open_once(folders, open_folder)
    assert [k for k, _ in opened] == [0, 1]
    assert parts[0] is parts[2] and parts[0] is not parts[1]
    src = DatasetSource(["m0"], parts)
    assert len(src) == 7
    assert [src.scene(i) for i in range(7)] == ["m0", "ph0", "ph1", "rings0", "rings1", "ph0", "ph1"]
