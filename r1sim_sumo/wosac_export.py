"""Export our scenarios and rollouts to the official Waymo Open Sim Agents protos (``Scenario``, ``ScenarioRollouts``).

With them, the official metric (``waymo-open-dataset-tf-2-12-0`` 1.6.7,
``waymo_open_dataset.wdl_limited.sim_agents_metrics.metrics``) scores our rollouts. That package pins TensorFlow 2.13
and numpy 1.23 and is no dependency of r1sim-sumo: install it in a separate virtual environment, where this module
runs without torch (it needs numpy, scipy and shapely only)::

    python3.11 -m venv wosac && wosac/bin/pip install waymo-open-dataset-tf-2-12-0==1.6.7 shapely
    r1sim export-wosac --data DATA --scenes 0,5 --rollouts 32 --out wosac_out        # project env: roll out
    PYTHONPATH=. wosac/bin/python -m r1sim_sumo.wosac_export wosac_out                # venv: write the protos

A *bundle* is two files per scene: ``<id>.scenario.npz`` (the scenario, :meth:`Scenario.save`) and
``<id>.rollouts.npz`` (``x_m, y_m, yaw_rad`` float64 and ``valid`` bool, ``[R, A, 80]``, the scenario's agent order,
step ``t`` = scenario step ``current_index + 1 + t``; internal frame: metres, yaw radians CCW from +x, box centres).

Conversion (WOSAC's conventions: 91 states at 10 Hz, current index 10, 80 simulated steps):

* tracks: every scenario agent, id ``index + 1``; type vehicle / cyclist / pedestrian -> ``TYPE_VEHICLE`` /
  ``TYPE_CYCLIST`` / ``TYPE_PEDESTRIAN``; states centre x, y, z = 0, length, width, height
  :data:`DEFAULT_HEIGHT_M`, heading, velocity, validity. Sim agents (WOSAC: valid at the current step) are all
  evaluated: the first one is the ``sdc_track_index``, the others are ``tracks_to_predict``.
* map: lane centres as ``TYPE_SURFACE_STREET`` lanes (id ``polyline index + 1``); road edges = the boundary rings of our
  drivable area (:func:`r1sim_sumo.metrics.map_features.drivable_area`, union of the buffered lanes), oriented
  counter-clockwise around the road as WOSAC requires (road on the port side), so both metrics measure against the
  same area; our own road-edge polylines are not used (they are SUMO's edge borders and miss junction areas).
* signals: per step, a lane state for each lane with a signal state (green -> ``LANE_STATE_GO``, yellow ->
  ``LANE_STATE_CAUTION``, red -> ``LANE_STATE_STOP``), stop point = the lane's first point (SUMO's signals sit on the
  junction's internal lanes, which start at the stop line).
* rollouts: one ``JointScene`` per rollout with the 80 future states of every sim agent. WOSAC requires every sim
  agent at every step; where our rollout has the agent invalid (SUMO removed it at the end of the network) the last
  valid pose is held.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from r1sim_sumo.metrics.types import MetricsInputError, SimTrajectories
from r1sim_sumo.scenario import LANE_CENTRE, TL_GREEN, TL_RED, TL_YELLOW, Scenario

WOSAC_STEPS = 91
WOSAC_CURRENT_INDEX = 10
WOSAC_SIM_STEPS = 80
DEFAULT_HEIGHT_M = 1.5  # [m] box height written for every agent (our data is 2D)
_TYPE = {0: 1, 1: 3, 2: 2}  # ours (vehicle, cyclist, pedestrian) -> WOMD ObjectType
_TL = {TL_GREEN: 6, TL_YELLOW: 5, TL_RED: 4}  # -> TrafficSignalLaneState.State (GO, CAUTION, STOP)
ROLLOUT_FIELDS = ("x_m", "y_m", "yaw_rad", "valid")


class WosacExportError(ValueError):
    """A scenario or rollout cannot be written in WOSAC's format; the message names the field and the fix."""


def _protos():
    try:
        from waymo_open_dataset.protos import map_pb2, scenario_pb2, sim_agents_submission_pb2
    except ImportError as exc:
        raise ImportError(
            f"writing WOSAC protos needs the official package ({exc}); in a separate environment: "
            "pip install waymo-open-dataset-tf-2-12-0==1.6.7 shapely, then run "
            "`PYTHONPATH=<repo> python -m r1sim_sumo.wosac_export <bundle dir>` there") from exc
    return map_pb2, scenario_pb2, sim_agents_submission_pb2


# ---------------------------------------------------------------------------- bundles


