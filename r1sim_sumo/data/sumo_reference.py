"""SUMO runs -> reference scenarios: 91-step windows (11 history + 80 future at 10 Hz) of recorded traffic.

One job = one (network, seed) simulation, described by :class:`SumoGenConfig`:

1. **Demand** (deterministic for a seed): the network's default ``.rou.xml`` (bundled networks ship
   calibrated Poisson flows ``period="exp(rate)"`` over a mixed ``vTypeDistribution`` of Krauss/IDM cars,
   trucks and buses with ``sigma > 0``) is copied with every flow rate multiplied by
   ``demand_scale * U(demand_jitter)``, the factor drawn from ``numpy.random.default_rng(seed)``, flow
   ends stretched to the end of the run and, optionally, the vType probabilities replaced
   (``vtype_probabilities``). SUMO's ``--seed`` then draws arrival times, vehicle types, desired speeds
   (``speedFactor``) and driver imperfection. Flows keep the network's plausible origin/destination
   routes, which random trips on small networks would not.
2. **Simulation**: libsumo started by :func:`r1sim_sumo.sumo_launch.sumo_command` (``--step-length 0.1``,
   ``--seed``, ``--collision.action warn``), no GUI.
   ``warmup_s`` of filling the network, then ``duration_s`` recorded: every step all vehicles
   (:func:`~r1sim_sumo.adapters.sumo_state.read_vehicle_states`, box centre, yaw CCW from east) and the
   per-lane traffic-light states (:meth:`~r1sim_sumo.adapters.sumo_map.SumoMap.tl_states`).
3. **Windows**: every ``stride_steps`` a window of 91 steps starts; its agents are the vehicles present at
   the current index 10, with ``valid`` false where a vehicle has not entered yet or has left. A vehicle
   that vanishes and reappears (teleport) or jumps more than ``MAX_JUMP_M`` in one step starts a new
   track ``<id>~<k>``. The map is the network's polylines with ``tl_state [L, 91]`` of the window.

Metadata of each scenario: ``source="sumo"``, ``network``, ``seed``, ``generator_version``,
``start_time_s`` (SUMO time of index 0), ``window_index``, ``stride_steps``, ``demand_factor``; with
``save_states`` also ``state_file`` (path relative to the dataset folder) and ``state_time_s``: a SUMO
state (``simulation.saveState``, RNG included) taken at the window's *current* index 10, i.e. the moment a
closed-loop rollout takes over; ``simulation.loadState(root / state_file)`` restores it.

Parallel generation (:func:`r1sim_sumo.data.dataset.generate_sumo_dataset`) runs each job in its own process
(libsumo holds one simulation per process).
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from r1sim_sumo import resources
from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.adapters.sumo_map import read_sumo_map
from r1sim_sumo.adapters.sumo_state import read_desired_speeds, read_vehicle_states
from r1sim_sumo.data.close_ups import CloseUpInjector, CloseUpSettings
from r1sim_sumo.data.desired_steps import DesiredStepInjector, DesiredStepSettings
from r1sim_sumo.data.policy_history import (
    LABEL_FROM_TOKEN,
    PolicyHistorySettings,
    PolicyPhases,
    phase_schedule,
)
from r1sim_sumo.data.slowdowns import SlowdownInjector, SlowdownSettings
from r1sim_sumo.safe_paths import safe_join, safe_name
from r1sim_sumo.scenario import (
    CURRENT_INDEX,
    DT_S,
    N_WINDOW_10HZ,
    AgentTracks,
    MapPolylines,
    Scenario,
)
from r1sim_sumo.sumo_launch import STEP_LENGTH_S, settle_remote_control, sumo_command

GENERATOR_VERSION = "sumo-reference/2"  # 2: each window records SUMO's desired speed per vehicle (session 17)
MAX_JUMP_M = 10.0  # a larger move within one 0.1 s step (100 m/s) is a teleport: start a new track

ProgressFn = Callable[[float], None]  # called with simulated seconds done since the last call


class SumoGenerationError(RuntimeError):
    """A SUMO reference-generation job could not run; the message names the network, seed and cause."""


@dataclass
class SumoGenConfig:
    """One SUMO reference-generation job: a (network, seed) simulation cut into windows.

    :param network: bundled network name (``r1sim_sumo.resources.list_networks()``) or the path of a folder
        holding one ``.net.xml``, one ``.sumocfg`` and the default demand ``.rou.xml``.
    :param seed: SUMO ``--seed`` and the seed of the demand factor draw.
    :param duration_s: recorded simulated time [s] after the warm-up.
    :param warmup_s: simulated time [s] run before recording so the network is filled.
    :param stride_steps: steps [0.1 s] between the starts of consecutive windows (20 = 2 s).
    :param demand_scale: multiplies every flow rate of the default demand.
    :param demand_jitter: per-seed multiplicative factor on demand, drawn uniformly in ``[lo, hi]``.
    :param vtype_probabilities: ``{vType id: probability}`` replacing those of the default demand's
        ``vTypeDistribution`` (ids not listed keep theirs); ``None`` keeps the network's mix.
    :param lateral_resolution_m: ``None`` = lane-based LC2013 lane changes; a value [m] enables the
        sublane model (``--lateral-resolution``; vTypes then use SL2015).
    :param lanechange_duration_s: SUMO ``--lanechange.duration`` [s]: 0 (SUMO's default) = a lane change is a jump of
        one lane width within one 0.1 s step; > 0 = the vehicle moves across continuously over that time, as a real
        vehicle does (what 0.5 s motion tokens can follow). Ignored with the sublane model.
    :param overtake_right: SUMO ``--lanechange.overtake-right true``: vehicles may pass on the right on motorways.
        SUMO's default forbids it (LC2013 holds a vehicle behind a slower one in the lane to its left), so a vehicle
        with its own lane free often keeps a steady speed well below its desired one; with the rule off, a free lane
        means speeding up more often (lane_drop: free below-allowed vehicle-states steady over 2 s 25% -> 6%,
        ``scripts/free_lane_holds.py``, session 27).
    :param save_states: save a SUMO state file at each window's current index (see module doc).
    :param time_to_teleport_s: SUMO ``--time-to-teleport`` [s] (gridlock breaker; <= 0 disables).
    :param min_agents: windows with fewer vehicles at the current index are skipped.
    :param slowdowns_per_vehicle_hour: random brake-hold-release events per vehicle and hour
        (:mod:`r1sim_sumo.data.slowdowns`; 0 = none), so the data shows vehicles recovering speed.
    :param slowdown_hold_s: ``(lo, hi)`` seconds a slowed vehicle holds its low speed before SUMO drives again.
    :param depart_speed: SUMO ``departSpeed`` for every flow of the demand (e.g. ``"random"``: uniform up to the
        lane's limit, so vehicles enter slow and speed up on a free road); ``None`` keeps the network's.
    :param close_ups_per_vehicle_hour: random tailgate-then-reopen events per vehicle and hour
        (:mod:`r1sim_sumo.data.close_ups`; 0 = none), so the data shows followers closing up and braking when too close.
    :param desired_steps_per_vehicle_hour: random lower-then-restore steps of a driver's speedFactor per vehicle and hour
        (:mod:`r1sim_sumo.data.desired_steps`; 0 = none), so the data shows drivers speeding up from a steady speed
        below their desired one.
    :param desired_step_factor: ``(lo, hi)`` multiplier of the driver's own speedFactor in the low phase.
    :param desired_step_hold_s: ``(lo, hi)`` seconds of the low phase.
    :param policy_history: a policy (``load_policy`` name or checkpoint folder) that drives every vehicle between
        windows; each window's history is then the policy's driving and its future SUMO's recovery from there
        (:mod:`r1sim_sumo.data.policy_history`; windows at the hand-overs instead of every ``stride_steps``).
    :param policy_history_s: ``(lo, hi)`` seconds of each policy phase.
    :param policy_history_drive: ``commands`` or ``position``, the drop-in drive the policy phases use.
    """

    network: str
    seed: int = 0
    duration_s: float = 600.0
    warmup_s: float = 120.0
    stride_steps: int = 20
    demand_scale: float = 1.0
    demand_jitter: tuple[float, float] = (0.7, 1.3)
    vtype_probabilities: dict[str, float] | None = None
    lateral_resolution_m: float | None = None
    lanechange_duration_s: float = 0.0
    overtake_right: bool = False
    save_states: bool = False
    time_to_teleport_s: float = 300.0
    min_agents: int = 1
    slowdowns_per_vehicle_hour: float = 0.0
    slowdown_hold_s: tuple[float, float] = (0.0, 4.0)
    depart_speed: str | None = None
    close_ups_per_vehicle_hour: float = 0.0
    desired_steps_per_vehicle_hour: float = 0.0
    desired_step_factor: tuple[float, float] = (0.55, 0.9)
    desired_step_hold_s: tuple[float, float] = (4.0, 12.0)
    policy_history: str | None = None
    policy_history_s: tuple[float, float] = (4.0, 16.0)
    policy_history_drive: str = "commands"

    def __post_init__(self) -> None:
        where = f"SumoGenConfig(network={self.network!r}, seed={self.seed})"
        try:  # the slow-down, close-up and policy-phase settings are checked here, not first when the run starts
            self.slowdown_settings()
            self.close_up_settings()
            self.desired_step_settings()
            self.policy_history_settings()
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        if self.duration_s * 10 < N_WINDOW_10HZ:
            raise ValueError(f"{where}.duration_s: {self.duration_s} s is shorter than one window "
                             f"({N_WINDOW_10HZ * DT_S:.1f} s); use >= {N_WINDOW_10HZ * DT_S:.1f}")
        if self.warmup_s < 0:
            raise ValueError(f"{where}.warmup_s: must be >= 0, got {self.warmup_s}")
        if self.lanechange_duration_s < 0:
            raise ValueError(f"{where}.lanechange_duration_s: must be >= 0 (0 = SUMO's instant lane changes), got "
                             f"{self.lanechange_duration_s}")
        if self.stride_steps < 1:
            raise ValueError(f"{where}.stride_steps: must be >= 1, got {self.stride_steps}")
        if self.demand_scale <= 0 or not (0 < self.demand_jitter[0] <= self.demand_jitter[1]):
            raise ValueError(f"{where}.demand_scale/demand_jitter: need scale > 0 and 0 < lo <= hi, got "
                             f"{self.demand_scale}, {self.demand_jitter}")
        self.demand_jitter = (float(self.demand_jitter[0]), float(self.demand_jitter[1]))

    def slowdown_settings(self) -> SlowdownSettings:
        return SlowdownSettings(self.slowdowns_per_vehicle_hour, hold_s=tuple(self.slowdown_hold_s))

    def close_up_settings(self) -> CloseUpSettings:
        return CloseUpSettings(self.close_ups_per_vehicle_hour)

    def desired_step_settings(self) -> DesiredStepSettings:
        return DesiredStepSettings(self.desired_steps_per_vehicle_hour, tuple(self.desired_step_factor),
                                   tuple(self.desired_step_hold_s))

    def policy_history_settings(self) -> PolicyHistorySettings | None:
        if not self.policy_history:
            return None
        return PolicyHistorySettings(str(self.policy_history), tuple(self.policy_history_s), drive=self.policy_history_drive)

    # ---- job protocol used by r1sim_sumo.data.dataset.run_generation_jobs
    @property
    def network_name(self) -> str:
        return Path(self.network).name

    @property
    def key(self) -> tuple:
        """Sort key: output order is by (source, network, seed) whatever the completion order."""
        return ("sumo", self.network_name, int(self.seed))

    @property
    def label(self) -> str:
        return f"{self.network_name}__seed{int(self.seed):05d}"

    @property
    def sim_seconds(self) -> float:
        return float(self.warmup_s + self.duration_s)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def generate(self, state_root: Path | None = None, progress: ProgressFn | None = None,
                 stats: RunStats | None = None) -> Iterator[Scenario]:
        return iter_sumo_scenarios(self, state_root=state_root, progress=progress, stats=stats)

    def num_windows(self) -> int:
        """Upper bound on the number of windows (windows with too few agents are skipped)."""
        n_rec = int(round(self.duration_s / STEP_LENGTH_S))
        ph = self.policy_history_settings()
        if ph is not None:
            return len(phase_schedule(n_rec, ph, self.seed)[1])
        return max(0, (n_rec - N_WINDOW_10HZ) // self.stride_steps + 1)


# ---------------------------------------------------------------------------- network files + demand


@dataclass
class NetworkSource:
    name: str
    net_file: Path
    sumocfg: Path
    route_file: Path


def resolve_network(network: str) -> NetworkSource:
    """Bundled network name or folder path -> its ``.net.xml``, ``.sumocfg`` and default ``.rou.xml``."""
    p = Path(network)
    if p.is_dir():
        folder = p
    else:
        try:
            folder = resources.network_path(network)
        except FileNotFoundError as exc:
            raise SumoGenerationError(f"network '{network}': not a bundled network nor a folder ({exc})") from exc

    def one(pattern: str) -> Path:
        found = sorted(folder.glob(pattern))
        if not found:
            raise SumoGenerationError(f"network '{network}': folder {folder} has no {pattern} file; a network "
                                      "folder needs a .net.xml, a .sumocfg and a default demand .rou.xml")
        return found[0]

    return NetworkSource(folder.name, one("*.net.xml"), one("*.sumocfg"), one("*.rou.xml"))


def demand_factor(config: SumoGenConfig) -> float:
    """Multiplier on the default demand for this config: ``demand_scale * U(lo, hi)`` drawn from the seed."""
    rng = np.random.default_rng([int(config.seed), 0x5D3A])
    lo, hi = config.demand_jitter
    return float(config.demand_scale * rng.uniform(lo, hi))


def _scale_period(value: str, factor: float, where: str) -> str:
    v = value.strip()
    if v.startswith("exp(") and v.endswith(")"):  # Poisson arrivals, rate in veh/s
        return f"exp({float(v[4:-1]) * factor:.6g})"
    try:
        return f"{float(v) / factor:.6g}"
    except ValueError as exc:
        raise SumoGenerationError(f"{where}: flow period '{value}' not understood (expected a number or "
                                  "'exp(rate)')") from exc


def write_scaled_demand(src: Path, dst: Path, factor: float, end_s: float,
                        vtype_probabilities: dict[str, float] | None = None,
                        lateral_resolution_m: float | None = None, depart_speed: str | None = None) -> Path:
    """Copy the route file ``src`` to ``dst`` with every flow's rate multiplied by ``factor``.

    Flows: ``period`` (number or ``exp(rate)``), ``vehsPerHour``, ``probability`` (capped at 1) and
    ``number`` are scaled; ``end`` is stretched to ``end_s`` [s] so long runs keep their demand.
    ``vtype_probabilities`` overrides vType ``probability`` attributes by id; with a lateral resolution
    the vTypes get ``lcModel="SL2015"``. ``depart_speed`` replaces every flow's, vehicle's and trip's
    ``departSpeed`` (SUMO's values: ``"random"``, ``"max"``, ``"desired"``, a number [m/s], ...).
    """
    try:
        tree = ET.parse(src)
    except ET.ParseError as exc:
        raise SumoGenerationError(f"{src}: not valid XML ({exc}); repair the network's default demand") from exc
    root = tree.getroot()
    known = set()
    for vt in root.iter("vType"):
        known.add(vt.get("id"))
        if vtype_probabilities and vt.get("id") in vtype_probabilities:
            vt.set("probability", f"{float(vtype_probabilities[vt.get('id')]):.6g}")
        if lateral_resolution_m is not None:
            vt.set("lcModel", "SL2015")
    unknown = set(vtype_probabilities or {}) - known
    if unknown:
        raise SumoGenerationError(f"{src}: vtype_probabilities names vTypes {sorted(unknown)} that the demand "
                                  f"does not define; known: {sorted(known)}")
    for fl in root.iter("flow"):
        where = f"{src}: flow '{fl.get('id')}'"
        if fl.get("period") is not None:
            fl.set("period", _scale_period(fl.get("period"), factor, where))
        elif fl.get("vehsPerHour") is not None:
            fl.set("vehsPerHour", f"{float(fl.get('vehsPerHour')) * factor:.6g}")
        elif fl.get("probability") is not None:
            fl.set("probability", f"{min(1.0, float(fl.get('probability')) * factor):.6g}")
        if fl.get("number") is not None:
            fl.set("number", str(max(1, int(round(int(fl.get("number")) * factor)))))
        elif fl.get("end") is not None and float(fl.get("end")) < end_s:
            fl.set("end", f"{end_s:.1f}")
    if depart_speed is not None:
        for tag in ("flow", "vehicle", "trip"):
            for el in root.iter(tag):
                el.set("departSpeed", str(depart_speed))
    tree.write(dst, encoding="UTF-8", xml_declaration=True)
    return dst


def generation_command(src: NetworkSource, route_file: Path, config: SumoGenConfig) -> list[str]:
    """Command line for libsumo.start (:func:`r1sim_sumo.sumo_launch.sumo_command`): the network's .sumocfg with
    our demand and settings overriding it."""
    extra = ["--lateral-resolution", f"{config.lateral_resolution_m}"] if config.lateral_resolution_m is not None else []
    if config.lanechange_duration_s > 0 and config.lateral_resolution_m is None:
        extra += ["--lanechange.duration", f"{config.lanechange_duration_s}"]
    if config.overtake_right:
        extra += ["--lanechange.overtake-right", "true"]
    return sumo_command(config.seed, sumocfg=src.sumocfg, route_files=route_file,
                        end_s=config.warmup_s + config.duration_s + 1.0, time_to_teleport_s=config.time_to_teleport_s,
                        save_state_rng=config.save_states, extra=extra)


class SumoStateError(ValueError):
    """A scenario cannot be restored in SUMO (no state file, unknown network); the message names the fix."""


def sumo_vehicle_id(track_id: str) -> str:
    """Scenario track id -> SUMO vehicle id (a reappearing vehicle's track ``<id>~<k>`` is SUMO's ``<id>``)."""
    return str(track_id).split("~", 1)[0]


def scenario_sumo_files(scenario, root: str | os.PathLike, where: str = "") -> tuple[str, str]:
    """``(net_file, absolute state_file)`` of a scenario generated with ``save_states``; clear error otherwise."""
    meta = scenario.metadata
    rel = meta.get("state_file")
    if not rel:
        raise SumoStateError(f"{where or 'scenario'}: metadata field 'state_file' missing; SUMO-in-the-loop rollouts need a "
                             "dataset generated with `r1sim generate sumo --save-states` (or SumoGenConfig(save_states=True))")
    state = Path(root) / rel
    if not state.exists():
        raise SumoStateError(f"{where or 'scenario'}: state file {state} (metadata 'state_file') not found under the dataset folder {root}")
    try:
        net = resolve_network(str(meta.get("network", ""))).net_file
    except SumoGenerationError as exc:
        raise SumoStateError(f"{where or 'scenario'}: metadata 'network' = {meta.get('network')!r}: {exc}") from exc
    return str(net), str(state)


# ---------------------------------------------------------------------------- recording


class TrackRecorder:
    """Long-form recording of all vehicles at every step; cut into windows afterwards.

    Rows are appended per step (sorted by step), so a window is a contiguous row range. Per row:
    ``track`` index and the per-step fields of :class:`~r1sim_sumo.scenario.AgentTracks`.
    """

    FIELDS = AgentTracks.PER_STEP  # x_m, y_m, yaw_rad, speed_mps, vx_mps, vy_mps

    def __init__(self) -> None:
        self.track_ids: list[str] = []
        self.agent_type: list[int] = []
        self.length_m: list[float] = []
        self.width_m: list[float] = []
        self._track_of: dict[str, int] = {}  # vehicle id -> its latest track
        self._n_tracks_of: dict[str, int] = {}
        # per track: last step seen and last centre [m] (capacity grows by doubling)
        self._last_step = np.full(256, -2, np.int64)
        self._last_xy = np.zeros((256, 2), np.float64)
        self._chunks: dict[str, list[np.ndarray]] = {f: [] for f in ("track", *self.FIELDS, "desired")}
        self._step_rows: list[int] = []
        self._tl: list[np.ndarray] = []
        self.num_steps = 0

    def _new_track(self, vid: str, states, i: int) -> int:
        k = len(self.track_ids)
        m = self._n_tracks_of.get(vid, 0)
        self._n_tracks_of[vid] = m + 1
        self._track_of[vid] = k
        self.track_ids.append(vid if m == 0 else f"{vid}~{m}")
        self.agent_type.append(int(states.agent_type[i]))
        self.length_m.append(float(states.length_m[i]))
        self.width_m.append(float(states.width_m[i]))
        if k >= len(self._last_step):
            self._last_step = np.concatenate([self._last_step, np.full(len(self._last_step), -2, np.int64)])
            self._last_xy = np.concatenate([self._last_xy, np.zeros_like(self._last_xy)])
        return k

    def add(self, states, tl_state: np.ndarray, desired_mps: np.ndarray | None = None) -> None:
        """Append one step: ``states`` (VehicleStates of all vehicles), ``tl_state`` ``[L]`` and each vehicle's desired
        speed ``[n]`` [m/s] (:func:`~r1sim_sumo.adapters.sumo_state.read_desired_speeds`; ``None``: unknown, NaN).

        A vehicle continues its track when it was seen at the previous step within ``MAX_JUMP_M``;
        otherwise (first sighting, reappearance after a teleport, jump) it starts a new track.
        """
        step = self.num_steps
        ids = np.asarray(states.ids).tolist()
        n = len(ids)
        xy = np.stack([np.asarray(states.x_m, np.float64), np.asarray(states.y_m, np.float64)], -1).reshape(n, 2)  # [n, 2]
        track = np.fromiter((self._track_of.get(v, -1) for v in ids), np.int64, n)  # [n], -1 = unknown
        known = track >= 0
        cont = known.copy()
        tk = track[known]
        cont[known] = (self._last_step[tk] == step - 1) & (
            np.hypot(*(xy[known] - self._last_xy[tk]).T) <= MAX_JUMP_M)
        for i in np.flatnonzero(~cont).tolist():
            track[i] = self._new_track(ids[i], states, i)
        self._last_step[track] = step
        self._last_xy[track] = xy
        self._chunks["track"].append(track.astype(np.int32))
        for f in self.FIELDS:
            self._chunks[f].append(np.asarray(getattr(states, f), np.float32))
        self._chunks["desired"].append(np.full(n, np.nan, np.float32) if desired_mps is None
                                       else np.asarray(desired_mps, np.float32).reshape(n))
        self._step_rows.append(n)
        self._tl.append(np.asarray(tl_state, np.int8))
        self.num_steps += 1

    @property
    def num_rows(self) -> int:
        return int(sum(self._step_rows))

    def finish(self) -> RecordedRun:
        cat = {f: (np.concatenate(c) if c else np.zeros(0, np.float32)) for f, c in self._chunks.items()}
        return RecordedRun(
            track_ids=np.asarray(self.track_ids, dtype=str),
            agent_type=np.asarray(self.agent_type, np.int8),
            length_m=np.asarray(self.length_m, np.float32),
            width_m=np.asarray(self.width_m, np.float32),
            track=cat.pop("track").astype(np.int32),
            fields={f: cat[f] for f in self.FIELDS},
            desired=cat["desired"],
            step_offsets=np.concatenate([[0], np.cumsum(self._step_rows)]).astype(np.int64),
            tl_state=np.stack(self._tl) if self._tl else np.zeros((0, 0), np.int8),
        )


@dataclass
class RecordedRun:
    """A finished recording. ``track`` ``[R]``, ``fields[f]`` ``[R]`` and ``desired`` ``[R]`` (desired speed [m/s],
    NaN unknown) are rows sorted by step; step ``t`` owns rows ``step_offsets[t]:step_offsets[t+1]``; ``tl_state``
    ``[S, L]``."""

    track_ids: np.ndarray
    agent_type: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray
    track: np.ndarray
    fields: dict[str, np.ndarray]
    step_offsets: np.ndarray
    tl_state: np.ndarray
    desired: np.ndarray | None = None

    @property
    def num_steps(self) -> int:
        return len(self.step_offsets) - 1

    def window(self, start: int, num_steps: int = N_WINDOW_10HZ, current: int = CURRENT_INDEX) -> AgentTracks | None:
        """Tracks of the vehicles present at step ``start + current``, over ``[start, start + num_steps)``; their
        ``desired_speed_mps`` is SUMO's at the current step (what the drop-in controller hands the policy)."""
        c0, c1 = self.step_offsets[start + current], self.step_offsets[start + current + 1]
        order = np.argsort(self.track[c0:c1], kind="stable")
        agents = self.track[c0:c1][order]  # [A] track indices, insertion order
        if len(agents) == 0:
            return None
        lut = np.full(len(self.track_ids), -1, np.int64)
        lut[agents] = np.arange(len(agents))
        r0, r1 = self.step_offsets[start], self.step_offsets[start + num_steps]
        slot = lut[self.track[r0:r1]]  # [R]
        step = np.searchsorted(self.step_offsets, np.arange(r0, r1), side="right") - 1 - start  # [R]
        keep = slot >= 0
        slot, step = slot[keep], step[keep]
        A = len(agents)
        out = {}
        for f, arr in self.fields.items():
            a = np.zeros((A, num_steps), np.float32)  # [A, T]
            a[slot, step] = arr[r0:r1][keep]
            out[f] = a
        valid = np.zeros((A, num_steps), bool)  # [A, T]
        valid[slot, step] = True
        desired = None
        if self.desired is not None:
            d = self.desired[c0:c1][order]
            desired = d if np.isfinite(d).any() else None
        return AgentTracks(ids=self.track_ids[agents], agent_type=self.agent_type[agents],
                           length_m=self.length_m[agents], width_m=self.width_m[agents], valid=valid,
                           desired_speed_mps=desired, **out)


def window_starts(num_steps: int, stride_steps: int, window_steps: int = N_WINDOW_10HZ) -> range:
    """Start steps of the overlapping windows fitting in a recording of ``num_steps`` steps."""
    return range(0, max(0, num_steps - window_steps + 1), stride_steps)


# ---------------------------------------------------------------------------- the job


@dataclass
class RunStats:
    """Counters of one run (filled while :func:`iter_sumo_scenarios` runs)."""

    steps: int = 0
    vehicle_states: int = 0
    windows: int = 0
    skipped_windows: int = 0
    step_s: float = 0.0  # wall time in simulationStep [s]
    record_s: float = 0.0  # wall time reading states + TL [s]
    demand_factor: float = 1.0
    extra: dict = field(default_factory=dict)


def iter_sumo_scenarios(config: SumoGenConfig, state_root: Path | None = None, progress: ProgressFn | None = None,
                        stats: RunStats | None = None, record: bool = True) -> Iterator[Scenario]:
    """Run one SUMO simulation and yield its windows as :class:`Scenario` (validated by the caller).

    :param state_root: dataset folder under which ``states/<label>/`` receives the state files when
        ``config.save_states`` (required then).
    :param progress: called with simulated seconds done, every 10 simulated seconds.
    :param stats: filled with counters and timings.
    :param record: ``False`` only steps SUMO (benchmark of the recording overhead); yields nothing.
    """
    ensure_sumo_home()
    import libsumo

    stats = stats if stats is not None else RunStats()
    if config.save_states and state_root is None:
        raise SumoGenerationError(f"{config.label}: save_states needs a state_root (the dataset folder)")
    src = resolve_network(config.network)
    smap = read_sumo_map(src.net_file)
    static_map = smap.polylines
    n_warm = int(round(config.warmup_s / STEP_LENGTH_S))
    n_rec = int(round(config.duration_s / STEP_LENGTH_S))
    ph_settings = config.policy_history_settings()
    phases = PolicyPhases(ph_settings, int(config.seed), n_rec, str(src.net_file)) if ph_settings else None
    starts = phases.starts if phases is not None else window_starts(n_rec, config.stride_steps)
    state_at = {s + CURRENT_INDEX: w for w, s in enumerate(starts)} if config.save_states else {}
    current_steps = {s + CURRENT_INDEX for s in starts}  # windows read desired speeds at their current step only
    # the label comes from the network's folder name: it must stay a name inside state_root/states
    state_dir = safe_join(Path(state_root) / "states", safe_name(config.label, "network label"), "network label") if config.save_states else None
    if state_dir is not None:
        state_dir.mkdir(parents=True, exist_ok=True)
    stats.demand_factor = factor = demand_factor(config)
    has_tl = smap.has_traffic_lights
    no_tl = np.zeros(static_map.num_polylines, np.int8)  # [L]

    slowdowns = SlowdownInjector(config.slowdown_settings(), config.seed, STEP_LENGTH_S)
    close_ups = CloseUpInjector(config.close_up_settings(), config.seed, STEP_LENGTH_S)
    desired_steps = DesiredStepInjector(config.desired_step_settings(), config.seed, STEP_LENGTH_S,
                                        restore_at=np.asarray(sorted(n_warm + c for c in current_steps), np.int64))
    rec = TrackRecorder()
    state_files: dict[int, str] = {}
    with tempfile.TemporaryDirectory(prefix="r1sim_sumo_gen_") as tmp:
        routes = write_scaled_demand(src.route_file, Path(tmp) / "demand.rou.xml", factor,
                                     config.warmup_s + config.duration_s + 1.0,
                                     config.vtype_probabilities, config.lateral_resolution_m, config.depart_speed)
        cmd = generation_command(src, routes, config)
        try:
            libsumo.start(cmd)
        except Exception as exc:
            raise SumoGenerationError(f"{config.label}: SUMO failed to start ({exc}); command: {' '.join(cmd)}") from exc
        try:
            if phases is not None:
                phases.start(libsumo)
            last_report = 0
            for k in range(n_warm + n_rec):
                if k >= n_warm:
                    i = k - n_warm
                    t0 = time.perf_counter()
                    if record:
                        states = read_vehicle_states(libsumo)
                        desired = read_desired_speeds(libsumo, states.ids) if i in current_steps else None
                        rec.add(states, smap.tl_states(libsumo) if has_tl else no_tl, desired)
                    else:
                        states = None
                    if i in state_at:
                        rel = Path("states") / config.label / f"w{state_at[i]:05d}.state.xml.gz"
                        libsumo.simulation.saveState(str(Path(state_root) / rel))
                        state_files[state_at[i]] = rel.as_posix()
                    stats.record_s += time.perf_counter() - t0
                    stats.vehicle_states += len(states.ids) if states is not None else libsumo.vehicle.getIDCount()
                if slowdowns.active:
                    slowdowns.before_step(libsumo)
                if close_ups.active:
                    close_ups.before_step(libsumo)
                if desired_steps.active:
                    desired_steps.before_step(libsumo)
                t0 = time.perf_counter()
                libsumo.simulationStep()
                stats.step_s += time.perf_counter() - t0
                stats.steps += 1
                if phases is not None and k >= n_warm:
                    phases.after_step(k - n_warm)
                if progress is not None and k - last_report >= 100:
                    progress((k - last_report) * STEP_LENGTH_S)
                    last_report = k
            if progress is not None:
                progress((n_warm + n_rec - last_report) * STEP_LENGTH_S)
        except Exception as exc:
            raise SumoGenerationError(f"{config.label}: SUMO run failed at step {stats.steps} "
                                      f"({type(exc).__name__}: {exc})") from exc
        finally:
            if phases is not None:  # the policy phases' last moveToXY (see sumo_launch.settle_remote_control)
                settle_remote_control(libsumo)
            libsumo.close()
    stats.extra["slowdown_events"] = slowdowns.events
    stats.extra["close_up_events"] = close_ups.events
    stats.extra["desired_step_events"] = desired_steps.events
    if phases is not None:
        stats.extra.update(phases.stats())
    if not record:
        return
    run = rec.finish()
    del rec
    t_start_s = config.warmup_s
    for w, s in enumerate(starts):
        tracks = run.window(s)
        if tracks is None or tracks.num_agents < config.min_agents:
            stats.skipped_windows += 1
            continue
        meta = {
            "source": "sumo", "network": src.name, "seed": int(config.seed), "generator_version": GENERATOR_VERSION,
            "start_time_s": round(t_start_s + s * STEP_LENGTH_S, 3), "window_index": w,
            "stride_steps": config.stride_steps, "demand_factor": round(factor, 6),
        }
        if slowdowns.active:
            meta["slowdowns_per_vehicle_hour"] = float(config.slowdowns_per_vehicle_hour)
            meta["slowdown_hold_s"] = [float(h) for h in config.slowdown_hold_s]
        if config.depart_speed is not None:
            meta["depart_speed"] = str(config.depart_speed)
        if config.close_ups_per_vehicle_hour > 0:
            meta["close_ups_per_vehicle_hour"] = float(config.close_ups_per_vehicle_hour)
        if config.desired_steps_per_vehicle_hour > 0:
            meta["desired_steps_per_vehicle_hour"] = float(config.desired_steps_per_vehicle_hour)
            meta["desired_step_factor"] = [float(f) for f in config.desired_step_factor]
            meta["desired_step_hold_s"] = [float(h) for h in config.desired_step_hold_s]
        if phases is not None:
            meta["policy_history"] = str(config.policy_history)
            meta["policy_history_drive"] = config.policy_history_drive
            meta["label_from_token"] = LABEL_FROM_TOKEN
        if w in state_files:
            meta["state_file"] = state_files[w]
            meta["state_time_s"] = round(t_start_s + (s + CURRENT_INDEX) * STEP_LENGTH_S, 3)
        mp = _with_tl(static_map, run.tl_state[s:s + N_WINDOW_10HZ].T)  # [L, 91]
        stats.windows += 1
        yield Scenario(agents=tracks, map=mp, metadata=meta)


def _with_tl(static_map: MapPolylines, tl_state: np.ndarray) -> MapPolylines:
    return static_map.with_tl_state(np.ascontiguousarray(tl_state, np.int8))


def generate_sumo_scenarios(config: SumoGenConfig, state_root: Path | None = None,
                            stats: RunStats | None = None) -> list[Scenario]:
    """Run one job in *this* process and return its validated windows (libsumo: one simulation per process;
    use :func:`r1sim_sumo.data.dataset.generate_sumo_dataset` for many jobs)."""
    return [sc.validate(source=config.label) for sc in iter_sumo_scenarios(config, state_root=state_root, stats=stats)]
