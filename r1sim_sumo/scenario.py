"""Scenario: a simulator-free traffic scene = map polylines + agent tracks at 10 Hz.

Frame: metres, x east, y north, yaw radians counter-clockwise from +x, positions are box centres.
Time: ``dt_s = 0.1``; a training window has ``N_HISTORY_10HZ = 11`` history states (index 0..10, the
current state is index 10) and ``N_FUTURE_10HZ = 80`` future states: 91 steps in all.

On-disk format (documented in README "Scenario format"): a dataset folder holds ``manifest.json`` and
shards ``shard-XXXXX.npz`` (``numpy.savez_compressed``). Inside a shard, scenario ``i`` stores its
arrays under ``s{i}/agents/<field>`` and a JSON metadata string under ``s{i}/meta``; maps are stored once
per distinct map under ``map/<hash>/<field>`` and referenced by the scenario's ``map_key``. No pickle is
used anywhere (``allow_pickle=False``); strings are stored as fixed-width unicode arrays.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import zipfile
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

DT_S = 0.1
N_HISTORY_10HZ = 11
N_FUTURE_10HZ = 80
N_WINDOW_10HZ = N_HISTORY_10HZ + N_FUTURE_10HZ
CURRENT_INDEX = N_HISTORY_10HZ - 1
FORMAT_VERSION = 1

AGENT_TYPES = ("vehicle", "cyclist", "pedestrian")
VEHICLE, CYCLIST, PEDESTRIAN = 0, 1, 2

# map polyline kinds
LANE_CENTRE, ROAD_EDGE = 0, 1
POLYLINE_KINDS = ("lane_centre", "road_edge")
# traffic-light states per lane per step (for lanes without a signal: TL_NONE)
TL_NONE, TL_GREEN, TL_YELLOW, TL_RED = 0, 1, 2, 3

MAX_ABS_SPEED_MPS = 80.0  # anything above is not a road user (teleport or unit error)
TELEPORT_SPEED_MPS = 100.0  # implied speed between consecutive valid states above this = a teleport jump (10 m per 0.1 s)


class ScenarioError(ValueError):
    """A scenario (or a file holding one) is invalid. The message names the file and field."""


def _where(source: str | os.PathLike | None) -> str:
    return f"{source}: " if source else ""


@dataclass
class AgentTracks:
    """Per-agent tracks, ``A`` agents x ``T`` steps at 10 Hz (invalid steps hold zeros).

    :param ids: ``[A]`` unique string ids (SUMO vehicle id, highway-env index, dataset track id).
    :param agent_type: ``[A]`` int8, 0 vehicle / 1 cyclist / 2 pedestrian.
    :param length_m, width_m: ``[A]`` box size [m].
    :param x_m, y_m: ``[A, T]`` box centre [m]; ``yaw_rad`` ``[A, T]`` heading [rad, CCW from east].
    :param speed_mps: ``[A, T]`` signed longitudinal speed [m/s]; ``vx_mps, vy_mps`` velocity [m/s].
    :param valid: ``[A, T]`` bool, the agent exists at that step.
    :param desired_speed_mps: optional ``[A]`` float32, the speed each driver would drive on a free road [m/s] when
        the simulator knows it (SUMO: the lane limit x the driver's speedFactor, capped by its type's maxSpeed;
        highway-env: ``target_speed``); NaN or ``None`` = unknown, then tokenization estimates it from the track
        (:func:`r1sim_sumo.tokens.matching.hindsight_speed`). Not stored in datasets.
    """

    ids: np.ndarray
    agent_type: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray
    vx_mps: np.ndarray
    vy_mps: np.ndarray
    valid: np.ndarray
    desired_speed_mps: np.ndarray | None = None

    PER_STEP = ("x_m", "y_m", "yaw_rad", "speed_mps", "vx_mps", "vy_mps")
    FIELDS = ("ids", "agent_type", "length_m", "width_m", *PER_STEP, "valid")

    @property
    def num_agents(self) -> int:
        return int(len(self.ids))

    @property
    def num_steps(self) -> int:
        return int(self.valid.shape[1]) if self.valid.ndim == 2 else 0

    @classmethod
    def empty(cls, num_agents: int, num_steps: int) -> AgentTracks:
        z = lambda: np.zeros((num_agents, num_steps), np.float32)  # noqa: E731
        return cls(
            ids=np.array([str(i) for i in range(num_agents)], dtype="<U64"),  # wide: assigned ids are not truncated
            agent_type=np.zeros(num_agents, np.int8),
            length_m=np.full(num_agents, 4.5, np.float32),
            width_m=np.full(num_agents, 1.8, np.float32),
            x_m=z(), y_m=z(), yaw_rad=z(), speed_mps=z(), vx_mps=z(), vy_mps=z(),
            valid=np.zeros((num_agents, num_steps), bool),
        )

    def select(self, idx) -> AgentTracks:
        """Subset of agents by index array or boolean mask."""
        ds = None if self.desired_speed_mps is None else np.asarray(self.desired_speed_mps)[idx]
        return AgentTracks(**{f: getattr(self, f)[idx] for f in self.FIELDS}, desired_speed_mps=ds)

    def slice_steps(self, start: int, stop: int) -> AgentTracks:
        kw = {f: getattr(self, f) for f in ("ids", "agent_type", "length_m", "width_m", "desired_speed_mps")}
        kw.update({f: getattr(self, f)[:, start:stop] for f in (*self.PER_STEP, "valid")})
        return AgentTracks(**kw)

    def astype_canonical(self) -> AgentTracks:
        kw = {
            "ids": np.asarray(self.ids).astype(str),
            "agent_type": np.asarray(self.agent_type, np.int8),
            "length_m": np.asarray(self.length_m, np.float32),
            "width_m": np.asarray(self.width_m, np.float32),
            "valid": np.asarray(self.valid, bool),
        }
        kw.update({f: np.asarray(getattr(self, f), np.float32) for f in self.PER_STEP})
        if self.desired_speed_mps is not None:
            kw["desired_speed_mps"] = np.asarray(self.desired_speed_mps, np.float32)
        return AgentTracks(**kw)


def _edge_of_lane(lane_id: str) -> str:
    """The edge (road) a lane id belongs to: SUMO ``<edge>_<index>``, highway-env ``from->to#index``."""
    return lane_id.rsplit("#", 1)[0] if "->" in lane_id else lane_id.rsplit("_", 1)[0]


