"""Realism metrics: SAT collisions, box distance, TTC, offroad, kinematics, likelihoods, RMM ordering."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("shapely")
pytest.importorskip("scipy")

from r1sim_sumo.metrics import (  # noqa: E402
    SimTrajectories,
    aggregate,
    collision_flags,
    compute_features,
    compute_realism,
    distance_to_road_edge,
    drivable_area,
    interaction_features,
    kinematic_features,
    offroad_flags,
    time_to_collision,
)
from r1sim_sumo.metrics.realism import bernoulli_log_likelihood, histogram_log_likelihood  # noqa: E402
from r1sim_sumo.metrics.types import HistogramSpec, MetricsInputError  # noqa: E402
from r1sim_sumo.scenario import (  # noqa: E402
    LANE_CENTRE,
    TL_GREEN,
    TL_RED,
    AgentTracks,
    MapPolylines,
    Scenario,
)

DT = 0.1
T_ALL = 91
CI = 10


@pytest.fixture(autouse=True)
def _one_thread():
    import torch

    torch.set_num_threads(1)


def straight_road(lanes: int = 2, width: float = 3.2, length: float = 400.0, tl_state=None) -> MapPolylines:
    """Eastbound lanes along +x starting at x = -100, lane k centred at y = k * width."""
    pls = [np.array([[-100.0, k * width], [length - 100.0, k * width]]) for k in range(lanes)]
    return MapPolylines.from_lists(pls, [LANE_CENTRE] * lanes, [f"l{k}" for k in range(lanes)], [30.0] * lanes,
                                   [width] * lanes, tl_state=tl_state)


def make_scene(x, y, yaw, valid, mp: MapPolylines, length=4.5, width=1.8) -> Scenario:
    x, y, yaw = (np.asarray(a, np.float32) for a in (x, y, yaw))
    A = x.shape[0]
    tr = AgentTracks.empty(A, x.shape[1])
    tr.x_m, tr.y_m, tr.yaw_rad = x, y, yaw
    tr.valid = np.asarray(valid, bool)
    tr.length_m = np.full(A, length, np.float32)
    tr.width_m = np.full(A, width, np.float32)
    sp = np.zeros_like(x)
    sp[:, 1:] = np.hypot(np.diff(x, axis=1), np.diff(y, axis=1)) / DT
    tr.speed_mps = sp
    return Scenario(agents=tr, map=mp, metadata={"source": "test"}).validate()


def boxes(x, y, yaw, length=4.5, width=1.8):
    """[1, A, T] arrays + sizes [A] for the pairwise functions."""
    x, y, yaw = (np.asarray(a, np.float64)[None] for a in (x, y, yaw))
    A = x.shape[1]
    return x, y, yaw, np.full(A, length), np.full(A, width), np.ones(x.shape, bool)


# ---------------------------------------------------------------------------- collisions


def test_collision_only_at_known_step_and_invalid_ignored():
    T = 12
    x = np.stack([np.full(T, 50.0), np.full(T, 60.0), np.full(T, 50.0)])  # [3, T]
    x[1, 5] = 52.0  # centres 2 m apart (< 4.5 m length): overlap at step 5 only
    y, yaw = np.zeros((3, T)), np.zeros((3, T))
    args = list(boxes(x, y, yaw))
    args[-1][0, 2] = False  # agent 2 sits on agent 0 all the time but is invalid
    col = collision_flags(*args)
    assert col.shape == (1, 3, T)
    assert col[0, 0].tolist() == [t == 5 for t in range(T)]
    assert col[0, 1].tolist() == [t == 5 for t in range(T)]
    assert not col[0, 2].any()
    # make agent 2 valid: agent 0 and 2 collide at every step
    args[-1][0, 2] = True
    assert collision_flags(*args)[0, 0].all()


def test_plus_shaped_overlap_is_a_collision_with_negative_distance():
    # two long thin boxes crossing at their centres: no corner lies inside the other box
    x, y, yaw, L, W, v = boxes([[0.0], [0.0]], [[0.0], [0.0]], [[0.0], [math.pi / 2]], length=10.0, width=1.0)
    f = interaction_features(x, y, yaw, L, W, v, box_shape="sharp")
    assert f.collision[0, :, 0].all()
    # penetration depth = the minimum translation separating them: half long side + half thin side
    assert f.distance_m[0, 0, 0] == pytest.approx(-5.5, abs=1e-9)
    # shifted along x by 5 m the crossing bar still overlaps by 0.5 m
    f2 = interaction_features(x + np.array([0.0, 5.0])[None, :, None], y, yaw, L, W, v, box_shape="sharp")
    assert f2.collision.all() and f2.distance_m[0, 0, 0] == pytest.approx(-0.5, abs=1e-9)
    # rounded (WOSAC): shrunk by s = 0.35 m per side, depth of the shrunk bars (4.65 + 0.15) plus 2 s
    r = interaction_features(x, y, yaw, L, W, v)
    assert r.collision[0, :, 0].all() and r.distance_m[0, 0, 0] == pytest.approx(-(4.65 + 0.15) - 0.7, abs=1e-9)
    # 0.5 m of sharp overlap is 0.5 - 2 * 0.35 * (1 - ...) : the rounded bars (thin side 1 m) still overlap by 0.5 m
    r2 = interaction_features(x + np.array([0.0, 5.0])[None, :, None], y, yaw, L, W, v)
    assert r2.distance_m[0, 0, 0] == pytest.approx(-0.5, abs=1e-9)


def test_box_distance_separated_aligned_and_rotated():
    # aligned boxes on the x axis, 3 m bumper gap
    x, y, yaw, L, W, v = boxes([[0.0], [7.5]], [[0.0], [0.0]], [[0.0], [0.0]], length=4.5, width=1.8)
    d = interaction_features(x, y, yaw, L, W, v).distance_m
    assert d[0, 0, 0] == pytest.approx(3.0) and d[0, 1, 0] == pytest.approx(3.0)  # flat faces: rounding changes nothing
    # a 2x2 square rotated 45 deg, corner pointing at an axis-aligned square's face 1 m away
    c = 1.0 + math.sqrt(2.0) + 1.0  # face at x=1, corner at x = c - sqrt(2)
    x, y, yaw, L, W, v = boxes([[0.0], [c]], [[0.0], [0.0]], [[0.0], [math.pi / 4]], length=2.0, width=2.0)
    f = interaction_features(x, y, yaw, L, W, v, box_shape="sharp")
    assert f.distance_m[0, 0, 0] == pytest.approx(1.0, abs=1e-9)
    assert not f.collision.any()
    # rounded: the corner is a 0.7 m arc, sqrt(2) * 0.7 - 0.7 farther away
    r = interaction_features(x, y, yaw, L, W, v)
    assert r.distance_m[0, 0, 0] == pytest.approx(1.0 + 0.7 * (math.sqrt(2.0) - 1.0), abs=1e-9)


def test_rounded_boxes_match_shapely_rounded_rectangles_and_corner_touch_is_no_collision():
    """WOSAC rounds box corners (factor 0.7): distance vs shapely's buffered shrunk rectangles; two boxes whose sharp
    corners overlap slightly are a sharp (SAT) collision but not a rounded one."""
    import shapely

    from r1sim_sumo.geometry import box_corners

    rng = np.random.default_rng(5)
    R, A, T = 1, 5, 6
    x, y = rng.uniform(0, 15, (R, A, T)), rng.uniform(0, 6, (R, A, T))
    yaw = rng.uniform(-math.pi, math.pi, (R, A, T))
    L, W = rng.uniform(3.5, 6, A), rng.uniform(1.6, 2.4, A)
    v = np.ones((R, A, T), bool)
    d = interaction_features(x, y, yaw, L, W, v).distance_m
    s = 0.7 * np.minimum(L, W) / 2
    for t in range(T):
        polys = [shapely.Polygon(box_corners(x[0, i, t], y[0, i, t], yaw[0, i, t], L[i] - 2 * s[i], W[i] - 2 * s[i]))
                 .buffer(s[i], quad_segs=256) for i in range(A)]
        for i in range(A):
            want = min(shapely.distance(polys[i], polys[j]) for j in range(A) if j != i)
            if want > 0:
                assert d[0, i, t] == pytest.approx(want, abs=1e-4)
            else:
                assert d[0, i, t] <= 1e-9
    # corner to corner: boxes 4.5 x 1.8 diagonally offset so the sharp corners overlap by 5 cm each way
    x2, y2, yaw2, L2, W2, v2 = boxes([[0.0], [4.45]], [[0.0], [1.75]], [[0.0], [0.0]])
    assert interaction_features(x2, y2, yaw2, L2, W2, v2, box_shape="sharp").collision.all()
    rr = interaction_features(x2, y2, yaw2, L2, W2, v2)
    assert not rr.collision.any() and (rr.distance_m > 0).all()


def test_ttc_follower_and_stopped_leader():
    T = 3
    x = np.array([[0.0] * T, [30.0] * T, [30.0] * T])
    y = np.array([[0.0] * T, [0.0] * T, [3.5] * T])  # agent 2: beside the leader in the next lane
    yaw = np.zeros((3, T))
    args = boxes(x, y, yaw)
    speed = np.array([[10.0] * T, [0.0] * T, [0.0] * T])[None]
    ttc = time_to_collision(*args, speed_mps=speed)
    gap = 30.0 - 4.5
    assert ttc[0, 0, 0] == pytest.approx(gap / 10.0)
    assert ttc[0, 1, 0] == pytest.approx(5.0)  # nothing ahead of the leader
    # leader moving at 4 m/s: closing speed 6 m/s -> capped at 5 s since 25.5/6 = 4.25 < 5
    speed[0, 1] = 4.0
    assert time_to_collision(*args, speed_mps=speed)[0, 0, 0] == pytest.approx(gap / 6.0)
    # leader faster than the follower: gap opening -> 5 s
    speed[0, 1] = 12.0
    assert time_to_collision(*args, speed_mps=speed)[0, 0, 0] == pytest.approx(5.0)
    # remove the in-lane leader: the neighbour one lane over is not "ahead"
    args[-1][0, 1] = False
    speed[0, 1] = 0.0
    assert time_to_collision(*args, speed_mps=speed)[0, 0, 0] == pytest.approx(5.0)


def test_ttc_from_scenario_kinematics():
    t = np.arange(T_ALL) * DT
    x = np.stack([10.0 * t, np.full(T_ALL, 60.0)])  # follower 10 m/s, leader stopped 60 m ahead at t=0
    sc = make_scene(x, np.zeros((2, T_ALL)), np.zeros((2, T_ALL)), np.ones((2, T_ALL), bool), straight_road())
    sim = SimTrajectories.log_replay(sc, 1)
    f = compute_features(sc, sim.x_m, sim.y_m, sim.yaw_rad, sim.checked(sc).valid)
    k = 0  # first future step = scenario step 11, follower at x = 11 m
    expected = (60.0 - 11.0 - 4.5) / 10.0
    assert f.time_to_collision[0, 0, k] == pytest.approx(min(expected, 5.0), rel=1e-4)
    assert f.linear_speed[0, 0, k] == pytest.approx(10.0, rel=1e-4)


# ---------------------------------------------------------------------------- kinematics


def test_constant_acceleration_track():
    a, v0, w = 2.0, 3.0, 0.3
    t = np.arange(0, 30) * DT
    x = v0 * t + 0.5 * a * t**2
    yaw = ((w * t + math.pi) % (2 * math.pi)) - math.pi
    tt = t[2:]
    # central differences (WOSAC): exact speed at t for a constant acceleration; nothing past the last state
    k = kinematic_features(x, np.zeros_like(x), yaw, np.ones_like(x, bool), num_prefix=2, dt_s=DT)
    np.testing.assert_allclose(k.linear_speed[:-1], (v0 + a * tt)[:-1], rtol=1e-9)
    np.testing.assert_allclose(k.linear_acceleration[:-2], a, rtol=1e-6)
    np.testing.assert_allclose(k.angular_speed[:-1], w, rtol=1e-6)
    np.testing.assert_allclose(k.angular_acceleration[:-2], 0.0, atol=1e-6)
    assert k.speed_valid[:-1].all() and not k.speed_valid[-1] and np.isnan(k.linear_speed[-1])
    assert k.acceleration_valid[:-2].all() and not k.acceleration_valid[-2:].any() and np.isnan(k.linear_acceleration[-2:]).all()
    # backward differences (legacy option): the speed of the step just before
    kb = kinematic_features(x, np.zeros_like(x), yaw, np.ones_like(x, bool), num_prefix=2, dt_s=DT, differences="backward")
    np.testing.assert_allclose(kb.linear_speed, v0 + a * (tt - DT / 2), rtol=1e-9)
    np.testing.assert_allclose(kb.linear_acceleration, a, rtol=1e-6)
    np.testing.assert_allclose(kb.angular_speed, w, rtol=1e-6)
    np.testing.assert_allclose(kb.angular_acceleration, 0.0, atol=1e-6)
    assert kb.speed_valid.all() and kb.acceleration_valid.all()
    # backward: an invalid step invalidates the speed at it and after it, and the two accelerations around it
    valid = np.ones_like(x, bool)
    valid[10] = False
    k2 = kinematic_features(x, np.zeros_like(x), yaw, valid, num_prefix=2, dt_s=DT, differences="backward")
    assert not k2.speed_valid[8] and not k2.speed_valid[9] and k2.speed_valid[10]
    assert not k2.acceleration_valid[8:11].any() and k2.acceleration_valid[11]


def test_central_difference_validity_spans_two_and_four_steps():
    """WOSAC: a speed at t needs states t-1 and t+1; an acceleration needs the speeds at t-1 and t+1 (states t-2,
    t, t+2). One invalid state at index 10 of the (prefix + future) track knocks out speeds 9, 11 and accelerations
    8, 10, 12, and nothing else (backward differences would knock out speeds 10, 11 and accelerations 10-12)."""
    n = 20
    x = np.arange(n) * 1.0
    v = np.ones(n, bool)
    v[10] = False
    k = kinematic_features(x, np.zeros(n), np.zeros(n), v, num_prefix=2, dt_s=DT)
    bad_speed = {i - 2 for i in (9, 11)} | {n - 1 - 2}
    bad_acc = {i - 2 for i in (8, 10, 12)} | {n - 2 - 2, n - 1 - 2}
    assert {i for i in range(n - 2) if not k.speed_valid[i]} == bad_speed
    assert {i for i in range(n - 2) if not k.acceleration_valid[i]} == bad_acc
    ok = k.speed_valid
    np.testing.assert_allclose(k.linear_speed[ok], 10.0)
    assert np.isnan(k.linear_speed[~ok]).all()


# ---------------------------------------------------------------------------- map features


def test_offroad_straight_road_flagged_at_right_step():
    mp = straight_road()
    area = drivable_area(mp)
    assert drivable_area(mp) is area  # cached by content key
    T = 40
    x = 10.0 * np.arange(T) * DT
    y = np.where(np.arange(T) < 20, 0.0, -0.2 * (np.arange(T) - 19))  # drifts right from step 20
    args = boxes([x], [y], [np.zeros(T)])
    d = distance_to_road_edge(area, *args)
    off = offroad_flags(d)[0, 0]
    # outer corner y - 0.9 leaves the road edge y = -1.6 once y < -0.7: first at step 23 (y = -0.8)
    assert off.tolist() == [t >= 23 for t in range(T)]
    # centred in lane 0: the most off-road corner is 0.7 m inside the edge
    assert d[0, 0, 0] == pytest.approx(-0.7, abs=0.13)
    assert d[0, 0, 30] == pytest.approx(0.2 * 11 + 0.9 - 1.6, abs=0.13)  # corner 1.5 m outside


def test_red_light_violation_entering_red_via_lane():
    T_all = T_ALL
    # approach lane 0 (x in [-100, 50]) -> junction lane 1 (x in [50, 70]) -> exit lane 2
    pls = [np.array([[-100.0, 0.0], [50.0, 0.0]]), np.array([[50.0, 0.0], [70.0, 0.0]]),
           np.array([[70.0, 0.0], [300.0, 0.0]])]
    tl = np.zeros((3, T_all), np.int8)
    tl[0] = TL_RED
    tl[1] = TL_RED
    mp = MapPolylines.from_lists(pls, [LANE_CENTRE] * 3, ["a", ":j", "b"], [20.0] * 3, [3.2] * 3,
                                 tl_state=tl, successors=[(0, 1), (1, 2)])
    t = np.arange(T_all) * DT
    x = np.stack([20.0 + 10.0 * t, 20.0 + np.minimum(10.0 * t, 25.0), np.full(T_all, 200.0)])
    sc = make_scene(x, np.zeros((3, T_all)), np.zeros((3, T_all)), np.ones((3, T_all), bool), mp)
    sim = SimTrajectories.log_replay(sc, 1)
    f = compute_features(sc, sim.x_m, sim.y_m, sim.yaw_rad, sim.checked(sc).valid)
    assert f.tl_violation is not None
    runner = np.flatnonzero(f.tl_violation[0, 0])
    # scenario step s puts the centre at x = 20 + s: at the stop line x = 50 at s = 30 (tie between the
    # lanes' end/start vertices), past the approach lane's last vertex by more than 0.5 m at s = 31
    assert len(runner) == 1 and runner[0] + CI + 1 in (30, 31)
    assert not f.tl_violation[0, 1].any() and not f.tl_violation[0, 2].any()
    # with the junction lane green there is no violation
    tl2 = tl.copy()
    tl2[1] = TL_GREEN
    sc2 = make_scene(x, np.zeros((3, T_all)), np.zeros((3, T_all)), np.ones((3, T_all), bool), mp.with_tl_state(tl2))
    f2 = compute_features(sc2, sim.x_m, sim.y_m, sim.yaw_rad, sim.checked(sc2).valid)
    assert not f2.tl_violation.any()
    res = compute_realism(sc, sim, weights="2025")
    assert "traffic_light_violation" in res.likelihoods and res.tl_violation_rate == pytest.approx(1 / 3)


# ---------------------------------------------------------------------------- likelihoods and RMM


def test_histogram_and_bernoulli_estimators():
    spec = HistogramSpec(0.0, 10.0, 10)
    log = np.array([[2.5, 2.5, 7.5]])  # [A=1, T=3]
    same = np.repeat(log[None], 4, 0)  # [R=4, 1, 3]
    ll = histogram_log_likelihood(log, same, np.ones_like(same, bool), spec)
    # bin 2 holds 8 of 12 samples, bin 7 holds 4: (8 + 0.1) / (12 + 1), (4 + 0.1) / 13
    np.testing.assert_allclose(np.exp(ll[0]), [8.1 / 13, 8.1 / 13, 4.1 / 13])
    shifted = histogram_log_likelihood(log, same + 3.0, np.ones_like(same, bool), spec)
    assert shifted.mean() < ll.mean()
    flags = np.array([[True, False], [False, False]])
    b = bernoulli_log_likelihood(np.array([True, False]), flags, pseudocount=0.1)
    np.testing.assert_allclose(np.exp(b), [1.1 / 2.2, 2.1 / 2.2])


def test_smoothing_defaults_are_the_official_config_values():
    """WOSAC 2024/2025 configs: histogram features set additive_smoothing_pseudocount 0.1; the Bernoulli features
    (collision, offroad, traffic light) leave BernoulliEstimate's proto default, 0.001. Read from the configs' text
    here, not restated: the numbers below are the protos' (sim_agents_metrics.proto)."""
    from r1sim_sumo.metrics.realism import RealismConfig

    cfg = RealismConfig()
    assert cfg.histogram_pseudocount == 0.1 and cfg.bernoulli_pseudocount == 0.001
    assert RealismConfig.legacy().bernoulli_pseudocount == 0.1
    # the estimator's own default is the Bernoulli one
    b = bernoulli_log_likelihood(np.array([True]), np.array([[False]] * 4))
    assert np.exp(b)[0] == pytest.approx(0.001 / (4 + 0.002))


