"""Steady-history augmentation (r1sim_sumo.train.steady_history): speeding-up vehicles see a steady past."""

import math

import numpy as np
import pytest
import torch

from r1sim_sumo.model.packed import packed_loss
from r1sim_sumo.model.synthetic import synthetic_batch
from r1sim_sumo.tokens.constants import N_POSE, N_TOK, TOKEN_DT_S
from r1sim_sumo.train.steady_history import SPEED_STEP_MPS, steady_history, straight_token_table
from tests.test_fast_training import _jittered_batch, _model


def _vocab_traj():
    """Straight tokens at 0..40 m/s (1 m/s apart) and a few curved ones, ``[V, 6, 3]`` in the start-pose frame."""
    t = np.arange(6) * TOKEN_DT_S / 5
    rows = [np.stack([v * t, 0 * t, 0 * t], -1) for v in range(41)]
    rows += [np.stack([v * t, 0.3 * t**2, 0.1 * t], -1) for v in (5, 15, 25)]
    return np.asarray(rows, np.float32)


def test_straight_token_table_picks_the_constant_speed_tokens():
    table = straight_token_table(_vocab_traj())
    assert table[0] == 0 and table[round(10 / SPEED_STEP_MPS)] == 10 and table[round(23.4 / SPEED_STEP_MPS)] == 23
    assert int(table.max()) <= 40  # never a curved token


def _scene(speeds_per_agent, desired):
    """One scene, agents driving along +x at the given per-token speeds [m/s]; poses integrate the speeds."""
    A = len(speeds_per_agent)
    b = synthetic_batch([torch.as_tensor(_vocab_traj())] * 3, num_scenes=1, num_agents=A, num_map_tokens=20, seed=0)
    xy = torch.zeros(1, A, N_POSE, 2)
    for a, sp in enumerate(speeds_per_agent):
        xy[0, a, 1:, 0] = torch.cumsum(torch.as_tensor(sp, dtype=torch.float32) * TOKEN_DT_S, 0)
        xy[0, a, :, 1] = 4.0 * a
    tok = torch.full((1, A, N_TOK), 7, dtype=torch.long)
    return b._replace(pose_xy=xy, pose_yaw=torch.zeros(1, A, N_POSE), pose_valid=torch.ones(1, A, N_POSE, dtype=torch.bool),
                      agent_token=tok, agent_token_valid=torch.ones(1, A, N_TOK, dtype=torch.bool),
                      agent_type=torch.zeros(1, A, dtype=torch.long), agent_mask=torch.ones(1, A, dtype=torch.bool),
                      agent_desired_speed=torch.as_tensor([desired], dtype=torch.float32))


def test_a_speeding_up_vehicle_gets_a_steady_straight_past_and_its_labels_there_are_ignored():
    accel = [8.0] * 6 + [8.0 + 0.5 * k for k in range(1, 13)]  # steady, then +1 m/s^2 from token 6 on
    steady = [10.0] * N_TOK
    slow_dream = list(accel)  # speeds up too, but its desired speed is already reached
    b = _scene([accel, steady, slow_dream], desired=[30.0, 30.0, 8.5])
    table = straight_token_table(_vocab_traj())
    out, labels = steady_history(b, None, 1.0, torch.Generator().manual_seed(0), table)
    changed = (out.pose_xy != b.pose_xy).any(-1).any(-1)[0]
    assert changed.tolist() == [True, False, False]
    ignored = (labels[0, 0] < 0).nonzero().flatten()
    t0 = int(ignored.max()) + 1
    assert ignored.tolist() == list(range(t0))  # exactly the steps before t0
    assert 6 <= t0 <= N_TOK - 1
    v = accel[t0 - 1]
    # poses before t0: straight along the heading at t0, 0.5 s * v apart, ending at the real pose t0
    for s in range(t0):
        assert out.pose_xy[0, 0, s, 0] == pytest.approx(float(b.pose_xy[0, 0, t0, 0]) - (t0 - s) * TOKEN_DT_S * v, abs=1e-4)
        assert out.pose_xy[0, 0, s, 1] == pytest.approx(0.0, abs=1e-5)
    assert torch.equal(out.pose_xy[0, 0, t0:], b.pose_xy[0, 0, t0:])  # the real pose t0 and the future stay
    assert out.agent_token[0, 0, :t0].tolist() == [int(table[round(v / SPEED_STEP_MPS)])] * t0
    assert torch.equal(labels[0, 0, t0:], b.agent_token[0, 0, t0:])  # labels from t0 on: the real tokens
    assert torch.equal(labels[0, 1:], b.agent_token[0, 1:])
    # deterministic for a generator state, nothing drawn when off
    again, _ = steady_history(b, None, 1.0, torch.Generator().manual_seed(0), table)
    assert torch.equal(again.pose_xy, out.pose_xy)
    g = torch.Generator().manual_seed(3)
    before = g.get_state()
    same, tg = steady_history(b, None, 0.0, g, table)
    assert same is b and tg is None and torch.equal(g.get_state(), before)


