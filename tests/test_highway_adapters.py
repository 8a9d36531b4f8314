"""highway-env adapters (map, vehicle states) and the highway-env reference generator."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("highway_env")
gymnasium = pytest.importorskip("gymnasium")
shapely = pytest.importorskip("shapely")

import highway_env  # noqa: E402,F401
from shapely.geometry import LineString, Point  # noqa: E402
from shapely.ops import unary_union  # noqa: E402

from r1sim_sumo.adapters import highway_map as hm  # noqa: E402
from r1sim_sumo.adapters.highway_state import (  # noqa: E402
    VEHICLE_ID_ATTR,
    internal_to_highway_state,
    read_highway_vehicles,
)
from r1sim_sumo.data import highway_reference as hr  # noqa: E402
from r1sim_sumo.scenario import (  # noqa: E402
    CURRENT_INDEX,
    LANE_CENTRE,
    N_WINDOW_10HZ,
    ROAD_EDGE,
    read_shard,
    write_shard,
)

pytestmark = [
    pytest.mark.highway,
    pytest.mark.filterwarnings("ignore::DeprecationWarning"),
    pytest.mark.filterwarnings("ignore::UserWarning"),
]

ENVS = ("highway-v0", "merge-v0", "roundabout-v0", "intersection-v0")


def _env(name: str, **config):
    env = gymnasium.make(name)
    u = env.unwrapped
    cfg = hr._env_config(u.default_config(), name, 20.0, None)
    cfg.update(config)
    u.configure(cfg)
    u.reset(seed=3)
    hr._make_ego_background(u)
    return env, u


def _lanes(net):
    return [
        ((a, b, i), lane) for a in net.graph for b in net.graph[a] for i, lane in enumerate(net.graph[a][b])
    ]


# ------------------------------------------------------------------ frames and states


def test_line_type_constants_match_highway_env():
    from highway_env.road.lane import LineType

    assert (LineType.NONE, LineType.STRIPED, LineType.CONTINUOUS, LineType.CONTINUOUS_LINE) == (
        hm.LINE_NONE,
        hm.LINE_STRIPED,
        hm.LINE_CONTINUOUS,
        hm.LINE_CONTINUOUS_LINE,
    )


def test_frame_conversion_flips_y_and_heading():
    env, u = _env("highway-v0", vehicles_count=3)
    v = u.road.vehicles[1]
    v.position = np.array([12.0, 3.0])
    v.heading = math.pi / 2  # driving "down" the screen (+y in highway-env)
    v.speed = 4.0
    st = read_highway_vehicles(u.road, [v])
    assert st.x_m[0] == pytest.approx(12.0) and st.y_m[0] == pytest.approx(-3.0)
    assert st.yaw_rad[0] == pytest.approx(-math.pi / 2)  # down the screen = negative yaw in ours
    assert st.vx_mps[0] == pytest.approx(0.0, abs=1e-9) and st.vy_mps[0] == pytest.approx(-4.0)
    assert st.length_m[0] == 5.0 and st.width_m[0] == 2.0 and st.agent_type[0] == 0
    back = internal_to_highway_state(st.x_m, st.y_m, st.yaw_rad, st.speed_mps)
    np.testing.assert_allclose(back.position_m[0], [12.0, 3.0])
    assert back.heading_rad[0] == pytest.approx(math.pi / 2)
    np.testing.assert_allclose(back.velocity_mps[0], v.velocity, atol=1e-9)
    # heading wraps: highway-env headings are not wrapped
    v.heading = 2 * math.pi + 0.25
    assert read_highway_vehicles(u.road, [v]).yaw_rad[0] == pytest.approx(-0.25)
    env.close()


def test_vehicle_ids_are_stable_across_steps():
    env, u = _env("intersection-v0")
    first = read_highway_vehicles(u.road)
    objs = {getattr(v, VEHICLE_ID_ATTR): v for v in u.road.vehicles}
    assert len(set(first.ids.tolist())) == len(first.ids)
    seen = set(first.ids.tolist())
    for _ in range(15):
        u.step(None)
        st = read_highway_vehicles(u.road)
        for vid, v in zip(st.ids.tolist(), u.road.vehicles, strict=True):
            if vid in objs:
                assert objs[vid] is v  # same object keeps its id
            else:
                assert vid not in seen  # new vehicles get fresh ids
            objs[vid] = v
            seen.add(vid)
    env.close()


# ------------------------------------------------------------------ map extraction


@pytest.mark.parametrize("name", ENVS)
def test_map_has_every_lane_with_limits_and_widths(name):
    env, u = _env(name)
    net = u.road.network
    m = read = hm.read_highway_map(net, step_m=1.0)
    mp = read.polylines
    lanes = _lanes(net)
    assert len(m.lane_index) == len(lanes) == int((mp.kind == LANE_CENTRE).sum())
    n_edges = 0
    for index, lane in lanes:
        row = m.lane_index[index]
        assert mp.lane_id[row] == hm.lane_id(index) and mp.kind[row] == LANE_CENTRE
        assert mp.speed_limit_mps[row] == pytest.approx(lane.speed_limit)
        assert mp.width_m[row] == pytest.approx(lane.width_at(0.0))
        pts = mp.polyline(row)
        # ends are lane.position(0, 0) and lane.position(length, 0), y flipped
        start, end = lane.position(0.0, 0.0), lane.position(lane.length, 0.0)
        np.testing.assert_allclose(pts[0], [start[0], -start[1]], atol=1e-3)
        np.testing.assert_allclose(pts[-1], [end[0], -end[1]], atol=1e-3)
        # steps of 1 m in the lane coordinate s (a SineLane's s runs along its straight base: a bit more arc)
        max_step = 1.1 if type(lane).__name__ == "SineLane" else 1.001
        assert np.linalg.norm(np.diff(pts, axis=0), axis=1).max() <= max_step
        for side, name_ in enumerate(("left", "right")):
            is_edge = f"{hm.lane_id(index)}#{name_}" in set(mp.lane_id.tolist())
            assert is_edge == (lane.line_types[side] in hm.ROAD_EDGE_LINE_TYPES)
            n_edges += is_edge
    assert n_edges == int((mp.kind == ROAD_EDGE).sum()) > 0
    assert mp.successors.size == 0 or set(mp.kind[mp.successors.ravel()].tolist()) == {LANE_CENTRE}
    env.close()


def test_highway_v0_geometry_in_internal_frame():
    env, u = _env("highway-v0", vehicles_count=3, lanes_count=4)
    m = hm.read_highway_map(u.road.network, bounds_m=(0.0, -100.0, 500.0, 100.0))
    mp = m.polylines
    # lane i of highway-env sits at y_hw = 4 i (downward): internal y = -4 i, left edge at +2, right at -14
    for i in range(4):
        pts = mp.polyline(m.lane_index[("0", "1", i)])
        np.testing.assert_allclose(pts[:, 1], -4.0 * i, atol=1e-5)
        assert pts[0, 0] == 0.0 and 500.0 <= pts[-1, 0] <= 502.0  # cropped to the box (+1 point)
    edges = {lid: mp.polyline(k) for k, lid in enumerate(mp.lane_id.tolist()) if mp.kind[k] == ROAD_EDGE}
    assert set(edges) == {"0->1#0#left", "0->1#3#right"}
    np.testing.assert_allclose(edges["0->1#0#left"][:, 1], 2.0, atol=1e-5)
    np.testing.assert_allclose(edges["0->1#3#right"][:, 1], -14.0, atol=1e-5)
    assert mp.speed_limit_mps[m.lane_index[("0", "1", 0)]] == pytest.approx(30.0)
    env.close()


def test_roundabout_successors_follow_the_ring():
    env, u = _env("roundabout-v0")
    m = hm.read_highway_map(u.road.network)
    ids = m.polylines.lane_id
    pairs = {(ids[a], ids[b]) for a, b in m.polylines.successors}
    assert ("se->ex#0", "ex->ee#0") in pairs and ("se->ex#1", "ex->ee#1") in pairs
    assert ("se->ex#0", "ex->ee#1") not in pairs  # lanes do not jump across the ring
    assert ("se->ex#1", "ex->exs#0") in pairs  # exit
    env.close()


# ------------------------------------------------------------------ vehicles lie on the lanes


@pytest.mark.parametrize("name", ENVS)
def test_recorded_vehicles_lie_within_lane_polygons(name):
    env, u = _env(name, **({"vehicles_count": 15} if name == "highway-v0" else {}))
    m = hm.read_highway_map(u.road.network, bounds_m=(-300.0, -300.0, 1500.0, 300.0))
    mp = m.polylines
    polys = {
        k: LineString(mp.polyline(k)).buffer(0.5 * mp.width_m[k])
        for k in range(mp.num_polylines)
        if mp.kind[k] == LANE_CENTRE
    }
    road = unary_union(list(polys.values()))
    checked = own_lane = 0
    for _ in range(30):
        u.step(None)
        st = read_highway_vehicles(u.road)
        for k, v in enumerate(u.road.vehicles):
            if not st.on_road[k]:
                continue
            p = Point(st.x_m[k], st.y_m[k])
            assert road.distance(p) < 0.05, (
                f"{name}: vehicle {st.ids[k]} at {p} off the road by {road.distance(p):.2f} m"
            )
            checked += 1
            if v.lane_index == v.target_lane_index and v.lane_index in m.lane_index:  # not changing lane
                lane = polys[m.lane_index[v.lane_index]]
                assert lane.distance(p) < 0.3, (
                    f"{name}: vehicle {st.ids[k]} {lane.distance(p):.2f} m outside lane {v.lane_index}"
                )
                own_lane += 1
    assert checked > 30 and own_lane > 10
    env.close()


# ------------------------------------------------------------------ generator


def _assert_same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert x.metadata == y.metadata
        for f in ("ids", "x_m", "y_m", "yaw_rad", "speed_mps", "valid"):
            np.testing.assert_array_equal(getattr(x.agents, f), getattr(y.agents, f))
        np.testing.assert_array_equal(x.map.points_m, y.map.points_m)


def test_generator_windows_validate_and_are_deterministic(tmp_path):
    kw = dict(n_episodes=2, episode_s=12.0, stride_steps=10, progress=False)
    a = hr.generate_highway_scenarios("merge-v0", seed=5, **kw)
    b = hr.generate_highway_scenarios("merge-v0", seed=5, **kw)
    c = hr.generate_highway_scenarios("merge-v0", seed=6, **kw)
    assert len(a) == 2 * 4  # (121 - 91) // 10 + 1 windows per episode
    for sc in a:
        sc.validate()
        assert sc.num_steps == N_WINDOW_10HZ and sc.current_index == CURRENT_INDEX
        assert sc.agents.valid[:, CURRENT_INDEX].all()
        assert sc.metadata["source"] == "highway-env" and sc.metadata["network"] == "merge-v0"
        assert {"seed", "generator_version", "episode", "start_step", "episode_seed"} <= set(sc.metadata)
    assert [sc.metadata["start_step"] for sc in a[:4]] == [0, 10, 20, 30]
    # consecutive overlapping windows hold the same states 10 steps apart
    w0, w1 = a[0].agents, a[1].agents
    i0, i1 = list(w0.ids).index(w1.ids[0]), 0
    np.testing.assert_array_equal(w0.x_m[i0, 10:], w1.x_m[i1, :-10])
    _assert_same(a, b)
    _assert_same(a, read_shard(write_shard(tmp_path / "hw.npz", a)))  # one map per episode round-trips
    assert not np.array_equal(a[0].agents.x_m, c[0].agents.x_m)
    # internal frame: merge-v0 traffic drives east (+x) on lanes at y <= 0
    v = a[0].agents
    assert (v.vx_mps[v.valid] > 0).all() and (v.y_m[v.valid] < 2.5).all()


def test_generator_highway_vehicles_count_and_intersection_appearances():
    from highway_env.vehicle.behavior import IDMVehicle

    before = IDMVehicle.DISTANCE_WANTED
    hw = hr.generate_highway_scenarios("highway-v0", seed=1, episode_s=9.0, vehicles_count=6, progress=False)
    assert len(hw) == 1 and hw[0].agents.num_agents == 7  # 6 background + the ego driven by IDM
    inter = hr.generate_highway_scenarios(
        "intersection-v0", seed=0, episode_s=12.0, stride_steps=15, vehicles_count=6, progress=False
    )
    assert inter, "intersection-v0 produced no window"
    valid = np.concatenate([sc.agents.valid for sc in inter])
    assert not valid.all()  # vehicles spawn / leave inside windows
    assert IDMVehicle.DISTANCE_WANTED == before  # intersection-v0's class mutation is undone
    with pytest.raises(ValueError, match="episode_s"):
        hr.generate_highway_scenarios("merge-v0", seed=0, episode_s=5.0, progress=False)
    with pytest.raises(ValueError, match="unsupported"):
        hr.generate_highway_scenarios("parking-v0", seed=0, progress=False)