def test_collision_likelihood_uses_official_bernoulli_smoothing():
    """Every rollout collides, the log does not: likelihood = (0 + ps) / (R + 2 ps) of "no collision" with ps = 0.001
    (official), not 0.1 (legacy)."""
    from r1sim_sumo.metrics.realism import RealismConfig

    t = np.arange(T_ALL) * DT
    x = np.stack([10.0 * t, 10.0 * t + 20.0])  # two cars 20 m apart, no collision in the log
    sc = make_scene(x, np.zeros((2, T_ALL)), np.zeros((2, T_ALL)), np.ones((2, T_ALL), bool), straight_road())
    R = 4
    sim = SimTrajectories.log_replay(sc, R)
    xs = np.array(sim.x_m, np.float64)
    xs[:, 1] = xs[:, 0] + 1.0  # the second car sits on the first in every rollout
    crash = SimTrajectories(xs, sim.y_m, sim.yaw_rad, sim.valid)
    new = compute_realism(sc, crash).likelihoods["collision_indication"]
    old = compute_realism(sc, crash, config=RealismConfig.legacy()).likelihoods["collision_indication"]
    assert new == pytest.approx(0.001 / (R + 0.002), rel=1e-9)
    assert old == pytest.approx(0.1 / (R + 0.2), rel=1e-9)