def test_at_rewrites_only_vehicles_speeding_up_at_that_step_and_keeps_the_reference():
    """GRPO's steady start (``at=CURRENT_POSE``): a vehicle whose reference speeds up at the first rolled-out token gets a
    steady past ending at its real current pose; one that speeds up later, or not at all, keeps its logged past."""
    from r1sim_sumo.tokens.constants import CURRENT_POSE

    at = CURRENT_POSE
    now = [8.0] * at + [8.0 + 0.5 * k for k in range(1, N_TOK - at + 1)]  # speeds up from token `at` on
    later = [8.0] * 8 + [8.0 + 0.5 * k for k in range(1, N_TOK - 8 + 1)]  # speeds up from token 8 on
    steady = [10.0] * N_TOK
    b = _scene([now, later, steady], desired=[30.0, 30.0, 30.0])
    table = straight_token_table(_vocab_traj())
    out, labels = steady_history(b, None, 1.0, torch.Generator().manual_seed(0), table, at=at)
    assert not torch.equal(out.agent_token[0, 0, :at], b.agent_token[0, 0, :at])  # rewritten to straight tokens
    assert out.agent_token[0, 0, :at].tolist() == [int(table[round(now[at - 1] / SPEED_STEP_MPS)])] * at
    assert torch.equal(out.agent_token[0, 1:], b.agent_token[0, 1:]) and torch.equal(out.pose_xy[0, 1:], b.pose_xy[0, 1:])
    assert torch.equal(out.pose_xy[0, 0, at:], b.pose_xy[0, 0, at:])  # the current pose and the reference future stay
    assert (labels[0, 0] < 0).nonzero().flatten().tolist() == list(range(at))
    # without `at`, the later vehicle would be rewritten too
    free, _ = steady_history(b, None, 1.0, torch.Generator().manual_seed(0), table)
    assert not torch.equal(free.pose_xy[0, 1], b.pose_xy[0, 1])
    with pytest.raises(ValueError, match="at=0"):
        steady_history(b, None, 1.0, torch.Generator().manual_seed(0), table, at=0)


def test_min_run_skips_single_speed_ups_that_revert():
    """``min_run=2``: a vehicle whose speed goes up for one token and back (dawdling noise around a held speed) keeps its
    logged past; one that speeds up for two tokens and more still gets a steady past before the run's first token."""
    blip = [10.0] * 6 + [10.6, 10.0] + [10.0] * (N_TOK - 8)  # one token up, then back
    run = [8.0] * 6 + [8.0 + 0.5 * k for k in range(1, N_TOK - 6 + 1)]  # up from token 6 on, every token
    b = _scene([blip, run], desired=[30.0, 30.0])
    table = straight_token_table(_vocab_traj())
    single, single_labels = steady_history(b, None, 1.0, torch.Generator().manual_seed(0), table)
    assert (single_labels[0, 0] < 0).any()  # min_run 1: the blip counts as a speed-up (its past relabelled steady)
    out, labels = steady_history(b, None, 1.0, torch.Generator().manual_seed(0), table, min_run=2)
    assert torch.equal(out.agent_token[0, 0], b.agent_token[0, 0]) and torch.equal(labels[0, 0], b.agent_token[0, 0])
    assert (labels[0, 1] < 0).any()  # the sustained one is rewritten
    t0 = int((labels[0, 1] < 0).nonzero().flatten().max()) + 1
    assert 6 <= t0 <= N_TOK - 2  # the run's first token, with a second speed-up after it inside the window
    too_long, long_labels = steady_history(b, None, 1.0, torch.Generator().manual_seed(0), table, min_run=N_TOK)
    assert too_long is b and long_labels is None  # no run that long fits in the window: the batch comes back as it was


def test_ignored_labels_leave_the_padded_and_packed_losses_equal():
    model, voc = _model()
    b = _jittered_batch(voc)
    targets = b.agent_token.clone()
    with torch.no_grad():
        assert math.isclose(float(packed_loss(model, b, targets=targets)[0]), float(packed_loss(model, b)[0]), rel_tol=1e-6)
    targets[:, :, :5] = -1
    fast, _ = packed_loss(model, b, targets=targets)
    ref, _ = model.loss(b, model(b), targets=targets)
    assert torch.isfinite(fast) and abs(float(fast) - float(ref)) < 1e-5
    assert abs(float(fast) - float(packed_loss(model, b)[0])) > 1e-4  # the ignored labels are really left out
