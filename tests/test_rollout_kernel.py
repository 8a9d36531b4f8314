"""The shared simulation kernel (r1sim_sumo.rollout.kernel): the engine on it reproduces the pre-refactor engine,
the SUMO and highway-env hosts follow a plan the same way, and the follower's rules hold."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from fixtures.rollout_kernel.record_engine_reference import FIELDS, reference_rollouts, reference_setup

from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.kernel import (
    LoopState,
    PlanFollower,
    StepRecorder,
    decode_frames,
    token_frames,
    token_step,
)
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.tokens.constants import CURRENT_POSE
from r1sim_sumo.tokens.matching import advance_pose

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "rollout_kernel"


@pytest.fixture(scope="module")
def setup():
    return reference_setup()


def test_engine_on_the_kernel_reproduces_the_recorded_rollouts(setup):
    """Tokens, log-probs, poses, 10 Hz states and validity equal what the engine gave before it ran on the kernel
    (recorded at c853185 by ``record_engine_reference.py``), with log replay and with greedy sampling.

    Tokens, K, poses, states and masks must be identical; the log-probabilities and entropies are float32 sums over
    the vocabulary, whose last bits depend on the CPU's vector width (the reference was recorded on an AVX2 machine;
    an AVX-512 one differs by ~2e-6), so those are compared to 1e-5 with the same non-finite pattern."""
    ref = torch.load(FIXTURES / "engine_reference.pt", weights_only=True)
    now = reference_rollouts(*setup)
    assert set(now) == set(ref)
    for key in sorted(ref):
        assert now[key].dtype == ref[key].dtype and now[key].shape == ref[key].shape, key
        if key.rsplit("/", 1)[-1] in ("entropy", "logp", "logp_full"):
            torch.testing.assert_close(now[key], ref[key], atol=1e-5, rtol=0, equal_nan=True, msg=key)
        else:
            assert torch.equal(now[key], ref[key]), key
    assert (ref["entropy_replay/token"] == -1).any() and (ref["entropy_replay/token"] >= 0).any()
    assert len(FIELDS) == 11


def test_host_mask_invalidates_from_the_step_on(setup):
    """An agent the host reports gone gets token -1 from that step, keeps its pose, and never comes back."""
    vocab, model, batch, _ = setup
    S, A = batch.agent_mask.shape
    drive = batch.pose_valid[:, :, CURRENT_POSE].bool() & batch.agent_mask.bool()
    gone_at, victim = CURRENT_POSE + 1, int(torch.nonzero(drive[0])[0])
    calls = []

    def host(st, tok, nxt_valid):
        assert torch.equal(st.xy, state.xy)  # the pose before the step
        calls.append(tok.clone())
        alive = torch.ones_like(nxt_valid)
        if len(calls) - 1 + CURRENT_POSE >= gone_at:
            alive[0, victim] = False
        return alive

    cache = model.init_rollout(batch, num_rollouts=1, upto_step=CURRENT_POSE)
    gt_tok = torch.where(batch.agent_token_valid.bool(), batch.agent_token, -1)
    state = LoopState(gt_tok[:, :, CURRENT_POSE - 1], batch.pose_xy[:, :, CURRENT_POSE], batch.pose_yaw[:, :, CURRENT_POSE],
                      drive.clone())
    rec = StepRecorder(state)
    atype = batch.agent_type.long()
    gen = torch.Generator().manual_seed(0)
    for k in range(CURRENT_POSE, CURRENT_POSE + 4):
        step = token_step(model, cache, k, state, parse_sampler("topk:8"), gen, vocab, atype, drive, host=host)
        rec.append(step)
        state = step.state
    out = rec.stack(vocab, atype)
    assert len(calls) == 4
    assert (out["token"][0, victim, :1] >= 0).all() and (out["token"][0, victim, 1:] == -1).all()
    assert out["valid"][0, victim, 1] and not out["valid"][0, victim, 2:].any()
    assert torch.equal(out["pose_xy"][0, victim, 2], out["pose_xy"][0, victim, 3])  # frozen where it vanished
    others = drive.clone()
    others[0, victim] = False
    assert out["valid"][others].all() and (out["token"][others] >= 0).all()
    # the 10 Hz states hit the boundary poses of the token chain
    v = out["valid"]
    torch.testing.assert_close(out["xy_10hz"][..., ::5, :][v], out["pose_xy"][v], atol=1e-3, rtol=0)


def test_token_frames_end_at_the_next_boundary_pose(setup):
    vocab, _, batch, _ = setup
    xy, yaw = batch.pose_xy[:, :, CURRENT_POSE].double(), batch.pose_yaw[:, :, CURRENT_POSE].double()
    tok = torch.randint(0, 32, xy.shape[:2], generator=torch.Generator().manual_seed(0))
    atype = batch.agent_type.long()
    fxy, fyaw = token_frames(xy, yaw, tok, vocab, atype)
    assert fxy.shape == (*xy.shape[:2], 6, 2) and fyaw.shape == (*xy.shape[:2], 6)
    assert torch.equal(fxy[..., 0, :], xy)
    nxy, nyaw = advance_pose(xy, yaw, tok, vocab, atype)
    torch.testing.assert_close(fxy[..., -1, :], nxy, atol=1e-9, rtol=0)


def test_central_decoding_keeps_the_path_and_starts_at_the_mean_of_two_token_speeds(setup):
    """``central``: same end pose as the token, frames on the token's path, one constant acceleration starting at the
    mean of the previous and the current token's mean speeds; ``tokens`` is the token's own frames."""
    vocab, _, batch, _ = setup
    xy, yaw = batch.pose_xy[:, :, CURRENT_POSE].double(), batch.pose_yaw[:, :, CURRENT_POSE].double()
    gen = torch.Generator().manual_seed(0)
    tok = torch.randint(0, 32, xy.shape[:2], generator=gen)
    prev = torch.randint(0, 32, xy.shape[:2], generator=gen)
    prev[0, 0] = -1
    atype = batch.agent_type.long()
    own = token_frames(xy, yaw, tok, vocab, atype)
    same = decode_frames(xy, yaw, prev, tok, vocab, atype, "tokens")
    assert torch.equal(own[0], same[0]) and torch.equal(own[1], same[1])
    cxy, cyaw = decode_frames(xy, yaw, prev, tok, vocab, atype, "central")
    torch.testing.assert_close(cxy[..., [0, -1], :], own[0][..., [0, -1], :], atol=1e-9, rtol=0)
    step = torch.linalg.norm(cxy.diff(dim=-2), dim=-1)  # [S, A, 5] [m per 0.1 s]
    L = torch.linalg.norm(own[0].diff(dim=-2), dim=-1).sum(-1)
    Lp = torch.linalg.norm(token_frames(xy, yaw, prev, vocab, atype)[0].diff(dim=-2), dim=-1).sum(-1)
    Lp = torch.where(prev >= 0, Lp, L)
    moving = (L > 0.5) & (Lp < 2.5 * L)  # no stop profile: a constant acceleration from (Lp + L) / 2 per 0.5 s
    v0 = (Lp + L) / 2 / 0.5
    a = 2 * (L - v0 * 0.5) / 0.25
    t = torch.arange(6, dtype=torch.float64) * 0.1
    s = v0[..., None] * t + 0.5 * a[..., None] * t * t
    assert moving.sum() > 4
    torch.testing.assert_close(step.cumsum(-1)[moving], s[..., 1:][moving], atol=2e-2, rtol=0)  # chord vs arc on curves
    assert (step[0, 0].std() < 1e-6) or L[0, 0] < 0.5  # no previous token: constant speed
    with pytest.raises(ValueError, match="decoding"):
        decode_frames(xy, yaw, prev, tok, vocab, atype, "spline")


def test_engine_decodings_share_tokens_and_boundary_poses(setup):
    vocab, model, batch, _ = setup
    r = {d: rollout(model, vocab, batch, num_rollouts=2, sampler=parse_sampler("topk:5"),
                    generator=torch.Generator().manual_seed(3), decoding=d) for d in ("tokens", "central")}
    assert torch.equal(r["tokens"].token, r["central"].token) and torch.equal(r["tokens"].pose_xy, r["central"].pose_xy)
    v = r["central"].valid
    torch.testing.assert_close(r["central"].xy_10hz[..., ::5, :][v], r["central"].pose_xy[v], atol=1e-3, rtol=0)
    assert not torch.allclose(r["tokens"].xy_10hz, r["central"].xy_10hz, atol=1e-3)


# ---------------------------------------------------------------------------- plan following


def _plan(n=1, speed=10.0, curve=0.0):
    """``n`` plans of 6 frames at 10 Hz from the origin heading east (optionally turning ``curve`` rad per frame)."""
    yaw = np.cumsum(np.full((n, 6), curve), 1) - curve
    step = speed * 0.1
    xy = np.zeros((n, 6, 2))
    for f in range(1, 6):
        xy[:, f] = xy[:, f - 1] + step * np.stack([np.cos(yaw[:, f - 1]), np.sin(yaw[:, f - 1])], -1)
    return xy, yaw


def test_follower_on_time_lands_exactly_on_the_frames():
    f = PlanFollower(4)
    xy, yaw = _plan(2, speed=12.0, curve=0.05)
    f.set_plans(np.array([3, 1]), xy, yaw)
    for j in range(1, 6):
        out = f.follow(np.array([3, 1]), 0.1)
        np.testing.assert_array_equal(out.xy, xy[:, j])
        np.testing.assert_array_equal(out.yaw, yaw[:, j])
        np.testing.assert_allclose(out.speed, 12.0, rtol=1e-9)
        assert not out.slowed.any()


def test_follower_slowed_lags_by_distance_until_a_new_plan():
    f = PlanFollower(1)
    xy, yaw = _plan(1, speed=10.0)
    f.set_plans([0], xy, yaw)
    f.follow([0], 0.1)  # frame 1 (1 m)
    out = f.follow([0], 0.1, v_allowed=np.array([4.0]))  # 0.4 m instead of 1 m
    assert out.slowed[0] and out.speed[0] == pytest.approx(4.0)
    np.testing.assert_allclose(out.xy[0], [1.4, 0.0])
    out = f.follow([0], 0.1, v_allowed=np.array([100.0]))  # free again: drives the plan's speed, still behind the clock
    assert not out.slowed[0]
    np.testing.assert_allclose(out.xy[0], [2.4, 0.0])
    f.set_plans([0], xy + [5.0, 0.0], yaw)  # a new plan restarts on its clock
    np.testing.assert_allclose(f.follow([0], 0.1).xy[0], [6.0, 0.0])


def test_follower_floor_runs_ahead_of_a_plan_that_brakes_too_hard():
    """``v_min``: a plan slower than the floor is driven at the floor, along its path and past its end; a plan that
    stands still (a path without length) is left along its heading."""
    f = PlanFollower(2)
    xy, yaw = _plan(2, speed=10.0)
    xy[1] = xy[1, :1]  # slot 1 plans to stand still at once, heading 0 (+x)
    f.set_plans([0, 1], xy, yaw)
    out = f.follow([0, 1], 0.1, v_allowed=np.array([100.0, 100.0]), v_min=np.array([12.0, 9.5]))
    np.testing.assert_allclose(out.speed, [12.0, 9.5])
    np.testing.assert_allclose(out.xy, [xy[0, 0] + [1.2, 0.0], xy[1, 0] + [0.95, 0.0]], atol=1e-9)
    assert not out.slowed.any()
    for _ in range(5):  # past the plan's last frame (5 m for slot 0): on along its last segment
        out = f.follow([0, 1], 0.1, v_min=np.array([12.0, 0.0]))
    np.testing.assert_allclose(out.xy[0], xy[0, 0] + [7.2, 0.0], atol=1e-9)
    np.testing.assert_allclose(out.xy[1], xy[1, 0] + [0.95, 0.0], atol=1e-9)  # floor 0: the plan's standstill


def test_sumo_and_highway_hosts_follow_a_plan_the_same_way():
    """Same plan, same sequence of allowed speeds -> the same positions, headings and speeds from the SUMO controller's
    and the highway-env coordinator's plan following (``SumoController._follow`` / ``LearnedTrafficCoordinator._follow``,
    the step after each host's own safety layer), read back into the internal frame."""
    pytest.importorskip("highway_env")
    from r1sim_sumo.adapters.highway_state import internal_to_highway_state
    from r1sim_sumo.sim.highway_vehicle import CoordinatorStats, LearnedTrafficCoordinator
    from r1sim_sumo.sim.sumo_controller import ControllerStats, SumoController

    xy, yaw = _plan(2, speed=15.0, curve=0.03)
    xy[1] += [30.0, 4.0]
    caps = [np.array(c) for c in ([np.inf, 20.0], [9.0, 14.0], [3.0, np.inf], [np.inf, 2.0], [20.0, np.inf])]
    sumo = SimpleNamespace(follower=PlanFollower(8), stats=ControllerStats())
    sumo.follower.set_plans([5, 2], xy, yaw)
    hw = SimpleNamespace(follower=PlanFollower(2), stats=CoordinatorStats())
    hw.follower.set_plans([0, 1], xy, yaw)
    cars = [SimpleNamespace(position=None, heading=None, speed=None, lane_index=None, on_state_update=lambda: None)
            for _ in range(2)]
    for cap in caps:
        a = SumoController._follow(sumo, np.array([5, 2]), cap)
        b = LearnedTrafficCoordinator._follow(hw, cars, np.array([0, 1]), 0.1, cap)
        np.testing.assert_array_equal(a.xy, b.xy)
        np.testing.assert_array_equal(a.yaw, b.yaw)
        np.testing.assert_array_equal(a.speed, b.speed)
        expect = internal_to_highway_state(a.xy[:, 0], a.xy[:, 1], a.yaw, a.speed)  # what highway-env's cars show
        for j, car in enumerate(cars):
            np.testing.assert_allclose(car.position, expect.position_m[j], atol=1e-12)
            assert car.heading == pytest.approx(float(expect.heading_rad[j])) and car.speed == pytest.approx(a.speed[j])
    assert sumo.stats.safety_slowdowns == hw.stats.safety_slowdowns == 4  # 9, 3 (car 0); 14, 2 (car 1) < 15 m/s
    # the slowed cars lag behind their plans' timing: car 0 drove 1.5 + 0.9 + 0.3 + 1.5 + 1.5 m of the plan's 7.5 m
    np.testing.assert_allclose(sumo.follower.prog_m[5], 5.7, atol=1e-9)


def test_highway_rates_that_do_not_divide_half_a_second_extrapolate_the_last_segment():
    """At 15 Hz the coordinator re-plans at the first step past 0.5 s: the follower goes on along the last segment."""
    f = PlanFollower(1)
    xy, yaw = _plan(1, speed=12.0)
    f.set_plans([0], xy, yaw)
    for _ in range(8):  # 8 / 15 s = 0.533 s
        out = f.follow([0], 1.0 / 15.0)
    np.testing.assert_allclose(out.xy[0], [12.0 * 8 / 15, 0.0], atol=1e-9)
    np.testing.assert_allclose(out.speed, 12.0)