def test_log_side_obstacles_are_only_the_sim_agents():
    """Issue 16 item 1: a car replayed exactly; a neighbour enters the log later (never simulated). Officially the
    logged scene holds only the sim agents, so the exact replay scores the distance feature as well as a lone car;
    the legacy option counts the late neighbour on the log side only and penalises the exact replay."""
    from r1sim_sumo.metrics.realism import RealismConfig

    t = np.arange(T_ALL) * DT
    x = np.stack([10.0 * t, 10.0 * t + 8.0])  # the neighbour drives 8 m ahead, from step 50 on
    valid = np.ones((2, T_ALL), bool)
    valid[1, :50] = False
    sc = make_scene(x, np.zeros((2, T_ALL)), np.zeros((2, T_ALL)), valid, straight_road())
    R = 8
    rep = SimTrajectories.log_replay(sc, R)
    v = np.array(rep.valid)
    v[:, 1] = False  # the rollouts never hold an agent that was not there at the current step
    sim = SimTrajectories(rep.x_m, rep.y_m, rep.yaw_rad, v)
    new = compute_realism(sc, sim).likelihoods["distance_to_nearest_object"]
    old = compute_realism(sc, sim, config=RealismConfig.legacy()).likelihoods["distance_to_nearest_object"]
    # official: log and sims both read "no object" (+inf -> last bin) at every step: (80 R + 0.1) / (80 R + 1)
    assert new == pytest.approx((80 * R + 0.1) / (80 * R + 1.0), rel=1e-9)
    assert old < 0.1 < new


