"""highway-env background vehicles driven by the learned policy, one batched policy call per 0.5 s.

Use through highway-env's own config::

    env = gym.make("highway-v0", config={
        "other_vehicles_type": "r1sim_sumo.sim.highway_vehicle.LearnedVehicle",
        "simulation_frequency": 10, "policy_frequency": 2})   # [Hz]: 0.5 s per agent action = 1 token

How it works. The first :class:`LearnedVehicle` built on a ``Road`` attaches a :class:`LearnedTrafficCoordinator`
to it (``road._r1sim_coordinator``) and replaces the road's ``act``/``step`` methods (instance attributes; the
class is untouched, other roads keep highway-env's behaviour). Every simulation step the coordinator

1. records a 10 Hz history (last 11 states, internal frame) of *every* vehicle on the road (the ego and IDM
   vehicles are context for the policy);
2. at each 0.5 s boundary of its clock makes ONE :meth:`PolicyDriver.plan` call for all vehicles and keeps
   the 0.5 s plan (6 states at 10 Hz) of each learned vehicle; vehicles that appeared since (spawned by the
   merge/intersection envs, any history length >= 1 state) are included at the next boundary and drive by
   IDM until then (with ``simulation_frequency=10, policy_frequency=2`` spawns happen at boundaries);
3. lets the other vehicles ``act``/``step`` as in highway-env, and moves every planned vehicle along its plan
   with the shared :class:`~r1sim_sumo.rollout.kernel.PlanFollower` (as the SUMO controller does): on the plan's
   clock (linear interpolation between the 10 Hz plan states, so any multiple of 10 Hz is exact; other rates
   replan at the first step starting past the 0.5 s boundary and extrapolate the last segment until then), no
   faster than a Krauss safe speed behind the vehicle ahead (``safety="krauss"``, the default; a vehicle held
   below its plan's speed follows the path by distance, lagging the clock, until its next plan); its speed is the
   speed driven over the step;
4. hands a learned vehicle that left the road (centre further than ``lane half-width + offroad_margin_m``
   from its closest lane, or heading more than 90 deg off the lane) back to highway-env's IDM/MOBIL model
   (``offroad="idm"``, the default: IDM steers it back to a lane, drawn blue again) or removes it from the
   road (``offroad="remove"``); crashed learned vehicles brake to a stop as highway-env's vehicles do;
5. checks collisions of every pair involving a :class:`LearnedVehicle` (vehicles and road objects) with one
   batched :func:`r1sim_sumo.geometry.boxes_overlap` call and sets ``crashed`` (``hit`` for non-solid
   objects) like highway-env; pairs of two other vehicles keep highway-env's Python pair loop (with its
   impact response). The ego's episode therefore ends on a crash exactly as in highway-env.

Learned vehicles subclass :class:`highway_env.vehicle.behavior.IDMVehicle` (``create_random``,
``randomize_behavior``, ``make_on_lane``, ``plan_route_to`` work unchanged) and are drawn in
``LEARNED_COLOR`` (purple) while the policy drives them.

The policy: :func:`set_default_policy` (tests pass an untrained synthetic policy), else
``r1sim_sumo.load_policy()`` loaded lazily on first use. The sampler's seed is drawn from the road's random
generator state when the coordinator is created (after ``env.reset(seed=...)``), so seeded episodes repeat.

Frames: highway-env's y-down frame on the vehicles; histories and plans are in the internal frame (y up),
converted only through :mod:`r1sim_sumo.adapters.highway_state` / :mod:`r1sim_sumo.geometry`.
"""

from __future__ import annotations

import hashlib
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from highway_env.vehicle.behavior import IDMVehicle

from r1sim_sumo.adapters.highway_map import read_highway_map
from r1sim_sumo.adapters.highway_state import (
    VEHICLE_ID_ATTR,
    internal_to_highway_state,
    read_highway_vehicles,
)
from r1sim_sumo.geometry import boxes_overlap, wrap_angle
from r1sim_sumo.model.untrained import untrained_policy
from r1sim_sumo.rollout.kernel import FollowStep, PlanFollower
from r1sim_sumo.scenario import DT_S as SIM_DT_S  # [s] one state of a plan
from r1sim_sumo.scenario import N_HISTORY_10HZ, AgentTracks
from r1sim_sumo.sim.policy_driver import Plan, PolicyDriver
from r1sim_sumo.sim.safety_filter import SafetyFilter
from r1sim_sumo.sim.stat_fields import count, listing
from r1sim_sumo.tokens.constants import TOKEN_DT_S as POLICY_DT_S  # [s] one decision