@dataclass
class MapPolylines:
    """Map as ``L`` ragged polylines stored flat: polyline ``i`` is ``points_m[start[i]:start[i+1]]``.

    :param points_m: ``[N, 2]`` float32 x, y [m] in the internal frame.
    :param start: ``[L+1]`` int64 offsets into ``points_m``.
    :param kind: ``[L]`` int8, 0 lane centreline (direction of travel) / 1 road edge (boundary).
    :param lane_id: ``[L]`` str, simulator id of the lane (road edges: ``<edge>#left`` / ``#right``).
    :param speed_limit_mps: ``[L]`` float32 [m/s] (0 for road edges).
    :param width_m: ``[L]`` float32 lane width [m] (0 for road edges).
    :param tl_state: ``[L, T]`` int8 traffic-light state per step (0 none, 1 green, 2 yellow, 3 red);
        ``T`` matches the scenario's steps, or 0 columns when the map has no signals.
    :param successors: ``[E, 2]`` int32 lane connectivity (from polyline index, to polyline index).
    """

    points_m: np.ndarray
    start: np.ndarray
    kind: np.ndarray
    lane_id: np.ndarray
    speed_limit_mps: np.ndarray
    width_m: np.ndarray
    tl_state: np.ndarray
    successors: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int32))

    FIELDS = ("points_m", "start", "kind", "lane_id", "speed_limit_mps", "width_m", "tl_state", "successors")

    @property
    def num_polylines(self) -> int:
        return int(len(self.kind))

    def polyline(self, i: int) -> np.ndarray:
        return self.points_m[self.start[i] : self.start[i + 1]]

    def polylines(self) -> Iterator[np.ndarray]:
        for i in range(self.num_polylines):
            yield self.polyline(i)

    @classmethod
    def from_lists(
        cls,
        polylines: list[np.ndarray],
        kind: Iterable[int],
        lane_id: Iterable[str],
        speed_limit_mps: Iterable[float],
        width_m: Iterable[float],
        tl_state: np.ndarray | None = None,
        successors: Iterable[tuple[int, int]] = (),
    ) -> MapPolylines:
        lens = [len(p) for p in polylines]
        start = np.concatenate([[0], np.cumsum(lens)]).astype(np.int64)
        pts = np.concatenate([np.asarray(p, np.float32).reshape(-1, 2) for p in polylines]) if polylines else np.zeros((0, 2), np.float32)
        L = len(polylines)
        succ = np.asarray(list(successors), np.int32).reshape(-1, 2)
        return cls(
            points_m=pts.astype(np.float32),
            start=start,
            kind=np.asarray(list(kind), np.int8),
            lane_id=np.asarray(list(lane_id), dtype=str) if L else np.zeros(0, "<U1"),
            speed_limit_mps=np.asarray(list(speed_limit_mps), np.float32),
            width_m=np.asarray(list(width_m), np.float32),
            tl_state=np.zeros((L, 0), np.int8) if tl_state is None else np.asarray(tl_state, np.int8),
            successors=succ,
        )

    def select(self, idx) -> MapPolylines:
        """The polylines at ``idx`` (index array or boolean mask), in that order; successor pairs between two kept
        polylines are kept (re-indexed), the others dropped."""
        idx = np.arange(self.num_polylines)[idx]
        new = np.full(self.num_polylines, -1, np.int64)
        new[idx] = np.arange(len(idx))
        succ = new[self.successors.astype(np.int64)].reshape(-1, 2)
        return MapPolylines.from_lists([self.polyline(i) for i in idx], self.kind[idx], self.lane_id[idx],
                                       self.speed_limit_mps[idx], self.width_m[idx], self.tl_state[idx],
                                       succ[(succ >= 0).all(1)])

    def ending_lanes(self) -> list[int]:
        """Polyline indices of the lanes that end beside a lane of the same edge that goes on: a vehicle on one has
        to change lanes (motorway_merge's acceleration lane ``merge_0``, lane_drop's dropped lane). Read from the
        connectivity alone: a lane centre (SUMO id ``<edge>_<index>``, internal ``:`` lanes excluded; highway-env
        ``from->to#index``) with no successor whose edge has a lane with one. A map cut without its connectivity
        marks nothing."""
        lanes = [j for j in range(self.num_polylines) if self.kind[j] == LANE_CENTRE and not str(self.lane_id[j]).startswith(":")]
        goes_on = set(np.asarray(self.successors).reshape(-1, 2)[:, 0].tolist())
        edge = {j: _edge_of_lane(str(self.lane_id[j])) for j in lanes}
        edges_going_on = {edge[j] for j in lanes if j in goes_on}
        return [j for j in lanes if j not in goes_on and edge[j] in edges_going_on]

    def with_tl_state(self, tl_state: np.ndarray) -> MapPolylines:
        return MapPolylines(**{**{f: getattr(self, f) for f in self.FIELDS}, "tl_state": np.asarray(tl_state, np.int8)})

    def content_key(self) -> str:
        """Hash of the map's static geometry and attributes (tl_state excluded) for de-duplication."""
        h = hashlib.sha1()
        for f in ("points_m", "start", "kind", "speed_limit_mps", "width_m", "successors"):
            h.update(np.ascontiguousarray(getattr(self, f)).tobytes())
        h.update("\x00".join(self.lane_id.tolist()).encode())
        return h.hexdigest()[:16]

    def bounds(self) -> tuple[float, float, float, float]:
        p = self.points_m
        return float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max())