def test_simulated_histogram_samples_pool_every_simulated_step():
    """Issue 16 item 2: the logged car leaves the network at x = 290 m; the simulated one drives on, off the map. The
    official estimator pools all simulated steps (only the log side is masked), so the off-map samples lower the
    road-edge likelihood of the logged (on-road) values; the legacy option masked them away."""
    from r1sim_sumo.metrics.realism import RealismConfig

    mp = straight_road(lanes=1, length=400.0)  # lane from x = -100 to 300
    x = 220.0 + 15.0 * DT * np.arange(T_ALL)[None]
    valid = x < 290.0
    sc = make_scene(x, np.zeros_like(x), np.zeros_like(x), valid, mp)
    fut = slice(CI + 1, T_ALL)
    T = T_ALL - CI - 1
    sim = SimTrajectories(np.repeat(x[None, :, fut], 4, 0), np.zeros((4, 1, T)), np.zeros((4, 1, T)), np.ones((4, 1, T), bool))
    new = compute_realism(sc, sim).likelihoods["distance_to_road_edge"]
    old = compute_realism(sc, sim, config=RealismConfig.legacy()).likelihoods["distance_to_road_edge"]
    n_log = int(valid[0, fut].sum())
    # legacy: sims masked like the log -> identical samples, one occupied bin: (4 n + 0.1) / (4 n + 1)
    assert old == pytest.approx((4 * n_log + 0.1) / (4 * n_log + 1.0), rel=1e-6)
    # official: the same bin holds only the on-road share of the 4 * 80 simulated samples
    assert new < old - 0.1


