"""Safety filter geometry and Krauss safe speed (pure numpy, no SUMO)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from r1sim_sumo.sim.safety_filter import SafetyFilter, path_arc_length, path_curvature, point_along

F = SafetyFilter()


def _scene(rows):
    """rows of (x, y, yaw, speed) for 4.5 x 1.8 m cars -> state arrays."""
    a = np.asarray(rows, np.float64)
    n = len(a)
    return a[:, 0], a[:, 1], a[:, 2], np.full(n, 4.5), np.full(n, 1.8), a[:, 3]


def test_leader_is_the_nearest_box_ahead_in_the_corridor():
    # ego at 0; same lane 30 m ahead; same lane 60 m ahead; adjacent lane (3.5 m left) 10 m ahead; behind 10 m
    x, y, yaw, ln, wd, v = _scene([(0, 0, 0, 30), (30, 0, 0, 20), (60, 0, 0, 10), (10, 3.5, 0, 5), (-10, 0, 0, 40)])
    gap, vl, lead = F.leader_gap(np.array([0]), x, y, yaw, ln, wd, v)
    assert lead[0] == 1 and math.isclose(gap[0], 30 - 4.5, abs_tol=1e-9) and math.isclose(vl[0], 20.0)
    # nothing ahead of the front car within its look-ahead (max(20 m, 10 m/s x 4 s) = 40 m)
    gap, _, lead = F.leader_gap(np.array([2]), x, y, yaw, ln, wd, v)
    assert lead[0] == -1 and np.isinf(gap[0])


def test_a_crossing_car_ahead_counts_with_its_length_across_and_zero_speed_along():
    x, y, yaw, ln, wd, v = _scene([(0, 0, 0, 10), (15, 1.0, math.pi / 2, 10)])
    gap, vl, lead = F.leader_gap(np.array([0]), x, y, yaw, ln, wd, v)
    assert lead[0] == 1 and math.isclose(gap[0], 15 - 2.25 - 0.9, abs_tol=1e-9) and vl[0] < 1e-9


def test_curved_corridor_follows_the_plan():
    # on a left curve of radius 20 m a car 15 m along the arc sits ~5.6 m to the left of the ego's heading line
    R, s = 20.0, 15.0
    px, py = R * math.sin(s / R), R * (1 - math.cos(s / R))
    x, y, yaw, ln, wd, v = _scene([(0, 0, 0, 8), (px, py, s / R, 8)])
    _, _, straight = F.leader_gap(np.array([0]), x, y, yaw, ln, wd, v)
    _, _, curved = F.leader_gap(np.array([0]), x, y, yaw, ln, wd, v, kappa=np.array([1 / R]))
    assert straight[0] == -1 and curved[0] == 1


def test_a_queue_on_the_other_lane_of_a_two_way_road_is_not_a_leader():
    # ego heading east on the right-hand lane; a car standing 20 m ahead on the opposite lane (3.5 m to the left,
    # heading west). With the plan bending left (leaving a roundabout) the widened corridor reaches that lane; an
    # oncoming car there is no leader (session 31: such queues braked every vehicle leaving the bundled roundabout).
    x, y, yaw, ln, wd, v = _scene([(0, 0, 0, 12), (20, 3.5, math.pi, 0)])
    kappa = np.array([0.01])  # 100 m radius: the arc is 2 m to the left at 20 m
    assert F._corridor_gap(np.array([0]), np.array([1]), x, y, yaw, ln, wd, v, kappa)[1][0] == False  # noqa: E712
    gap, _, lead = F.leader_gap(np.array([0]), x, y, yaw, ln, wd, v, kappa=kappa)
    assert lead[0] == -1 and np.isinf(gap[0])
    # the same car heading east (a slow leader on the other lane of a one-way road) is still in the bent corridor
    x, y, yaw, ln, wd, v = _scene([(0, 0, 0, 12), (20, 3.5, 0.0, 0)])
    assert F.leader_gap(np.array([0]), x, y, yaw, ln, wd, v, kappa=kappa)[2][0] == 1
    # head-on in the ego's own lane it is a standing leader, with no speed along the ego's heading
    x, y, yaw, ln, wd, v = _scene([(0, 0, 0, 12), (20, 0.5, math.pi, 3)])
    gap, vl, lead = F.leader_gap(np.array([0]), x, y, yaw, ln, wd, v, kappa=kappa)
    assert lead[0] == 1 and math.isclose(gap[0], 20 - 4.5, abs_tol=1e-9) and vl[0] == 0.0


def test_krauss_safe_speed_and_limits():
    # at the Krauss equilibrium gap (v * tau + min gap) the safe speed is the leader's speed
    v = 20.0
    vs = F.safe_speed(np.array([v]), np.array([v * F.tau_s + F.min_gap_m]), np.array([v]))
    assert math.isclose(vs[0], v, rel_tol=1e-9)
    assert F.safe_speed(np.array([20.0]), np.array([np.inf]), np.array([0.0]))[0] == np.inf
    assert F.safe_speed(np.array([20.0]), np.array([1.0]), np.array([0.0]))[0] == 0.0  # inside the standstill gap
    # the filter never speeds up the plan and never brakes harder than the emergency deceleration per step
    out = F.limit(np.array([25.0, 25.0, 10.0]), np.array([25.0, 25.0, 10.0]), np.array([0.0, 24.5, 30.0]), 0.1)
    np.testing.assert_allclose(out, [25.0 - 0.9, 24.5, 10.0])


def test_point_along_a_plan_and_its_curvature():
    t = np.arange(6) * 0.1
    xy = np.stack([10 * t, np.zeros(6)], -1)[None]  # [1, 6, 2] straight at 10 m/s
    yaw = np.zeros((1, 6))
    arc = path_arc_length(xy)
    np.testing.assert_allclose(arc[0], 10 * t)
    p, a = point_along(xy, yaw, arc, np.array([2.5]))
    np.testing.assert_allclose(p[0], [2.5, 0.0]) and np.testing.assert_allclose(a, [0.0])
    p, _ = point_along(xy, yaw, arc, np.array([99.0]))  # clipped to the end of the plan
    np.testing.assert_allclose(p[0], [5.0, 0.0])
    assert path_curvature(yaw, arc)[0] == 0.0
    turn = np.linspace(0, 0.25, 6)[None]  # 0.25 rad over 5 m
    assert math.isclose(path_curvature(turn, arc)[0], 0.05, rel_tol=1e-9)


@pytest.mark.parametrize("curved", [False, True])
def test_tree_candidates_find_the_same_leaders_as_every_pair(monkeypatch, curved):
    import r1sim_sumo.sim.safety_filter as sfm

    rng = np.random.default_rng(3)
    n = 400  # a dense city: boxes of cars, trucks and buses in 300 m x 300 m, some touching, random headings
    x, y = rng.uniform(0, 300, n), rng.uniform(0, 300, n)
    yaw = rng.uniform(-np.pi, np.pi, n)
    ln = rng.choice([4.6, 12.0, 18.0], n)
    wd = rng.choice([1.8, 2.5], n)
    v = rng.uniform(0, 30, n)
    ego = rng.choice(n, 250, replace=False)
    kappa = rng.normal(0, 0.05, len(ego)) if curved else None
    F = SafetyFilter()
    monkeypatch.setattr(sfm, "TREE_MIN_PAIRS", 10**12)
    dense = F.leader_gap(ego, x, y, yaw, ln, wd, v, kappa)
    monkeypatch.setattr(sfm, "TREE_MIN_PAIRS", 1)
    tree = F.leader_gap(ego, x, y, yaw, ln, wd, v, kappa)
    assert (dense[2] >= 0).sum() > 50  # many egos have a leader
    for a, b in zip(dense, tree, strict=True):
        np.testing.assert_array_equal(a, b)