@dataclass
class Scenario:
    """One scene: agents (``AgentTracks``), map (``MapPolylines``), metadata (JSON-serialisable dict).

    ``metadata`` carries at least ``source`` (``sumo``/``highway-env``/``csv``/``highd``), ``network``,
    ``seed``, ``generator_version``; SUMO windows add ``start_time_s`` and optionally ``state_file``.
    ``current_index`` is the index of the "now" state (10 for standard 11+80 windows).
    """

    agents: AgentTracks
    map: MapPolylines
    metadata: dict = field(default_factory=dict)
    current_index: int = CURRENT_INDEX
    dt_s: float = DT_S

    @property
    def num_steps(self) -> int:
        return self.agents.num_steps

    # ------------------------------------------------------------ validation
    def validate(self, source: str | os.PathLike | None = None, check_jumps: bool = False) -> Scenario:
        """Check shapes, finiteness, yaw/speed ranges, unique ids, a non-empty map. Returns self.

        :param check_jumps: also refuse teleport jumps (a move between consecutive valid states faster than
            ``TELEPORT_SPEED_MPS``); :func:`split_teleports` is the clean-up. Off by default: the bundled
            generators (SUMO, logged CSV/highD) already split teleports into new agents ``<id>~<k>``.
        Raises :class:`ScenarioError` naming ``source`` (file) and the offending field.
        """
        w = _where(source or self.metadata.get("_path"))
        a = self.agents
        A = len(a.ids)
        if A == 0:
            raise ScenarioError(f"{w}agents.ids: scenario has zero agents")
        if a.valid.ndim != 2 or a.valid.shape[0] != A:
            raise ScenarioError(f"{w}agents.valid: expected shape [A={A}, T], got {a.valid.shape}")
        T = a.valid.shape[1]
        for f in ("agent_type", "length_m", "width_m"):
            if np.shape(getattr(a, f)) != (A,):
                raise ScenarioError(f"{w}agents.{f}: expected shape ({A},), got {np.shape(getattr(a, f))}")
        for f in AgentTracks.PER_STEP:
            arr = getattr(a, f)
            if np.shape(arr) != (A, T):
                raise ScenarioError(f"{w}agents.{f}: expected shape ({A}, {T}), got {np.shape(arr)}")
            bad = ~np.isfinite(arr) & a.valid
            if bad.any():
                i, t = np.argwhere(bad)[0]
                raise ScenarioError(f"{w}agents.{f}: non-finite value at agent '{a.ids[i]}' step {t}")
        if len(set(np.asarray(a.ids).tolist())) != A:
            ids = np.asarray(a.ids).tolist()
            dup = sorted({i for i in ids if ids.count(i) > 1})[:5]
            raise ScenarioError(f"{w}agents.ids: duplicated agent ids {dup}")
        if not np.isin(a.agent_type, (VEHICLE, CYCLIST, PEDESTRIAN)).all():
            raise ScenarioError(f"{w}agents.agent_type: values must be 0/1/2 (vehicle/cyclist/pedestrian)")
        if not (np.isfinite(a.length_m).all() and np.isfinite(a.width_m).all()) or (a.length_m <= 0).any() or (a.width_m <= 0).any():
            raise ScenarioError(f"{w}agents.length_m/width_m: sizes must be finite and > 0")
        yaw = np.where(a.valid, a.yaw_rad, 0.0)
        if (np.abs(yaw) > np.pi + 1e-3).any():
            raise ScenarioError(f"{w}agents.yaw_rad: yaw must be wrapped to [-pi, pi] radians (got max |yaw| {np.abs(yaw).max():.3f}); degrees given?")
        spd = np.where(a.valid, a.speed_mps, 0.0)
        if (np.abs(spd) > MAX_ABS_SPEED_MPS).any():
            raise ScenarioError(f"{w}agents.speed_mps: |speed| above {MAX_ABS_SPEED_MPS} m/s (max {np.abs(spd).max():.1f}); km/h given?")
        if not a.valid.any(axis=1).all():
            i = int(np.argmin(a.valid.any(axis=1)))
            raise ScenarioError(f"{w}agents.valid: agent '{a.ids[i]}' is never valid")
        if check_jumps:
            jumps = find_teleports(a, self.dt_s)
            if jumps:
                i, t0, t1, d = jumps[0]
                raise ScenarioError(
                    f"{w}agents.x_m/y_m: agent '{a.ids[i]}' jumps {d:.1f} m between steps {t0} and {t1} "
                    f"(> {TELEPORT_SPEED_MPS:.0f} m/s; {len(jumps)} jump(s) in all): a teleport; split such agents with "
                    "r1sim_sumo.scenario.split_teleports(scenario)"
                )
        if not (0 <= self.current_index < T):
            raise ScenarioError(f"{w}current_index: {self.current_index} outside [0, {T})")
        m = self.map
        L = len(m.kind)
        if L == 0 or len(m.points_m) == 0:
            raise ScenarioError(f"{w}map: empty map (no polylines)")
        if m.points_m.ndim != 2 or m.points_m.shape[1] != 2:
            raise ScenarioError(f"{w}map.points_m: expected shape [N, 2], got {m.points_m.shape}")
        if not np.isfinite(m.points_m).all():
            raise ScenarioError(f"{w}map.points_m: non-finite coordinates")
        if m.start.shape != (L + 1,) or m.start[0] != 0 or m.start[-1] != len(m.points_m) or (np.diff(m.start) < 1).any():
            raise ScenarioError(f"{w}map.start: offsets must be [L+1={L + 1}] increasing from 0 to {len(m.points_m)}")
        for f in ("lane_id", "speed_limit_mps", "width_m"):
            if np.shape(getattr(m, f)) != (L,):
                raise ScenarioError(f"{w}map.{f}: expected shape ({L},), got {np.shape(getattr(m, f))}")
        if not np.isin(m.kind, (LANE_CENTRE, ROAD_EDGE)).all():
            raise ScenarioError(f"{w}map.kind: values must be 0 (lane centre) or 1 (road edge)")
        if m.tl_state.ndim != 2 or m.tl_state.shape[0] != L or m.tl_state.shape[1] not in (0, T):
            raise ScenarioError(f"{w}map.tl_state: expected shape [{L}, {T}] or [{L}, 0], got {m.tl_state.shape}")
        if m.successors.size and ((m.successors < 0).any() or (m.successors >= L).any()):
            raise ScenarioError(f"{w}map.successors: indices outside [0, {L})")
        return self

    # ------------------------------------------------------------ (de)serialisation
    def to_arrays(self, prefix: str, map_prefix: str) -> dict[str, np.ndarray]:
        a = self.agents.astype_canonical()
        out = {f"{prefix}/agents/{f}": getattr(a, f) for f in AgentTracks.FIELDS}
        if a.desired_speed_mps is not None:  # optional: the simulator's desired speeds [m/s]
            out[f"{prefix}/agents/desired_speed_mps"] = np.asarray(a.desired_speed_mps, np.float32)
        meta = dict(self.metadata)
        meta.pop("_path", None)
        meta.update(_map_key=map_prefix, _current_index=int(self.current_index), _dt_s=float(self.dt_s))
        out[f"{prefix}/meta"] = np.array(json.dumps(meta, sort_keys=True))
        # per-scenario tl_state (dynamic), static map stored once per shard
        out[f"{prefix}/tl_state"] = np.asarray(self.map.tl_state, np.int8)
        return out

    def save(self, path: str | os.PathLike) -> Path:
        """Save this one scenario as a single-scenario shard (``.npz``)."""
        return write_shard(path, [self])

    @staticmethod
    def load(path: str | os.PathLike, index: int = 0) -> Scenario:
        """Load scenario ``index`` of a shard file, validated."""
        return read_shard(path, indices=[index])[0]