def save_bundle(out_dir: str | Path, scenario_id: str, scenario: Scenario, sim: SimTrajectories) -> tuple[Path, Path]:
    """Write ``<id>.scenario.npz`` and ``<id>.rollouts.npz`` (module doc); returns both paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = sim.checked(scenario)
    sc_path = scenario.save(out / f"{scenario_id}.scenario.npz")
    ro_path = out / f"{scenario_id}.rollouts.npz"
    np.savez_compressed(ro_path, x_m=s.x_m, y_m=s.y_m, yaw_rad=s.yaw_rad, valid=s.valid)
    return sc_path, ro_path


def load_bundle(scenario_path: str | Path) -> tuple[str, Scenario, SimTrajectories]:
    """``(scenario_id, scenario, sim)`` from ``<id>.scenario.npz`` and its ``<id>.rollouts.npz`` beside it."""
    p = Path(scenario_path)
    if not p.name.endswith(".scenario.npz"):
        raise WosacExportError(f"{p}: a bundle's scenario file is named <id>.scenario.npz")
    sid = p.name[: -len(".scenario.npz")]
    ro = p.with_name(f"{sid}.rollouts.npz")
    if not ro.exists():
        raise WosacExportError(f"{ro}: rollouts of {p.name} not found; write bundles with save_bundle / r1sim export-wosac")
    with np.load(ro) as z:
        missing = [f for f in ROLLOUT_FIELDS if f not in z]
        if missing:
            raise WosacExportError(f"{ro}: missing arrays {missing}; expected {ROLLOUT_FIELDS}")
        sim = SimTrajectories(*(np.asarray(z[f]) for f in ROLLOUT_FIELDS))
    sc = Scenario.load(p)
    sim.checked(sc)
    return sid, sc, sim


# ---------------------------------------------------------------------------- conversion


def sim_agent_mask(scenario: Scenario) -> np.ndarray:
    """``[A]`` bool: the agents WOSAC simulates (and we evaluate), valid at the current step."""
    return np.asarray(scenario.agents.valid, bool)[:, scenario.current_index]


def _check_window(scenario: Scenario, where: str) -> None:
    if scenario.current_index != WOSAC_CURRENT_INDEX or scenario.num_steps < WOSAC_STEPS:
        raise WosacExportError(
            f"{where}: WOSAC needs current_index {WOSAC_CURRENT_INDEX} and {WOSAC_STEPS} states, got current_index "
            f"{scenario.current_index} and {scenario.num_steps} states; export standard 11 + 80 windows")
    if abs(scenario.dt_s - 0.1) > 1e-9:
        raise WosacExportError(f"{where}: WOSAC runs at 10 Hz, scenario dt_s is {scenario.dt_s}")


def road_edge_rings(scenario: Scenario) -> list[np.ndarray]:
    """Boundary rings ``[n, 2]`` of our drivable area, closed, oriented with the road on the left (WOSAC)."""
    import shapely

    from r1sim_sumo.metrics.map_features import drivable_area

    area = drivable_area(scenario.map).polygon
    polys = list(area.geoms) if hasattr(area, "geoms") else [area]
    rings = []
    for poly in polys:
        poly = shapely.geometry.polygon.orient(poly, sign=1.0)  # exterior CCW, holes CW: road on the left of both
        rings.append(np.asarray(poly.exterior.coords))
        rings += [np.asarray(r.coords) for r in poly.interiors]
    return rings


def scenario_to_proto(scenario: Scenario, scenario_id: str):
    """The official ``scenario_pb2.Scenario`` of a standard window (module doc)."""
    map_pb2, scenario_pb2, _ = _protos()
    _check_window(scenario, f"scenario {scenario_id}")
    a, mp = scenario.agents, scenario.map
    sim = sim_agent_mask(scenario)
    if not sim.any():
        raise WosacExportError(f"scenario {scenario_id}: no agent is valid at the current step; nothing to simulate")
    out = scenario_pb2.Scenario(scenario_id=scenario_id, current_time_index=WOSAC_CURRENT_INDEX,
                                timestamps_seconds=[0.1 * t for t in range(WOSAC_STEPS)])
    for i in range(a.num_agents):
        tr = out.tracks.add(id=i + 1, object_type=_TYPE[int(a.agent_type[i])])
        for t in range(WOSAC_STEPS):
            ok = bool(a.valid[i, t])
            tr.states.add(center_x=float(a.x_m[i, t]), center_y=float(a.y_m[i, t]), center_z=0.0,
                          length=float(a.length_m[i]), width=float(a.width_m[i]), height=DEFAULT_HEIGHT_M,
                          heading=float(a.yaw_rad[i, t]), velocity_x=float(a.vx_mps[i, t]),
                          velocity_y=float(a.vy_mps[i, t]), valid=ok)
    idx = np.flatnonzero(sim)
    out.sdc_track_index = int(idx[0])
    for i in idx[1:]:
        out.tracks_to_predict.add(track_index=int(i))
    lanes = [i for i in range(mp.num_polylines) if int(mp.kind[i]) == LANE_CENTRE]
    for i in lanes:
        mf = out.map_features.add(id=i + 1)
        mf.lane.type = map_pb2.LaneCenter.TYPE_SURFACE_STREET
        for x, y in mp.polyline(i):
            mf.lane.polyline.add(x=float(x), y=float(y), z=0.0)
    next_id = mp.num_polylines + 1
    for ring in road_edge_rings(scenario):
        mf = out.map_features.add(id=next_id)
        next_id += 1
        mf.road_edge.type = map_pb2.RoadEdge.TYPE_ROAD_EDGE_BOUNDARY
        for x, y in ring:
            mf.road_edge.polyline.add(x=float(x), y=float(y), z=0.0)
    tl = np.asarray(mp.tl_state)
    has_tl = tl.ndim == 2 and tl.shape[1] >= WOSAC_STEPS
    for t in range(WOSAC_STEPS):
        dms = out.dynamic_map_states.add()
        if not has_tl:
            continue
        for i in lanes:
            st = _TL.get(int(tl[i, t]))
            if st is not None:
                p0 = mp.polyline(i)[0]
                ls = dms.lane_states.add(lane=i + 1, state=st)
                ls.stop_point.x, ls.stop_point.y, ls.stop_point.z = float(p0[0]), float(p0[1]), 0.0
    return out


def _held(values: np.ndarray, valid: np.ndarray, start: np.ndarray) -> np.ndarray:
    """``[R, A, T]`` values with invalid steps holding the last valid one (``start [A]`` before step 0)."""
    out = np.array(values, np.float64)
    last = np.broadcast_to(np.asarray(start, np.float64)[None], out.shape[:2]).copy()
    for t in range(out.shape[2]):
        last = np.where(valid[..., t], out[..., t], last)
        out[..., t] = last
    return out


def rollouts_to_proto(scenario: Scenario, sim: SimTrajectories, scenario_id: str):
    """The official ``ScenarioRollouts`` of ``R`` rollouts (80 future steps of every sim agent; module doc)."""
    _, _, sub = _protos()
    _check_window(scenario, f"scenario {scenario_id}")
    s = sim.checked(scenario)
    if s.num_steps != WOSAC_SIM_STEPS:
        raise WosacExportError(f"rollouts of {scenario_id}: {s.num_steps} future steps, WOSAC needs {WOSAC_SIM_STEPS}")
    a, ci = scenario.agents, scenario.current_index
    x = _held(s.x_m, s.valid, a.x_m[:, ci])
    y = _held(s.y_m, s.valid, a.y_m[:, ci])
    yaw = _held(s.yaw_rad, s.valid, a.yaw_rad[:, ci])
    out = sub.ScenarioRollouts(scenario_id=scenario_id)
    idx = np.flatnonzero(sim_agent_mask(scenario))
    for r in range(s.num_rollouts):
        js = out.joint_scenes.add()
        for i in idx:
            js.simulated_trajectories.add(center_x=x[r, i].tolist(), center_y=y[r, i].tolist(),
                                          center_z=[0.0] * WOSAC_SIM_STEPS, heading=yaw[r, i].tolist(),
                                          object_id=int(i) + 1)
    return out


def export_dir(bundle_dir: str | Path, out_dir: str | Path | None = None) -> list[Path]:
    """Write ``<id>.scenario.pb`` and ``<id>.rollouts.pb`` (serialized protos) for every bundle in ``bundle_dir``."""
    src = Path(bundle_dir)
    out = Path(out_dir) if out_dir else src
    out.mkdir(parents=True, exist_ok=True)
    files = sorted(src.glob("*.scenario.npz"))
    if not files:
        raise WosacExportError(f"{src}: no <id>.scenario.npz bundles; write them with `r1sim export-wosac`")
    written = []
    for f in files:
        sid, sc, sim = load_bundle(f)
        for name, msg in (("scenario", scenario_to_proto(sc, sid)), ("rollouts", rollouts_to_proto(sc, sim, sid))):
            p = out / f"{sid}.{name}.pb"
            p.write_bytes(msg.SerializeToString())
            written.append(p)
    return written


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) not in (1, 2):
        print("usage: python -m r1sim_sumo.wosac_export BUNDLE_DIR [OUT_DIR]", file=sys.stderr)
        return 2
    try:
        paths = export_dir(*args)
    except (WosacExportError, MetricsInputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {len(paths)} proto files to {Path(args[-1])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
