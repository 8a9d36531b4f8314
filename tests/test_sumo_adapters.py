"""SUMO adapters: network -> map polylines, vehicle state <-> internal state, through libsumo and TraCI.

The test network is built here from plain XML with netconvert (it does not depend on the bundled
networks): a signalised junction C with a straight 3-lane approach W->C (lane 0 a pedestrian-only
sidewalk), a curved exit C->N (quarter circle, radius 100 m), C->E and a crossing approach S->C.
"""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from r1sim_sumo.geometry import (
    centre_to_front_bumper,
    front_bumper_to_centre,
    sumo_angle_deg_to_yaw_rad,
    yaw_rad_to_sumo_angle_deg,
)
from r1sim_sumo.scenario import (
    LANE_CENTRE,
    ROAD_EDGE,
    TL_GREEN,
    TL_NONE,
    TL_RED,
    TL_YELLOW,
    AgentTracks,
    Scenario,
)

pytestmark = pytest.mark.sumo

# ---------------------------------------------------------------------------- test network

_NODES = """<nodes>
  <node id="W" x="-200" y="0"/> <node id="C" x="0" y="0" type="traffic_light"/>
  <node id="E" x="200" y="0"/> <node id="N" x="100" y="100"/> <node id="S" x="0" y="-200"/>
</nodes>"""


def _edges_xml() -> str:
    t = np.linspace(0.0, 0.5 * math.pi, 24)
    arc = " ".join(f"{100 - 100 * math.cos(a):.3f},{100 * math.sin(a):.3f}" for a in t)
    return f"""<edges>
  <edge id="W2C" from="W" to="C" numLanes="3" speed="13.89">
    <lane index="0" allow="pedestrian" width="2.0"/>
  </edge>
  <edge id="C2E" from="C" to="E" numLanes="2" speed="13.89"/>
  <edge id="C2N" from="C" to="N" numLanes="1" speed="11.0" shape="{arc}"/>
  <edge id="S2C" from="S" to="C" numLanes="1" speed="13.89" width="3.5"/>
</edges>"""


_CONNECTIONS = """<connections>
  <connection from="W2C" to="C2E" fromLane="1" toLane="0"/>
  <connection from="W2C" to="C2E" fromLane="2" toLane="1"/>
  <connection from="W2C" to="C2N" fromLane="2" toLane="0"/>
  <connection from="S2C" to="C2N" fromLane="0" toLane="0"/>
  <connection from="S2C" to="C2E" fromLane="0" toLane="0"/>
</connections>"""

_ROUTES = """<routes>
  <vType id="car" length="4.8" width="1.9" maxSpeed="30" sigma="0"/>
  <vType id="bike" vClass="bicycle" length="1.8" width="0.7"/>
  <route id="r_wn" edges="W2C C2N"/> <route id="r_we" edges="W2C C2E"/> <route id="r_se" edges="S2C C2E"/>
</routes>"""


@pytest.fixture(scope="module")
def net_dir(tmp_path_factory) -> Path:
    from r1sim_sumo._sumo_env import sumo_binary

    d = tmp_path_factory.mktemp("sumo_net")
    (d / "n.nod.xml").write_text(_NODES)
    (d / "n.edg.xml").write_text(_edges_xml())
    (d / "n.con.xml").write_text(_CONNECTIONS)
    (d / "r.rou.xml").write_text(_ROUTES)
    res = subprocess.run(
        [sumo_binary("netconvert"), "-n", "n.nod.xml", "-e", "n.edg.xml", "-x", "n.con.xml", "-o", "t.net.xml",
         "--no-turnarounds", "--tls.cycle.time", "30", "--no-warnings"],
        cwd=d, capture_output=True, text=True, timeout=60,
    )
    assert res.returncode == 0, res.stderr
    return d


@pytest.fixture(scope="module")
def net_file(net_dir) -> Path:
    return net_dir / "t.net.xml"


@pytest.fixture(scope="module")
def smap(net_file):
    from r1sim_sumo.adapters.sumo_map import read_sumo_map

    return read_sumo_map(net_file)