COORDINATOR_ATTR = "_r1sim_coordinator"
LEARNED_COLOR = (160, 60, 200)  # purple: highway-env draws IDM blue, the ego green, crashes red
_EPS_S = 1e-6
OFFROAD_MODES = ("idm", "remove")


# ---------------------------------------------------------------- the policy


@dataclass
class _DefaultPolicy:
    policy: object = None
    sampler: str = "topk:5"
    seed: int | None = None  # None: derived from the road's RNG (the env seed)


_DEFAULT = _DefaultPolicy()
_LOADED: dict[str, object] = {}


def set_default_policy(policy, sampler: str = "topk:5", seed: int | None = None) -> None:
    """Policy used by learned vehicles whose road has no explicit one.

    :param policy: object with ``.model`` and ``.vocab`` (``r1sim_sumo.load_policy()`` or a test policy);
        ``None`` resets to lazily loading ``r1sim_sumo.load_policy()``.
    :param sampler: sampler spec (``topk:5``, ``entropy:16,80``, ``greedy``).
    :param seed: fixed sampler seed for every road; ``None`` derives it from the road's RNG (env seed).
    """
    _DEFAULT.policy, _DEFAULT.sampler, _DEFAULT.seed = policy, sampler, seed


def get_policy(checkpoint: str | None = None):
    """``checkpoint`` loaded once per process; ``None`` = the default set by :func:`set_default_policy`,
    else ``r1sim_sumo.load_policy()`` (raises FileNotFoundError naming the missing checkpoint)."""
    if checkpoint is None and _DEFAULT.policy is not None:
        return _DEFAULT.policy
    key = str(checkpoint)
    if key not in _LOADED:
        from r1sim_sumo import load_policy

        _LOADED[key] = load_policy(checkpoint)
    return _LOADED[key]


# ---------------------------------------------------------------- config


@dataclass
class LearnedTrafficConfig:
    """Options of one road's learned traffic.

    :param checkpoint: policy checkpoint (name or path); ``None`` = the default policy.
    :param sampler: sampler spec; ``None`` = the default's.
    :param seed: sampler seed; ``None`` = the default's, else derived from the road's RNG state.
    :param learned_fraction: probability that a LearnedVehicle is driven by the policy when the road first
        sees it (else IDM/MOBIL from the start, drawn blue); drawn from the coordinator's own generator.
    :param offroad: ``"idm"`` hand off-road learned vehicles back to IDM, ``"remove"`` delete them.
    :param offroad_margin_m: tolerance beyond the lane half-width before a vehicle counts as off-road [m].
    :param map_step_m: lane sampling step of the map read from the road network [m].
    :param map_radius_m: map kept around the agents for each plan [m]; ``None`` = what the model can see,
        its map-to-agent plus map-to-map radius (``PolicyConfig.map_agent_radius_m + map_radius_m``).
    :param safety: ``"krauss"`` (default): a learned vehicle follows its planned path no faster than a Krauss safe
        speed behind the vehicle ahead (the ego included; :mod:`r1sim_sumo.sim.safety_filter`), as in the SUMO
        controller; ``"none"``: the raw policy.
    :param speed_carry: ``PolicyDriver(speed_carry=...)``: ``"off"`` (default) drives each token to its end pose;
        ``"gains"`` keeps the speed-ups the end pose would give back, as the SUMO drop-in does since session 58
        (measured here in docs/ego_sb3/traffic_health_s58.md: merge-v0's learned traffic as fast as IDM's, with more
        background collisions on merge-v0 and roundabout-v0, so not the default).
    """

    checkpoint: str | None = None
    sampler: str | None = None
    seed: int | None = None
    learned_fraction: float = 1.0
    offroad: str = "idm"
    offroad_margin_m: float = 1.0
    map_step_m: float = 1.0
    map_radius_m: float | None = None
    safety: str = "krauss"
    speed_carry: str = "off"

    def __post_init__(self) -> None:
        if self.safety not in ("krauss", "none"):
            raise ValueError(f"LearnedTrafficConfig.safety: got {self.safety!r}, choose 'krauss' or 'none'")
        from r1sim_sumo.sim.policy_driver import SPEED_CARRY

        if self.speed_carry not in SPEED_CARRY:
            raise ValueError(f"LearnedTrafficConfig.speed_carry: got {self.speed_carry!r}, choose one of {SPEED_CARRY}")
        if self.offroad not in OFFROAD_MODES:
            raise ValueError(f"LearnedTrafficConfig.offroad: got {self.offroad!r}, choose one of {OFFROAD_MODES}")
        if not 0.0 <= self.learned_fraction <= 1.0:
            raise ValueError(f"LearnedTrafficConfig.learned_fraction: got {self.learned_fraction}, expected in [0, 1]")