def curved_scene(num_agents: int = 4, radius: float = 50.0, speed: float = 10.0) -> Scenario:
    """Agents driving counter-clockwise on a 2-lane arc (radius 50 m and 53.2 m)."""
    th = np.linspace(-1.0, 4.0, 200)
    pls = [np.stack([r * np.cos(th), r * np.sin(th)], 1) for r in (radius, radius + 3.2)]
    mp = MapPolylines.from_lists(pls, [LANE_CENTRE] * 2, ["in", "out"], [20.0] * 2, [3.2] * 2)
    t = np.arange(T_ALL) * DT
    xs, ys, yaws = [], [], []
    for k in range(num_agents):
        r = radius + 3.2 * (k % 2)
        th0 = -0.5 + 0.25 * k
        ang = th0 + (speed / r) * t
        xs.append(r * np.cos(ang))
        ys.append(r * np.sin(ang))
        yaws.append(((ang + math.pi / 2 + math.pi) % (2 * math.pi)) - math.pi)
    return make_scene(np.stack(xs), np.stack(ys), np.stack(yaws), np.ones((num_agents, T_ALL), bool), mp)


def constant_velocity(sc: Scenario, R: int) -> SimTrajectories:
    a, ci = sc.agents, sc.current_index
    vx = (a.x_m[:, ci] - a.x_m[:, ci - 1]) / DT
    vy = (a.y_m[:, ci] - a.y_m[:, ci - 1]) / DT
    t = np.arange(1, 81) * DT
    x = a.x_m[:, ci, None] + vx[:, None] * t
    y = a.y_m[:, ci, None] + vy[:, None] * t
    yaw = np.broadcast_to(a.yaw_rad[:, ci, None], x.shape)
    return SimTrajectories(np.repeat(x[None], R, 0), np.repeat(y[None], R, 0), np.repeat(yaw[None], R, 0))