# ---------------------------------------------------------------------------- teleport jumps


def find_teleports(agents: AgentTracks, dt_s: float = DT_S, max_speed_mps: float = TELEPORT_SPEED_MPS) -> list[tuple[int, int, int, float]]:
    """Teleport jumps: ``(agent index, step before, step after, distance [m])`` for every pair of consecutive
    valid states (invalid steps in between allowed) whose implied speed exceeds ``max_speed_mps``."""
    out = []
    for i in range(len(agents.ids)):
        steps = np.flatnonzero(agents.valid[i])
        if len(steps) < 2:
            continue
        d = np.hypot(np.diff(agents.x_m[i, steps].astype(np.float64)), np.diff(agents.y_m[i, steps].astype(np.float64)))
        bad = np.flatnonzero(d > max_speed_mps * dt_s * np.diff(steps))
        out.extend((i, int(steps[b]), int(steps[b + 1]), float(d[b])) for b in bad)
    return out


def split_teleports(sc: Scenario, max_speed_mps: float = TELEPORT_SPEED_MPS) -> Scenario:
    """Clean-up: each teleport jump starts a new agent ``<id>~<k>`` (the part after the jump), as the SUMO
    generator does; the original agent keeps the part before. Returns a new scenario (``sc`` is unchanged)."""
    a = sc.agents
    jumps = find_teleports(a, sc.dt_s, max_speed_mps)
    if not jumps:
        return sc
    rows: list[tuple[int, int, int, str]] = []  # (source agent, first step, stop step, id)
    by_agent: dict[int, list[int]] = {}
    for i, _t0, t1, _d in jumps:
        by_agent.setdefault(i, []).append(t1)
    T = a.num_steps
    for i in range(len(a.ids)):
        cuts = [0, *by_agent.get(i, []), T]
        for k in range(len(cuts) - 1):
            rows.append((i, cuts[k], cuts[k + 1], str(a.ids[i]) if k == 0 else f"{a.ids[i]}~{k}"))
    src = np.array([r[0] for r in rows])
    new = a.select(src)
    new = AgentTracks(**{f: np.array(getattr(new, f), copy=True) for f in AgentTracks.FIELDS})
    new.ids = np.array([r[3] for r in rows])
    steps = np.arange(T)
    keep = np.stack([(steps >= r[1]) & (steps < r[2]) for r in rows])  # [A', T]
    new.valid = new.valid & keep
    for f in AgentTracks.PER_STEP:
        getattr(new, f)[~new.valid] = 0.0
    has = new.valid.any(1)
    meta = dict(sc.metadata, teleports_split=len(jumps))
    return Scenario(agents=new.select(has), map=sc.map, metadata=meta, current_index=sc.current_index, dt_s=sc.dt_s)