@dataclass
class CoordinatorStats:
    """Counters of one road: policy calls, plans given, hand-offs to IDM, removals, crashes found."""

    plan_calls: int = count("policy decisions (one per 0.5 s with learned vehicles on the road)", "decisions")
    planned_vehicles: int = count("plans given to learned vehicles, summed over decisions", "plans")
    handed_to_idm: int = count("learned vehicles that left the road and were handed to IDM", "vehicles")
    removed: int = count("learned vehicles that left the road and were removed", "vehicles")
    crashes: int = count("vehicles that touched, a learned one among them, each pair once", "vehicle pairs")
    safety_slowdowns: int = count("vehicle-steps in which the safety filter slowed a learned vehicle", "vehicle-steps")
    offroad_ids: list[str] = listing("learned vehicles found off the road", "vehicle ids")


# ---------------------------------------------------------------- the vehicle


class LearnedVehicle(IDMVehicle):
    """A background vehicle whose motion comes from the learned policy (via the road's coordinator).

    ``learned`` is True while the policy drives it; False after a hand-off (then it is a plain
    IDM/MOBIL vehicle). ``plan`` holds its current 0.5 s plan (None until its first boundary).
    """

    def __init__(self, road, position, heading: float = 0, speed: float = 0, *args, **kwargs):
        super().__init__(road, position, heading, speed, *args, **kwargs)
        self.learned = True
        self.plan: _VehiclePlan | None = None
        self._color_override = None
        if road is not None:
            LearnedTrafficCoordinator.for_road(road)

    @property
    def color(self):
        """Drawing colour for highway-env's VehicleGraphics: purple while learned, else highway-env's own."""
        if self._color_override is not None:
            return self._color_override
        return LEARNED_COLOR if (self.learned and not self.crashed) else None

    @color.setter
    def color(self, value) -> None:
        self._color_override = value

    @property
    def policy_controlled(self) -> bool:
        return self.learned and not self.crashed and self.plan is not None

    def act(self, action=None) -> None:
        if self.policy_controlled:
            return  # the coordinator decides; skipping IDM's neighbour search is where the time goes
        super().act(action)

    def hand_to_idm(self) -> None:
        """Stop policy control: from now on IDM/MOBIL drives, aiming at the current lane."""
        self.learned, self.plan = False, None
        self.target_lane_index = self.lane_index


@dataclass
class _VehiclePlan:
    """A learned vehicle's current plan: its row in the coordinator's :class:`PlanFollower` (the 6 frames, internal
    frame, and the progress along them)."""

    slot: int


# ---------------------------------------------------------------- the coordinator


def _network_fingerprint(network) -> str:
    """Hash of a RoadNetwork's lanes (ends, length, width): equal networks share one map tokenization."""
    h = hashlib.sha1()
    for a in sorted(network.graph):
        for b in sorted(network.graph[a]):
            for i, lane in enumerate(network.graph[a][b]):
                p0, p1 = lane.position(0.0, 0.0), lane.position(float(lane.length), 0.0)
                h.update(f"{a}|{b}|{i}|{type(lane).__name__}|{p0[0]:.3f},{p0[1]:.3f}|{p1[0]:.3f},{p1[1]:.3f}|"
                         f"{lane.length:.3f}|{lane.width_at(0.0):.3f}".encode())
    return h.hexdigest()


_DRIVERS: dict[tuple, PolicyDriver] = {}  # (policy id, sampler, radius, map step, network) -> template driver


def _visible_map_radius_m(policy) -> float:
    """Map radius [m] that changes the policy's output: map-to-agent + map-to-map neighbourhoods (60 m if unknown)."""
    c = getattr(policy.model, "config", None)
    try:
        return float(c.map_agent_radius_m + c.map_radius_m) + 1.0
    except AttributeError:
        return 60.0


def _rng_seed(rng) -> int:
    """A seed from a numpy Generator/RandomState's state, without drawing from it (the env's stream is untouched)."""
    state = rng.bit_generator.state if hasattr(rng, "bit_generator") else rng.get_state()
    return int(hashlib.sha1(repr(state).encode()).hexdigest()[:8], 16)