def test_log_replay_scores_higher_than_constant_velocity_on_curve():
    sc = curved_scene()
    replay = compute_realism(sc, SimTrajectories.log_replay(sc, 4))
    cv = compute_realism(sc, constant_velocity(sc, 4))
    assert replay.is_finite() and cv.is_finite()
    assert replay.rmm > cv.rmm + 0.05
    assert replay.likelihoods["angular_speed"] > cv.likelihoods["angular_speed"]
    assert replay.ade == pytest.approx(0.0, abs=1e-5) and cv.ade > 5.0
    assert replay.offroad_rate == 0.0 and cv.offroad_rate > 0.5
    assert replay.diversity == pytest.approx(0.0, abs=1e-6)
    assert set(replay.buckets) == {"kinematic", "interactive", "map_based"}
    agg = aggregate([replay, cv])
    assert agg["realism/rmm"] == pytest.approx((replay.rmm + cv.rmm) / 2)
    assert agg["realism/num_scenarios"] == 2.0


def test_perturbed_rollouts_score_lower_than_exact_ones():
    sc = curved_scene()
    exact = compute_realism(sc, SimTrajectories.log_replay(sc, 8))
    base = SimTrajectories.log_replay(sc, 8)
    rng = np.random.default_rng(0)
    noisy = SimTrajectories(base.x_m + rng.normal(0, 0.3, base.x_m.shape), base.y_m + rng.normal(0, 0.3, base.y_m.shape),
                            base.yaw_rad + rng.normal(0, 0.05, base.yaw_rad.shape), base.valid)
    pert = compute_realism(sc, noisy)
    for name in ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration"):
        assert exact.likelihoods[name] > pert.likelihoods[name], name
    assert exact.rmm > pert.rmm
    assert pert.diversity > 0.0 and pert.min_ade <= pert.ade