@pytest.fixture
def libsumo_sim(net_dir):
    """A libsumo simulation of the test network at 0.1 s steps; closed afterwards."""
    import libsumo

    from r1sim_sumo._sumo_env import sumo_binary

    libsumo.start([sumo_binary("sumo"), "-n", str(net_dir / "t.net.xml"), "-r", str(net_dir / "r.rou.xml"),
                   "--step-length", "0.1", "--no-step-log", "--no-warnings", "--seed", "1",
                   "--time-to-teleport", "-1"])
    try:
        yield libsumo
    finally:
        libsumo.close()


def _add_and_depart(conn, veh_id: str, route: str, type_id: str = "car", depart_pos: float = 10.0) -> None:
    conn.vehicle.add(veh_id, route, typeID=type_id, departPos=str(depart_pos), departLane="best")
    for _ in range(5):
        conn.simulationStep()
        if veh_id in conn.vehicle.getIDList():
            return
    raise AssertionError(f"vehicle {veh_id} did not depart")


def _lane_pose(conn, lane_id: str, frac: float, length_m: float):
    """Box-centre pose whose front bumper lies on the lane centre at fraction ``frac`` of its length."""
    shape = np.asarray(conn.lane.getShape(lane_id), np.float64)
    seg = np.linalg.norm(np.diff(shape, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    target = frac * s[-1]
    k = min(int(np.searchsorted(s, target, side="right")) - 1, len(seg) - 1)
    p = shape[k] + (target - s[k]) / seg[k] * (shape[k + 1] - shape[k])
    yaw = math.atan2(*(shape[k + 1] - shape[k])[::-1])
    x, y = front_bumper_to_centre(p[0], p[1], yaw, length_m)
    return float(x), float(y), yaw


def _yaw_err_deg(a, b) -> float:
    return float(np.abs(np.rad2deg((np.asarray(a) - np.asarray(b) + math.pi) % (2 * math.pi) - math.pi)).max())


# ---------------------------------------------------------------------------- pure numpy conversions


def test_angle_known_values():
    # north = 0 deg = yaw pi/2, east = 90 deg = yaw 0, south = 180 = -pi/2, west = 270 = +-pi
    np.testing.assert_allclose(sumo_angle_deg_to_yaw_rad([0.0, 90.0, 180.0]), [math.pi / 2, 0.0, -math.pi / 2], atol=1e-12)
    assert abs(abs(float(sumo_angle_deg_to_yaw_rad(270.0))) - math.pi) < 1e-12
    np.testing.assert_allclose(yaw_rad_to_sumo_angle_deg([math.pi / 2, 0.0, -math.pi / 2, math.pi]), [0.0, 90.0, 180.0, 270.0], atol=1e-9)
    # wrap-around at 360: 359 deg and -1 deg and 719 deg are the same heading, 1 degree west of north
    yaws = sumo_angle_deg_to_yaw_rad([359.0, -1.0, 719.0, 360.0])
    np.testing.assert_allclose(yaws[:3], math.radians(91.0), atol=1e-12)
    np.testing.assert_allclose(yaws[3], math.pi / 2, atol=1e-12)
    assert (np.abs(yaws) <= math.pi).all()
    out = yaw_rad_to_sumo_angle_deg(np.array([math.radians(91.0), math.radians(91.0) + 4 * math.pi]))
    np.testing.assert_allclose(out, 359.0, atol=1e-9)
    assert ((out >= 0) & (out < 360)).all()


def test_angle_round_trip_random():
    rng = np.random.default_rng(0)
    deg = rng.uniform(0, 360, 1000)
    back = yaw_rad_to_sumo_angle_deg(sumo_angle_deg_to_yaw_rad(deg))
    np.testing.assert_allclose((back - deg + 180) % 360 - 180, 0.0, atol=1e-9)


def test_front_bumper_centre_known_and_inverse():
    from r1sim_sumo.adapters.sumo_state import to_sumo_pose

    # heading north (yaw pi/2), length 4: the front bumper is 2 m north of the centre
    x_fb, y_fb, ang = to_sumo_pose(10.0, 20.0, math.pi / 2, 4.0)
    assert abs(x_fb - 10.0) < 1e-12 and abs(y_fb - 22.0) < 1e-12 and abs(ang - 0.0) < 1e-9
    # heading east (SUMO 90 deg): bumper 2 m east
    x_fb, y_fb, ang = to_sumo_pose(10.0, 20.0, 0.0, 4.0)
    assert abs(x_fb - 12.0) < 1e-12 and abs(y_fb - 20.0) < 1e-12 and abs(ang - 90.0) < 1e-9
    rng = np.random.default_rng(1)
    x, y, yaw, ln = rng.normal(size=50) * 100, rng.normal(size=50) * 100, rng.uniform(-math.pi, math.pi, 50), rng.uniform(1, 20, 50)
    xf, yf, ang = to_sumo_pose(x, y, yaw, ln)
    xc, yc = front_bumper_to_centre(xf, yf, sumo_angle_deg_to_yaw_rad(ang), ln)
    np.testing.assert_allclose(xc, x, atol=1e-9)
    np.testing.assert_allclose(yc, y, atol=1e-9)
    np.testing.assert_allclose(np.hypot(xf - x, yf - y), ln / 2, atol=1e-9)
    np.testing.assert_allclose(centre_to_front_bumper(x, y, yaw, ln), (xf, yf))


def test_tl_char_mapping():
    from r1sim_sumo.adapters.sumo_map import sumo_chars_to_tl

    codes = sumo_chars_to_tl("GgsyYrRuoO")
    assert codes.tolist() == [TL_GREEN] * 3 + [TL_YELLOW] * 2 + [TL_RED] * 3 + [TL_NONE] * 2


# ---------------------------------------------------------------------------- map extraction


def test_map_lanes_match_sumolib(smap, net_file):
    import sumolib

    net = sumolib.net.readNet(str(net_file), withInternal=True)
    all_lanes = {ln.getID(): ln for e in net.getEdges(withInternal=True) for ln in e.getLanes()}
    drivable = {k for k, ln in all_lanes.items() if set(ln.getPermissions()) - {"pedestrian"}}
    pl = smap.polylines
    lane_rows = np.flatnonzero(pl.kind == LANE_CENTRE)
    ids = pl.lane_id[lane_rows].tolist()
    assert len(ids) == len(set(ids)), "a lane appears twice"
    assert set(ids) == drivable
    assert "W2C_0" not in ids and "W2C_1" in ids  # sidewalk out, the car lane next to it in
    assert any(i.startswith(":C_") for i in ids), "junction internal lanes missing"
    for k in lane_rows:
        ln = all_lanes[pl.lane_id[k]]
        assert smap.lane_index[pl.lane_id[k]] == k
        assert pl.speed_limit_mps[k] == pytest.approx(ln.getSpeed(), abs=1e-4)
        assert pl.width_m[k] == pytest.approx(ln.getWidth(), abs=1e-4)
        np.testing.assert_allclose(pl.polyline(k), np.asarray(ln.getShape()), atol=1e-3)
    assert pl.width_m[smap.lane_index["S2C_0"]] == pytest.approx(3.5)
    assert pl.speed_limit_mps[smap.lane_index["C2N_0"]] == pytest.approx(11.0)
    assert smap.net_offset == pytest.approx(net.getLocationOffset())
    # netconvert shifts the plain-XML frame by netOffset; the map keeps the net's coordinates as they are
    assert smap.net_offset == pytest.approx((200.0, 200.0))
    lane_pts = np.concatenate([pl.polyline(k) for k in lane_rows])
    xmin, ymin, xmax, ymax = smap.bounds
    assert xmax - xmin == pytest.approx(400.0, abs=1.0) and ymax - ymin == pytest.approx(300.0, abs=1.0)
    assert (lane_pts.min(0) >= (xmin - 1, ymin - 1)).all() and (lane_pts.max(0) <= (xmax + 1, ymax + 1)).all()


def test_map_road_edges_offset_by_half_width(smap):
    from shapely.geometry import LineString, Point

    pl = smap.polylines
    edge_rows = np.flatnonzero(pl.kind == ROAD_EDGE)
    names = set(pl.lane_id[edge_rows].tolist())
    assert names == {f"{e}#{s}" for e in ("W2C", "C2E", "C2N", "S2C") for s in ("left", "right")}
    # borders come from the leftmost / rightmost *drivable* lane of each edge
    src = {"W2C#left": "W2C_2", "W2C#right": "W2C_1", "C2E#left": "C2E_1", "C2E#right": "C2E_0",
           "C2N#left": "C2N_0", "C2N#right": "C2N_0", "S2C#left": "S2C_0", "S2C#right": "S2C_0"}
    for k in edge_rows:
        name = pl.lane_id[k]
        lane = smap.lane_index[src[name]]
        centre = pl.polyline(lane).astype(np.float64)
        half = 0.5 * float(pl.width_m[lane])
        line = LineString(centre)
        pts = pl.polyline(k)
        d = np.array([line.distance(Point(p)) for p in pts])
        # vertex offsets are exact on straight parts; on the arc the averaged normal stays within 1 cm
        np.testing.assert_allclose(d, half, atol=1e-2, err_msg=name)
        # side: left borders lie to the left of the direction of travel (positive cross product)
        t = centre[1] - centre[0]
        r = pts[0] - centre[0]
        side = np.sign(t[0] * r[1] - t[1] * r[0])
        assert side == (1 if name.endswith("#left") else -1), name
        assert pl.speed_limit_mps[k] == 0 and pl.width_m[k] == 0


def test_map_successors_through_internal_lanes(smap):
    succ = smap.successors
    (via,) = [s for s in succ["W2C_2"] if smap.successors.get(s) == ["C2N_0"]]
    assert via.startswith(":C_")
    assert "C2N_0" in succ[via]
    assert all(s.startswith(":") for s in succ["W2C_1"])  # normal lanes lead into internal lanes
    pairs = {(int(a), int(b)) for a, b in smap.polylines.successors}
    assert (smap.lane_index["W2C_2"], smap.lane_index[via]) in pairs
    assert smap.successors["C2N_0"] == []  # dead end
    assert len(pairs) == sum(len(v) for v in succ.values())


def test_map_validates_in_scenario(smap):
    tracks = AgentTracks.empty(1, 91)
    tracks.valid[:] = True
    Scenario(agents=tracks, map=smap.polylines, metadata={"source": "sumo"}).validate()


def test_traffic_lights_libsumo(smap, libsumo_sim):
    conn = libsumo_sim
    assert smap.has_traffic_lights and smap.tl_links.tls_ids == ["C"]
    L = smap.num_polylines
    # cross-check via lanes against SUMO's own controlled-link table at many instants
    links = conn.trafficlight.getControlledLinks("C")
    seen_states = set()
    history = []
    for step in range(400):  # 40 s > one 30 s cycle
        conn.simulationStep()
        st = smap.tl_states(conn)
        assert st.shape == (L,) and st.dtype == np.int8
        assert (st[smap.polylines.kind == ROAD_EDGE] == TL_NONE).all()
        chars = conn.trafficlight.getRedYellowGreenState("C")
        for idx, group in enumerate(links):
            for _frm, _to, via in group:
                expect = {"G": TL_GREEN, "g": TL_GREEN, "y": TL_YELLOW, "r": TL_RED}[chars[idx]]
                assert st[smap.lane_index[via]] == expect, (step, via, chars)
        seen_states.add(chars)
        history.append(st[[smap.lane_index["W2C_1"], smap.lane_index["S2C_0"]]])
    history = np.array(history)  # [T, 2]
    assert len(seen_states) >= 3, "signal program did not cycle"
    for j in range(2):
        assert {TL_GREEN, TL_RED} <= set(history[:, j].tolist()), "incoming lane state did not change over time"
    # conflicting approaches are never green together
    assert not ((history[:, 0] == TL_GREEN) & (history[:, 1] == TL_GREEN)).any()
    # unsignalised lanes (exits) stay TL_NONE
    assert (np.array([smap.tl_states(conn)[smap.lane_index["C2E_0"]]]) == TL_NONE).all()


# ---------------------------------------------------------------------------- vehicle state round trip


@pytest.mark.parametrize("keep_route", [2, 3])
def test_round_trip_straight_curved_internal(libsumo_sim, smap, keep_route):
    from r1sim_sumo.adapters.sumo_state import move_vehicle, read_vehicle_states, take_control

    conn = libsumo_sim
    _add_and_depart(conn, "ego", "r_wn")
    take_control(conn, "ego")
    assert conn.vehicle.getSpeedMode("ego") == 32 and conn.vehicle.getLaneChangeMode("ego") == 0
    length = conn.vehicle.getLength("ego")
    internal = [v for v in smap.successors["W2C_2"] if "C2N_0" in smap.successors[v]]
    assert len(internal) == 1 and internal[0].startswith(":C_"), "no internal lane W2C_2 -> C2N_0"
    for lane_id, frac in (("W2C_2", 0.6), (internal[0], 0.6), ("C2N_0", 0.5), ("C2N_0", 0.8)):
        x, y, yaw = _lane_pose(conn, lane_id, frac, length)
        move_vehicle(conn, "ego", x, y, yaw, length, speed_mps=5.0, keep_route=keep_route)
        conn.simulationStep()
        s = read_vehicle_states(conn, ["ego"])
        assert conn.vehicle.getLaneID("ego") == lane_id
        assert math.hypot(s.x_m[0] - x, s.y_m[0] - y) < 0.01, (lane_id, s.x_m[0] - x, s.y_m[0] - y)
        assert _yaw_err_deg(s.yaw_rad[0], yaw) < 0.1, lane_id
        assert s.length_m[0] == pytest.approx(4.8) and s.width_m[0] == pytest.approx(1.9)


def test_round_trip_off_lane_and_speed(libsumo_sim):
    """Exact x,y (keepRoute bit 1) also off the lane centre; speed follows the commanded motion."""
    from r1sim_sumo.adapters.sumo_state import move_vehicle, read_vehicle_states, take_control

    conn = libsumo_sim
    _add_and_depart(conn, "ego", "r_we", depart_pos=5.0)
    take_control(conn, "ego")
    s = read_vehicle_states(conn, ["ego"])
    x, y, yaw = _lane_pose(conn, "W2C_1", 0.2, s.length_m[0])
    y, yaw = y + 0.7, yaw + math.radians(3.0)  # 0.7 m left of lane 1's centre, 3 deg skew
    v = 8.0
    for _ in range(5):
        move_vehicle(conn, "ego", x, y, yaw, s.length_m[0], speed_mps=v, keep_route=2)
        conn.simulationStep()
        s = read_vehicle_states(conn, ["ego"])
        assert math.hypot(s.x_m[0] - x, s.y_m[0] - y) < 0.01
        assert _yaw_err_deg(s.yaw_rad[0], yaw) < 0.1
        x, y = x + v * 0.1 * math.cos(yaw), y + v * 0.1 * math.sin(yaw)
    assert s.speed_mps[0] == pytest.approx(v, abs=0.05)
    np.testing.assert_allclose([s.vx_mps[0], s.vy_mps[0]], [v * math.cos(yaw), v * math.sin(yaw)], atol=0.05)


def test_read_states_all_vehicles_and_types(libsumo_sim):
    from r1sim_sumo.adapters.sumo_state import read_vehicle_states

    conn = libsumo_sim
    empty = read_vehicle_states(conn)
    assert len(empty) == 0 and empty.x_m.shape == (0,)
    _add_and_depart(conn, "car0", "r_we")
    _add_and_depart(conn, "bike0", "r_se", type_id="bike")
    for _ in range(20):
        conn.simulationStep()
    s = read_vehicle_states(conn)
    assert sorted(s.ids.tolist()) == ["bike0", "car0"]
    k = {vid: i for i, vid in enumerate(s.ids.tolist())}
    assert s.agent_type[k["bike0"]] == 1 and s.agent_type[k["car0"]] == 0
    for vid, i in k.items():
        xf, yf = conn.vehicle.getPosition(vid)
        yaw = sumo_angle_deg_to_yaw_rad(conn.vehicle.getAngle(vid))
        xc, yc = front_bumper_to_centre(xf, yf, yaw, conn.vehicle.getLength(vid))
        assert (s.x_m[i], s.y_m[i]) == pytest.approx((xc, yc), abs=1e-9)
        assert s.speed_mps[i] == pytest.approx(conn.vehicle.getSpeed(vid))
        assert s.length_m[i] == pytest.approx(conn.vehicle.getLength(vid))
    assert s.yaw_rad[k["car0"]] == pytest.approx(0.0, abs=1e-6)  # W2C runs east
    assert s.yaw_rad[k["bike0"]] == pytest.approx(math.pi / 2, abs=1e-6)  # S2C runs north
    with pytest.raises(KeyError, match="nope"):
        read_vehicle_states(conn, ["car0", "nope"])
    # a size changed through TraCI gives the vehicle its own type: the static cache must see it
    conn.vehicle.setLength("car0", 7.5)
    conn.simulationStep()
    s2 = read_vehicle_states(conn, ["car0", "bike0"])
    assert s2.length_m.tolist() == pytest.approx([7.5, 1.8])


def test_static_cache_refreshed_on_new_simulation(net_dir):
    """An id reused by a new simulation with another type must not return the old cached size."""
    import libsumo

    from r1sim_sumo._sumo_env import sumo_binary
    from r1sim_sumo.adapters.sumo_state import read_vehicle_states

    args = [sumo_binary("sumo"), "-n", str(net_dir / "t.net.xml"), "-r", str(net_dir / "r.rou.xml"),
            "--step-length", "0.1", "--no-step-log", "--no-warnings"]
    for type_id, length in (("car", 4.8), ("bike", 1.8)):
        libsumo.start(args)
        try:
            _add_and_depart(libsumo, "v", "r_we", type_id=type_id)
            for _ in range(3):
                libsumo.simulationStep()
            assert read_vehicle_states(libsumo).length_m[0] == pytest.approx(length)
        finally:
            libsumo.close()


# ---------------------------------------------------------------------------- TraCI connection


def test_traci_connection_round_trip_and_lights(net_dir, smap):
    import traci

    from r1sim_sumo._sumo_env import sumo_binary
    from r1sim_sumo.adapters.sumo_state import move_vehicle, read_vehicle_states, take_control

    label = f"adapters-test-{id(smap)}"
    traci.start([sumo_binary("sumo"), "-n", str(net_dir / "t.net.xml"), "-r", str(net_dir / "r.rou.xml"),
                 "--step-length", "0.1", "--no-step-log", "--no-warnings"], label=label)
    conn = traci.getConnection(label)
    try:
        _add_and_depart(conn, "ego", "r_wn")
        take_control(conn, "ego")
        length = conn.vehicle.getLength("ego")
        x, y, yaw = _lane_pose(conn, "C2N_0", 0.5, length)
        move_vehicle(conn, "ego", x, y, yaw, length, keep_route=2)
        conn.simulationStep()
        s = read_vehicle_states(conn)
        assert s.ids.tolist() == ["ego"]
        assert math.hypot(s.x_m[0] - x, s.y_m[0] - y) < 0.01 and _yaw_err_deg(s.yaw_rad[0], yaw) < 0.1
        seen = set()
        for _ in range(300):
            conn.simulationStep()
            seen.add(int(smap.tl_states(conn)[smap.lane_index["W2C_1"]]))
        assert {TL_GREEN, TL_RED} <= seen
    finally:
        conn.close()


# ---------------------------------------------------------------------------- bad input


def test_missing_net_file(tmp_path):
    from r1sim_sumo.adapters.sumo_map import MapError, read_sumo_map

    with pytest.raises(MapError, match=r"nope\.net\.xml.*not found"):
        read_sumo_map(tmp_path / "nope.net.xml")
    with pytest.raises(MapError, match="folder"):
        read_sumo_map(tmp_path)


def test_malformed_net_file(tmp_path):
    from r1sim_sumo.adapters.sumo_map import MapError, read_sumo_map

    bad = tmp_path / "bad.net.xml"
    bad.write_text('<net version="1.20"><edge id="a"><lane id="a_0" shape="0,0 1,1"')
    with pytest.raises(MapError, match=r"bad\.net\.xml.*netconvert") as info:
        read_sumo_map(bad)
    assert isinstance(info.value, ValueError)


def test_network_without_drivable_lanes(tmp_path):
    from r1sim_sumo.adapters.sumo_map import MapError, read_sumo_map

    routes = tmp_path / "routes.rou.xml"
    routes.write_text(_ROUTES)
    with pytest.raises(MapError, match="no drivable lanes"):
        read_sumo_map(routes)


# ---------------------------------------------------------------------------- bundled networks


def _distance_to_lanes(pl, xy: np.ndarray) -> np.ndarray:
    """Distance [m] from points ``[N, 2]`` to the nearest lane-centre segment of ``pl``; ``[N]``."""
    a, b = [], []
    for k in np.flatnonzero(pl.kind == LANE_CENTRE):
        p = pl.polyline(k).astype(np.float64)
        a.append(p[:-1])
        b.append(p[1:])
    a, b = np.concatenate(a), np.concatenate(b)  # [S, 2]
    ab = b - a
    t = np.clip(((xy[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12)[None], 0, 1)  # [N, S]
    proj = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(xy[:, None] - proj, axis=-1).min(1)


def _bundled_networks() -> list[str]:
    try:
        from r1sim_sumo.resources import list_networks

        return list_networks()
    except FileNotFoundError:
        return []


@pytest.mark.parametrize("name", _bundled_networks() or [pytest.param(None, marks=pytest.mark.skip("no bundled networks yet"))])
def test_bundled_networks_read_and_validate(name):
    from r1sim_sumo.adapters.sumo_map import read_sumo_map
    from r1sim_sumo.resources import network_files

    try:
        net = network_files(name)["net"]
    except FileNotFoundError as exc:
        pytest.skip(f"bundled network '{name}' not built yet: {exc}")
    m = read_sumo_map(net)
    assert (m.polylines.kind == LANE_CENTRE).sum() == len(m.lane_index) > 0
    assert (m.polylines.kind == ROAD_EDGE).sum() >= 2
    tracks = AgentTracks.empty(1, 91)
    tracks.valid[:] = True
    Scenario(agents=tracks, map=m.polylines, metadata={"source": "sumo", "network": name}).validate(source=net)
    tl = np.zeros((m.num_polylines, 91), np.int8)
    Scenario(agents=tracks, map=m.polylines.with_tl_state(tl), metadata={}).validate(source=net)


def test_turns_off_the_major_road_are_the_roundabouts_exits():
    """``SumoMap.turns_off_major_road``: the internal lanes of the turns from an edge onto one of lower SUMO priority.
    On the bundled roundabout (ring priority 10, arms 5) exactly the 4 exits, checked against sumolib's connections;
    none on urban_grid (every road of one priority), none on the motorways (no turns) and none on eclipse-sumo's
    game/cross (its 8 turns off the major road are signalised)."""
    import sumolib

    from r1sim_sumo.adapters.sumo_map import read_sumo_map
    from r1sim_sumo.resources import network_files

    net_file = network_files("roundabout")["net"]
    exits = set()
    for e in sumolib.net.readNet(str(net_file), withInternal=True).getEdges(withInternal=False):
        for cons in e.getOutgoing().values():
            for c in cons:
                if e.getID().startswith("ring_") and c.getTo().getID().endswith("_out"):
                    exits.add(c.getViaLaneID())
    assert len(exits) == 4
    assert read_sumo_map(net_file).turns_off_major_road == exits
    for name in ("urban_grid", "motorway_merge", "lane_drop"):
        assert read_sumo_map(network_files(name)["net"]).turns_off_major_road == frozenset(), name
    from r1sim_sumo._sumo_env import ensure_sumo_home

    cross = Path(ensure_sumo_home()) / "tools" / "game" / "cross" / "cross.net.xml"
    if cross.exists():
        assert read_sumo_map(cross).turns_off_major_road == frozenset()


@pytest.mark.parametrize("name", _bundled_networks() or [pytest.param(None, marks=pytest.mark.skip("no bundled networks yet"))])
def test_bundled_networks_run_states_and_lights(name):
    """The adapters against each bundled network's own demand: states readable, signals consistent."""
    import libsumo

    from r1sim_sumo._sumo_env import sumo_binary
    from r1sim_sumo.adapters.sumo_map import read_sumo_map
    from r1sim_sumo.adapters.sumo_state import read_vehicle_states
    from r1sim_sumo.resources import network_files

    try:
        files = network_files(name)
    except FileNotFoundError as exc:
        pytest.skip(f"bundled network '{name}' not built yet: {exc}")
    m = read_sumo_map(files["net"])
    libsumo.start([sumo_binary("sumo"), "-c", str(files["sumocfg"]), "--no-step-log", "--no-warnings", "--end", "100"])
    try:
        seen = np.zeros(4, bool)
        n_max = 0
        for _ in range(300):  # 30 s
            libsumo.simulationStep()
            seen[np.unique(m.tl_states(libsumo))] = True
        s = read_vehicle_states(libsumo)
        n_max = len(s)
        assert np.isfinite(s.x_m).all() and (np.abs(s.yaw_rad) <= math.pi).all()
        if n_max:
            # every vehicle's box centre lies within half a lane width of some lane centreline
            d = _distance_to_lanes(m.polylines, np.stack([s.x_m, s.y_m], 1))
            assert (d < 2.5).all(), d.max()
        if m.has_traffic_lights:
            assert seen[TL_GREEN] and seen[TL_RED]
        else:
            assert not seen[[TL_GREEN, TL_YELLOW, TL_RED]].any()
    finally:
        libsumo.close()


def test_lane_speed_ratio_in_a_curve_and_on_a_straight():
    """SUMO's speed is the front bumper's along its lane; with both bumpers on a ring of radius R the box centre runs on
    sqrt(R^2 - L^2 / 4), and the ratio measured from a history equals R over that."""
    from r1sim_sumo.adapters.sumo_state import LANE_SPEED_RATIO_MAX, lane_speed_ratio

    R, v, t = 20.0, 7.0, np.arange(11) * 0.1
    xs, ys = [], []
    for L in (5.0, 12.0):
        th = v * t / R  # the front bumper's angle on the ring [rad], driving at v along the lane
        back = th - 2 * np.arcsin(L / (2 * R))  # the rear bumper on the ring, the chord L behind
        xs.append(R * (np.cos(th) + np.cos(back)) / 2)  # the box centre
        ys.append(R * (np.sin(th) + np.sin(back)) / 2)
    x, y = np.stack(xs), np.stack(ys)
    got = lane_speed_ratio(x, y, np.full_like(x, v), np.ones_like(x, bool))
    want = [R / math.sqrt(R * R - L * L / 4) for L in (5.0, 12.0)]
    np.testing.assert_allclose(got, want, rtol=2e-3)  # (the centre's chords vs its arc: < 0.1%)
    assert got[1] > got[0] > 1.006  # longer vehicles lag more; a car on a 20 m ring by 0.8%
    # a straight road: 1; standing, short or invalid histories: 1; a wild ratio is capped
    xl = np.arange(11)[None] * 0.7
    assert lane_speed_ratio(xl, np.zeros_like(xl), np.full_like(xl, 7.0), np.ones_like(xl, bool))[0] == pytest.approx(1.0)
    still = np.zeros((1, 11))
    assert lane_speed_ratio(still, still, still, np.ones_like(still, bool))[0] == 1.0
    bad = np.ones_like(xl, bool)
    bad[0, 7] = False
    assert lane_speed_ratio(xl, np.zeros_like(xl), np.full_like(xl, 7.0), bad)[0] == 1.0
    assert lane_speed_ratio(xl[:, -3:], np.zeros((1, 3)), np.full((1, 3), 7.0), np.ones((1, 3), bool))[0] == 1.0
    assert lane_speed_ratio(xl, np.zeros_like(xl), np.full_like(xl, 30.0), np.ones_like(xl, bool))[0] == LANE_SPEED_RATIO_MAX