class LearnedTrafficCoordinator:
    """Owns the learned vehicles of one highway-env ``Road``: histories, batched plans, motion, collisions.

    Get it with :meth:`for_road` (created and attached on first use). ``time_s`` is its clock [s].
    """

    def __init__(self, road, config: LearnedTrafficConfig | None = None):
        self.road = road
        self.config = config or LearnedTrafficConfig()
        self.time_s = 0.0
        self.next_plan_s = 0.0
        self.history: dict[str, deque] = {}  # id -> deque of [6] (x, y, yaw, speed, vx, vy), 10 Hz
        self.last_tick: dict[str, int] = {}
        self.stats = CoordinatorStats()
        self.safety = SafetyFilter() if self.config.safety == "krauss" else None
        self.follower = PlanFollower(16)  # the learned vehicles' plans and progress, one row per planned vehicle
        self._driver: PolicyDriver | None = None
        self._set_seed()
        self._orig_act, self._orig_step = road.act, road.step
        road.act, road.step = self.act, self.step

    # ------------------------------------------------------------ attach

    @classmethod
    def for_road(cls, road, config: LearnedTrafficConfig | None = None) -> LearnedTrafficCoordinator:
        """The road's coordinator, created (with ``config``) if it has none; a given config replaces the old one."""
        coord = getattr(road, COORDINATOR_ATTR, None)
        if coord is None:
            coord = cls(road, config)
            setattr(road, COORDINATOR_ATTR, coord)
        elif config is not None:
            coord.config = config
            coord.safety = SafetyFilter() if config.safety == "krauss" else None
            coord._driver = None
            coord._set_seed()
        return coord

    def _set_seed(self) -> None:
        """Sampler seed: config's, else the default's, else from the road's RNG state (the env seed)."""
        seed = self.config.seed if self.config.seed is not None else _DEFAULT.seed
        self.seed = int(seed) if seed is not None else _rng_seed(self.road.np_random)
        self.rng = np.random.default_rng(self.seed)  # learned-fraction draws

    @property
    def driver(self) -> PolicyDriver:
        """The PolicyDriver of this road (map read and tokenized once per network shape and policy)."""
        if self._driver is None:
            cfg = self.config
            policy = get_policy(cfg.checkpoint)
            sampler = cfg.sampler or _DEFAULT.sampler
            radius = cfg.map_radius_m if cfg.map_radius_m is not None else _visible_map_radius_m(policy)
            key = (id(policy), sampler, radius, cfg.map_step_m, cfg.speed_carry, _network_fingerprint(self.road.network))
            if key not in _DRIVERS:
                hmap = read_highway_map(self.road.network, step_m=cfg.map_step_m)
                _DRIVERS[key] = PolicyDriver(policy, hmap.polylines, sampler=sampler, seed=0,
                                             map_radius_m=radius, speed_carry=cfg.speed_carry)
            self._driver = _DRIVERS[key].fork(self.seed)  # shares model + map tokens, own random generator
        return self._driver

    # ------------------------------------------------------------ decide

    def learned_vehicles(self) -> list[LearnedVehicle]:
        return [v for v in self.road.vehicles if isinstance(v, LearnedVehicle) and v.learned and not v.crashed]

    def act(self) -> None:
        """Record 10 Hz histories, replan at 0.5 s boundaries, then let the other vehicles decide."""
        self._observe()
        if self.time_s >= self.next_plan_s - _EPS_S:
            self._replan()
            self.next_plan_s = self.time_s + POLICY_DT_S
        for v in self.road.vehicles:
            if not (isinstance(v, LearnedVehicle) and v.policy_controlled):
                v.act()

    def _observe(self) -> None:
        """Append the current state of every vehicle whose last record is older than this 10 Hz tick."""
        vehicles = self.road.vehicles
        if not vehicles:
            return
        tick = int(math.floor(self.time_s / SIM_DT_S + 1e-6))
        st = read_highway_vehicles(self.road, vehicles)
        rows = np.stack([st.x_m, st.y_m, st.yaw_rad, st.speed_mps, st.vx_mps, st.vy_mps], -1)  # [N, 6]
        present = set()
        frac = self.config.learned_fraction
        for v, vid, row in zip(vehicles, st.ids.tolist(), rows, strict=True):
            present.add(vid)
            if vid not in self.history and isinstance(v, LearnedVehicle) and v.learned and frac < 1.0:
                if frac <= 0.0 or self.rng.uniform() >= frac:
                    v.hand_to_idm()
            if self.last_tick.get(vid) == tick:
                continue
            self.history.setdefault(vid, deque(maxlen=N_HISTORY_10HZ)).append(row)
            self.last_tick[vid] = tick
        for vid in [k for k in self.history if k not in present]:  # vehicles that left the road
            del self.history[vid], self.last_tick[vid]

    def _tracks(self, vehicles) -> AgentTracks:
        """``[A, 11]`` history of ``vehicles`` (right-aligned, last = now; shorter histories are padded invalid)."""
        A, T = len(vehicles), N_HISTORY_10HZ
        tr = AgentTracks.empty(A, T)
        buf = np.zeros((A, T, 6), np.float32)  # [A, T, (x, y, yaw, speed, vx, vy)]
        for i, v in enumerate(vehicles):
            h = self.history[getattr(v, VEHICLE_ID_ATTR)]
            buf[i, T - len(h):] = np.asarray(h, np.float32)
            tr.valid[i, T - len(h):] = True
        for k, f in enumerate(AgentTracks.PER_STEP):
            setattr(tr, f, buf[..., k])
        tr.ids = np.array([getattr(v, VEHICLE_ID_ATTR) for v in vehicles], dtype="<U64")
        tr.length_m = np.array([v.LENGTH for v in vehicles], np.float32)
        tr.width_m = np.array([v.WIDTH for v in vehicles], np.float32)
        # the driver's desired speed [m/s]: highway-env's target_speed (IDM and controlled vehicles), else unknown
        tr.desired_speed_mps = np.array([float(getattr(v, "target_speed", np.nan)) for v in vehicles], np.float32)
        return tr

    def _replan(self) -> None:
        learned = self.learned_vehicles()
        if not learned:
            return
        vehicles = list(self.road.vehicles)  # learned ones + context (ego, IDM, handed-off, crashed)
        plan: Plan = self.driver.plan(self._tracks(vehicles))
        self.stats.plan_calls += 1
        row = {id(v): i for i, v in enumerate(vehicles)}
        ok = [v for v in learned if plan.ok[row[id(v)]]]
        rows = np.array([row[id(v)] for v in ok], np.int64)
        self.follower.ensure(len(ok))
        self.follower.set_plans(np.arange(len(ok)), plan.xy_m[rows], plan.yaw_rad[rows])  # every plan is new
        for v in learned:
            v.plan = None  # IDM drives it until the next boundary
        for j, v in enumerate(ok):
            v.plan = _VehiclePlan(j)
        self.stats.planned_vehicles += len(ok)

    # ------------------------------------------------------------ move

    def step(self, dt: float) -> None:
        """Advance the road by ``dt`` [s]: others by their dynamics, planned vehicles along their plans."""
        planned = [v for v in self.road.vehicles if isinstance(v, LearnedVehicle) and v.policy_controlled]
        planned_ids = {id(v) for v in planned}
        for v in self.road.vehicles:
            if id(v) not in planned_ids:
                v.step(dt)
        self.time_s += dt
        if planned:
            self._follow_plans(planned, dt)
            self._handle_offroad(planned)
        self._collisions(dt)

    def _follow_plans(self, planned: list[LearnedVehicle], dt: float) -> None:
        """Move ``planned`` one step of ``dt`` [s] along their plans, no faster than the safety layer allows."""
        slots = np.array([v.plan.slot for v in planned], np.int64)
        v_allowed = None if self.safety is None else self._allowed_speeds(planned, slots, dt)
        self._follow(planned, slots, dt, v_allowed)

    def _follow(self, planned: list[LearnedVehicle], slots: np.ndarray, dt: float, v_allowed: np.ndarray | None) -> FollowStep:
        """One step of ``dt`` [s] of ``planned`` (follower rows ``slots``) with the shared
        :class:`~r1sim_sumo.rollout.kernel.PlanFollower`, at most ``v_allowed [n]`` [m/s] (``None``: the plan); the
        vehicles are placed (highway-env frame) at the poses and speeds it gives."""
        out = self.follower.follow(slots, dt, v_allowed)
        self.stats.safety_slowdowns += int(out.slowed.sum())
        hw = internal_to_highway_state(out.xy[:, 0], out.xy[:, 1], out.yaw, out.speed)
        for j, v in enumerate(planned):
            v.position = hw.position_m[j].copy()
            v.heading = float(hw.heading_rad[j])
            v.speed = float(hw.speed_mps[j])
            v.on_state_update()  # lane index (and highway-env's display history)
            v.target_lane_index = v.lane_index
        return out

    def _allowed_speeds(self, planned: list[LearnedVehicle], slots: np.ndarray, dt: float) -> np.ndarray:
        """The most each planned vehicle may drive over this step [m/s] ``[n]``: a Krauss safe speed behind the vehicle
        ahead (any road vehicle, the ego included), slowing by at most the emergency deceleration. A vehicle held
        below its plan's speed lags behind the plan's timing until its next plan."""
        vehicles = list(self.road.vehicles)
        st = read_highway_vehicles(self.road, vehicles)  # internal frame, state before this move
        row = {id(v): i for i, v in enumerate(vehicles)}
        rows = np.array([row[id(v)] for v in planned])
        gap, v_lead, _ = self.safety.leader_gap(rows, st.x_m, st.y_m, st.yaw_rad, st.length_m, st.width_m,
                                               st.speed_mps, self.follower.kappa[slots])
        v_now = st.speed_mps[rows]
        return self.safety.allowed(v_now, self.safety.safe_speed(v_now, gap, v_lead), dt)

    def _handle_offroad(self, planned: list[LearnedVehicle]) -> None:
        margin = self.config.offroad_margin_m
        for v in planned:
            lane = v.lane
            s, lat = lane.local_coordinates(v.position)
            off = not lane.on_lane(v.position, s, lat, margin=margin)
            off = off or abs(wrap_angle(v.heading - lane.heading_at(s))) > 0.5 * math.pi
            if not off:
                continue
            self.stats.offroad_ids.append(getattr(v, VEHICLE_ID_ATTR, "?"))
            if self.config.offroad == "remove":
                self.road.vehicles.remove(v)
                self.stats.removed += 1
            else:
                v.hand_to_idm()
                self.stats.handed_to_idm += 1

    # ------------------------------------------------------------ collisions

    def _collisions(self, dt: float) -> None:
        """Batched SAT for pairs with a LearnedVehicle; highway-env's pair loop for the rest."""
        vehicles = self.road.vehicles
        fast = [isinstance(v, LearnedVehicle) for v in vehicles]
        others = [v for v, is_fast in zip(vehicles, fast, strict=True) if not is_fast]
        for i, v in enumerate(others):  # highway-env's own loop, only among non-learned vehicles + objects
            for o in others[i + 1:]:
                v.handle_collisions(o, dt)
            for o in self.road.objects:
                v.handle_collisions(o, dt)
        if not any(fast):
            return
        items = list(vehicles) + list(self.road.objects)
        n = len(items)
        is_fast = np.array(fast + [False] * len(self.road.objects))  # [N]
        pos = np.array([o.position for o in items], np.float64).reshape(n, 2)  # [N, 2] y-down (SAT is frame-free)
        hd = np.array([o.heading for o in items], np.float64)  # [N]
        ln = np.array([o.LENGTH for o in items], np.float64)
        wd = np.array([o.WIDTH for o in items], np.float64)
        collidable = np.array([o.collidable for o in items])
        checks = np.array([o.check_collisions for o in items])
        hit = boxes_overlap(pos[:, None, 0], pos[:, None, 1], hd[:, None], ln[:, None], wd[:, None],
                            pos[None, :, 0], pos[None, :, 1], hd[None, :], ln[None, :], wd[None, :])  # [N, N]
        pair = np.triu(np.ones((n, n), bool), 1)
        pair &= is_fast[:, None] | is_fast[None, :]
        pair &= collidable[:, None] & collidable[None, :]
        pair &= checks[:, None] | checks[None, :]
        for a, b in np.argwhere(hit & pair):
            oa, ob = items[a], items[b]
            if oa.solid and ob.solid:
                if not (oa.crashed and ob.crashed):
                    self.stats.crashes += 1
                oa.crashed = ob.crashed = True
            if not oa.solid:
                oa.hit = True
            if not ob.solid:
                ob.hit = True


def coordinator_of(road) -> LearnedTrafficCoordinator | None:
    """The coordinator attached to ``road`` (None when no learned vehicle was ever built on it)."""
    return getattr(road, COORDINATOR_ATTR, None)


def default_or_untrained_policy(checkpoint: str | None = None):
    """``load_policy(checkpoint)`` if a checkpoint exists, else :func:`untrained_policy` (returns ``(policy, trained)``)."""
    try:
        return get_policy(checkpoint), True
    except FileNotFoundError:
        return untrained_policy(), False