def test_realism_finite_with_invalid_agents():
    sc0 = curved_scene(num_agents=5)
    a = sc0.agents
    a.valid[2, 40:] = False  # leaves mid-way
    a.valid[3, :50] = False  # appears later: not evaluated
    a.valid[4, CI - 1] = False  # no previous state: speed at the first future step invalid
    for f in AgentTracks.PER_STEP:
        getattr(a, f)[~a.valid] = 0.0
    sc = Scenario(a, sc0.map, sc0.metadata).validate()
    res = compute_realism(sc, SimTrajectories.log_replay(sc, 3))
    assert res.is_finite()
    assert res.num_evaluated_agents == 4
    assert 0.0 < res.rmm <= 1.0
    # sims with NaN at invalid entries are accepted; NaN at valid entries are refused
    sim = SimTrajectories.log_replay(sc, 3)
    x = sim.x_m.astype(np.float64)
    x[~sim.valid] = np.nan
    assert compute_realism(sc, SimTrajectories(x, sim.y_m, sim.yaw_rad, sim.valid)).is_finite()
    x[0, 0, 5] = np.nan
    with pytest.raises(MetricsInputError, match="non-finite"):
        compute_realism(sc, SimTrajectories(x, sim.y_m, sim.yaw_rad, sim.valid))
    with pytest.raises(MetricsInputError, match="agents"):
        compute_realism(sc, SimTrajectories(sim.x_m[:, :2], sim.y_m[:, :2], sim.yaw_rad[:, :2]))


def test_broad_phase_matches_brute_force_on_random_scenes():
    """Collisions vs an all-pairs SAT, distances vs shapely polygon distances, TTC vs a per-pair loop."""
    import shapely

    from r1sim_sumo.geometry import box_corners, boxes_overlap, wrap_angle

    rng = np.random.default_rng(3)
    R, A, T = 2, 7, 12
    x, y = rng.uniform(0, 25, (R, A, T)), rng.uniform(0, 8, (R, A, T))
    yaw = rng.normal(0, 0.3, (R, A, T)) + np.where(rng.random((R, A, 1)) < 0.2, math.pi, 0.0)
    yaw = wrap_angle(yaw)
    L, W = rng.uniform(3.5, 8, A), rng.uniform(1.6, 2.6, A)
    v = rng.random((R, A, T)) < 0.85
    sp = rng.uniform(0, 15, (R, A, T))
    f = interaction_features(x, y, yaw, L, W, v, sp, box_shape="sharp")
    fw = interaction_features(x, y, yaw, L, W, v, sp, box_shape="sharp", ttc_heading="wrapped")
    n_differ = 0
    c = box_corners(x, y, yaw, L[None, :, None], W[None, :, None])  # [R, A, T, 4, 2]
    for r in range(R):
        for t in range(T):
            for i in range(A):
                if not v[r, i, t]:
                    continue
                others = [j for j in range(A) if j != i and v[r, j, t]]
                ov = [bool(boxes_overlap(x[r, i, t], y[r, i, t], yaw[r, i, t], L[i], W[i],
                                         x[r, j, t], y[r, j, t], yaw[r, j, t], L[j], W[j])) for j in others]
                assert f.collision[r, i, t] == any(ov)
                pi = shapely.Polygon(c[r, i, t])
                dists = [shapely.distance(pi, shapely.Polygon(c[r, j, t])) for j in others]
                if not any(ov) and others:
                    assert f.distance_m[r, i, t] == pytest.approx(min(dists), abs=1e-6)
                elif any(ov):
                    assert f.distance_m[r, i, t] < 0
                # TTC: nearest object ahead, per pair; WOSAC's yaw difference is |yaw_j - yaw_i| unwrapped
                # (interaction_features.py: tf.math.abs(other_yaw - ego_yaw)), the option wraps it to [0, pi]
                wants = []
                for wrapped in (False, True):
                    best, v_lead = math.inf, 0.0
                    for j in others:
                        ci, si = math.cos(yaw[r, i, t]), math.sin(yaw[r, i, t])
                        dx, dy = x[r, j, t] - x[r, i, t], y[r, j, t] - y[r, i, t]
                        raw = yaw[r, j, t] - yaw[r, i, t]
                        yd = abs((raw + math.pi) % (2 * math.pi) - math.pi) if wrapped else abs(raw)
                        gap = dx * ci + dy * si - L[i] / 2 - (L[j] / 2 * abs(math.cos(yd)) + W[j] / 2 * abs(math.sin(yd)))
                        lat = abs(-dx * si + dy * ci) - W[i] / 2 - (L[j] / 2 * abs(math.sin(yd)) + W[j] / 2 * abs(math.cos(yd)))
                        ahead = gap > 0 and yd <= math.radians(75) and lat < 0 and (lat < -0.5 or yd <= math.radians(10))
                        if ahead and gap < best:
                            best, v_lead = gap, sp[r, j, t]
                    closing = sp[r, i, t] - v_lead
                    wants.append(min(best / closing, 5.0) if math.isfinite(best) and closing > 0 else 5.0)
                assert f.ttc_s[r, i, t] == pytest.approx(wants[0], rel=1e-9, abs=1e-9)
                assert fw.ttc_s[r, i, t] == pytest.approx(wants[1], rel=1e-9, abs=1e-9)
                n_differ += wants[0] != wants[1]
    assert n_differ > 0  # the scene has pairs heading west with yaws of opposite sign