# ---------------------------------------------------------------------------- shards


def _atomic_savez(path: Path, arrays: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp.npz", dir=path.parent)
    os.close(fd)
    try:
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_shard(path: str | os.PathLike, scenarios: list[Scenario], validate: bool = True) -> Path:
    """Write scenarios into one compressed shard, maps de-duplicated; atomic (temp file + rename)."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_suffix(".npz")
    arrays: dict[str, np.ndarray] = {}
    maps_written: set[str] = set()
    for i, sc in enumerate(scenarios):
        if validate:
            sc.validate(source=path)
        key = sc.map.content_key()
        if key not in maps_written:
            for f in MapPolylines.FIELDS:
                if f != "tl_state":
                    arrays[f"map/{key}/{f}"] = np.asarray(getattr(sc.map, f))
            maps_written.add(key)
        arrays.update(sc.to_arrays(f"s{i}", key))
    arrays["format"] = np.array(json.dumps({"format_version": FORMAT_VERSION, "num_scenarios": len(scenarios)}))
    _atomic_savez(path, arrays)
    return path


def _read_npz(path: Path):
    if not path.exists():
        raise ScenarioError(f"{path}: file not found")
    try:
        return np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise ScenarioError(f"{path}: not a readable scenario shard (corrupted or truncated npz: {exc})") from exc


def shard_size(path: str | os.PathLike) -> int:
    path = Path(path)
    with _read_npz(path) as z:
        try:
            return int(json.loads(str(z["format"]))["num_scenarios"])
        except Exception as exc:
            raise ScenarioError(f"{path}: field 'format' missing or unreadable: {exc}") from exc


def read_shard(path: str | os.PathLike, indices: Iterable[int] | None = None, validate: bool = True) -> list[Scenario]:
    """Read (some) scenarios of a shard. Corrupted files raise :class:`ScenarioError` naming file and field."""
    path = Path(path)
    out = []
    with _read_npz(path) as z:
        try:
            fmt = json.loads(str(z["format"]))
        except Exception as exc:
            raise ScenarioError(f"{path}: field 'format' missing or unreadable ({exc}); not a r1sim scenario shard") from exc
        if fmt.get("format_version") != FORMAT_VERSION:
            raise ScenarioError(f"{path}: format_version {fmt.get('format_version')} unsupported (expected {FORMAT_VERSION})")
        n = int(fmt["num_scenarios"])
        idx = range(n) if indices is None else list(indices)
        maps: dict[str, dict] = {}
        for i in idx:
            if not 0 <= i < n:
                raise ScenarioError(f"{path}: scenario index {i} outside [0, {n})")
            try:
                meta = json.loads(str(z[f"s{i}/meta"]))
                key = meta.pop("_map_key")
                if key not in maps:
                    maps[key] = {f: z[f"map/{key}/{f}"] for f in MapPolylines.FIELDS if f != "tl_state"}
                agents = AgentTracks(**{f: z[f"s{i}/agents/{f}"] for f in AgentTracks.FIELDS})
                if f"s{i}/agents/desired_speed_mps" in z:
                    agents.desired_speed_mps = z[f"s{i}/agents/desired_speed_mps"]
                mp = MapPolylines(**maps[key], tl_state=z[f"s{i}/tl_state"])
            except KeyError as exc:
                raise ScenarioError(f"{path}: scenario {i} misses field {exc}") from exc
            except (zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError) as exc:
                raise ScenarioError(f"{path}: scenario {i} unreadable (corrupted data: {exc})") from exc
            ci = int(meta.pop("_current_index", CURRENT_INDEX))
            dt = float(meta.pop("_dt_s", DT_S))
            sc = Scenario(agents=agents, map=mp, metadata=meta, current_index=ci, dt_s=dt)
            if validate:
                sc.validate(source=f"{path}[{i}]")
            out.append(sc)
    return out


# ---------------------------------------------------------------------------- datasets


class ScenarioDataset:
    """A folder of shards + ``manifest.json``; random access by global index, lazy shard loading.

    ``manifest.json``: ``{"format_version", "shards": [{"file", "num_scenarios"}], "num_scenarios", ...}``.
    """

    def __init__(self, root: str | os.PathLike, cache_shards: int = 4):
        self.root = Path(root)
        mpath = self.root / "manifest.json"
        if not mpath.exists():
            raise ScenarioError(f"{mpath}: manifest.json not found; is '{root}' a scenario dataset folder (r1sim generate ...)?")
        try:
            self.manifest = json.loads(mpath.read_text())
            shards = self.manifest["shards"]
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise ScenarioError(f"{mpath}: field 'shards' missing or manifest not valid JSON ({exc})") from exc
        from r1sim_sumo.safe_paths import UnsafePathError, safe_join

        try:  # shard names come from the file: they must stay inside the dataset folder
            self.files = [safe_join(self.root, s["file"], f"manifest field 'shards[{i}].file'", check_symlinks=False) for i, s in enumerate(shards)]
            self.sizes = [int(s["num_scenarios"]) for s in shards]
        except UnsafePathError as exc:
            raise ScenarioError(f"{mpath}: {exc}") from exc
        except (KeyError, TypeError, ValueError) as exc:
            raise ScenarioError(f"{mpath}: field 'shards' entries need 'file' and integer 'num_scenarios' ({type(exc).__name__}: {exc})") from exc
        for f in self.files:
            if not f.exists():
                raise ScenarioError(f"{mpath}: shard '{f.name}' listed but missing; the dataset is incomplete")
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes)]).astype(np.int64)
        self._cache: dict[int, list[Scenario]] = {}
        self._cache_order: list[int] = []
        self._cache_shards = cache_shards

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def _shard(self, k: int) -> list[Scenario]:
        if k not in self._cache:
            self._cache[k] = read_shard(self.files[k])
            self._cache_order.append(k)
            if len(self._cache_order) > self._cache_shards:
                self._cache.pop(self._cache_order.pop(0), None)
        return self._cache[k]

    def __getitem__(self, i: int) -> Scenario:
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(i)
        k = int(np.searchsorted(self.offsets, i, side="right") - 1)
        return self._shard(k)[i - int(self.offsets[k])]

    def __iter__(self) -> Iterator[Scenario]:
        for k in range(len(self.files)):
            yield from self._shard(k)


def write_dataset(root: str | os.PathLike, scenarios: Iterable[Scenario], shard_size: int = 256, extra_manifest: dict | None = None) -> Path:
    """Write scenarios as shards + manifest into ``root`` (created; existing shards there are refused)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    if (root / "manifest.json").exists():
        raise FileExistsError(f"{root / 'manifest.json'} exists: refusing to overwrite a dataset; choose a new folder")
    shards, buf = [], []

    def flush():
        name = f"shard-{len(shards):05d}.npz"
        write_shard(root / name, buf)
        shards.append({"file": name, "num_scenarios": len(buf)})
        buf.clear()

    for sc in scenarios:
        buf.append(sc)
        if len(buf) >= shard_size:
            flush()
    if buf:
        flush()
    manifest = {"format_version": FORMAT_VERSION, "shards": shards, "num_scenarios": sum(s["num_scenarios"] for s in shards)}
    manifest.update(extra_manifest or {})
    write_manifest(root, manifest)
    return root


def write_manifest(root: str | os.PathLike, manifest: dict) -> Path:
    root = Path(root)
    tmp = root / "manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True))
    os.replace(tmp, root / "manifest.json")
    return root / "manifest.json"