def test_log_window_rates_ignore_driving_past_the_end_of_the_map():
    # the logged car leaves the 300 m road (its log ends at x = 290 m); a simulated copy keeps driving past the end
    mp = straight_road(lanes=1, length=400.0)  # lane from x = -100 to 300
    x = 250.0 + 10.0 * DT * np.arange(T_ALL)[None]  # 10 m/s
    valid = (x < 290.0)
    sc = make_scene(x, np.zeros_like(x), np.zeros_like(x), valid, mp)
    fut = slice(CI + 1, T_ALL)
    sim = SimTrajectories(x[None, :, fut], np.zeros((1, 1, T_ALL - CI - 1)), np.zeros((1, 1, T_ALL - CI - 1)),
                          np.ones((1, 1, T_ALL - CI - 1), bool))
    res = compute_realism(sc, sim)
    assert res.offroad_rate == 1.0  # off the map after x = 300 m
    assert res.extra["offroad_rate_log_window"] == 0.0  # but never while the logged car was still on the network
    assert res.to_dict()["realism/offroad_rate_log_window"] == 0.0


def test_ttc_is_scored_on_vehicles_only():
    """WOSAC scores TTC (and the traffic-light feature) on vehicles only. A cyclist closing in on a car in every
    rollout (but not in the log) lowers the TTC likelihood only in the legacy option."""
    from r1sim_sumo.metrics.realism import RealismConfig

    t = np.arange(T_ALL) * DT
    x = np.stack([np.full(T_ALL, 100.0), np.full(T_ALL, 60.0)])  # car stopped at 100 m, cyclist stopped 40 m behind
    sc = make_scene(x, np.zeros((2, T_ALL)), np.zeros((2, T_ALL)), np.ones((2, T_ALL), bool), straight_road())
    sc.agents.agent_type[1] = 1
    sc.agents.length_m[1], sc.agents.width_m[1] = 1.8, 0.7
    sim = SimTrajectories.log_replay(sc, 4)
    xs = np.array(sim.x_m, np.float64)
    xs[:, 1] = 60.0 + 8.0 * t[None, CI + 1:]  # the simulated cyclist rides at 8 m/s towards the car
    fast = SimTrajectories(xs, sim.y_m, sim.yaw_rad, sim.valid)
    new = compute_realism(sc, fast).likelihoods["time_to_collision"]
    old = compute_realism(sc, fast, config=RealismConfig.legacy()).likelihoods["time_to_collision"]
    # vehicles only: the car never has anything ahead, log and sims read 5 s: (80 * 4 + 0.1) / (80 * 4 + 1)
    assert new == pytest.approx((320 + 0.1) / (320 + 1.0), rel=1e-9)
    assert old < new - 0.05
