"""Drop-in background-traffic controller: the learned policy drives chosen vehicles of a running SUMO.

Use (libsumo or TraCI, your own loop)::

    ctrl = SumoController(libsumo, r1sim_sumo.load_policy(), control="fraction=0.5")
    while libsumo.simulation.getMinExpectedNumber() > 0:
        libsumo.simulationStep()
        ctrl.step()                      # or once: ctrl.attach_step_listener()
    print(ctrl.stats.summary())

Timing (SUMO step length must be 0.1 s = one 10 Hz state): ``step()`` is called after each
``simulationStep``. It records every vehicle's state into a 1.1 s history ring buffer (11 states, last =
now). Every 5th call (0.5 s) it hands over newly eligible vehicles, checks the controlled ones (off road,
end of route, off their route) and runs one batched :meth:`PolicyDriver.plan` for all controlled vehicles
plus the SUMO-driven vehicles near them (context). Every call it then places each controlled vehicle at
its plan's next frame with ``vehicle.moveToXY`` (front-bumper centre + navigational angle from
:func:`~r1sim_sumo.adapters.sumo_state.to_sumo_pose`), applied by SUMO at the next ``simulationStep``; so
after step ``j`` (1..5) of a plan the vehicle stands exactly on plan frame ``j`` (position drive: the shared
:class:`~r1sim_sumo.rollout.kernel.PlanFollower`, which lags behind the frames only when the safety layer slows it).
``replan_every_s`` (default 0.5 s, one decision per token) replans the commands drive more often, every 0.1-0.4 s:
each decision reads the last 1.1 s afresh (no per-agent memory) and only the plan's first 1-4 steps are driven, a
receding horizon that answers a leader moving off or a gap opening sooner, at 2.2-2.4x the run time for 0.2 s
(docs/simulate/replan_s44).

Lifecycle of a vehicle (``VehicleRecord.state``):

* departed -> SUMO-driven while its history holds fewer than 11 states (1.1 s), or when not selected by
  ``control`` (mixed traffic: it stays SUMO-driven but is context for the policy);
* handed over at the first decision with 11 states: ``take_control`` (speed mode 32, lane-change mode 0;
  the previous modes are kept and restored on hand-back);
* handed to SUMO for a while: ``standstill`` (standing ``standstill_handoff_s``, default 5 s: SUMO's car-following
  and junction model start queues again, which the policy does slowly); taken back by the policy
  once SUMO has it moving at ``RESUME_SPEED_SHARE`` of its allowed speed (``retakes``); position drive also
  ``wrong_lane`` (within ``STRATEGIC_LOOKAHEAD_S`` at its allowed speed of the end of a lane that does not lead on
  along its route, which the policy does not know: SUMO changes lanes) and ``junction_turn`` (with
  ``junction_turns="sumo"``: on a junction lane where its plan leaves its way, or that turns off the major road: SUMO
  drives it through the junction) and ``junction_crossing`` (with ``junction_crossings="sumo"``: within
  :func:`crossing_reach_m` of a lane end where it may have to stop, a signal, yield or crossing links: SUMO drives it
  through the junction), all three taken back on a later edge of its route (never inside a junction or within that
  reach of such a lane end, nor taken there for the first time);
* handed back (never taken again) with a reason: ``offroad`` (no lane centre within half a lane width +
  ``offroad_margin_m``), ``plan_not_ok``, ``policy_error`` (the policy raised: logged warning, the
  simulation goes on), ``sumo_error`` (a TraCI call about it failed), ``stuck`` (standing for
  ``STUCK_AFTER_S`` with no leader within 15 m and no red signal within 30 m), ``route_end`` (on the last edge of
  its route near the end: SUMO drives the last metres so the vehicle *arrives* normally, since a vehicle
  placed by ``moveToXY`` never arrives on its own);
* left the simulation: ``arrived`` (in ``getArrivedIDList``) or ``removed`` (vanished otherwise, e.g.
  ``vehicle.remove`` by the user). ``departed == arrived + removed + running`` always holds.

Route consistency: vehicles are moved with keepRoute 3 (exact x,y, mapped onto their route: ~9 us per
call vs ~68 us for 2). When the lane nearest the vehicle (heading-aware) lies on a normal edge outside its
route, e.g. the policy took another exit, that one move uses keepRoute 2 (SUMO maps it onto the edge it is
really on and makes that edge its route) and the next step calls ``changeTarget`` to the original
destination; when that is unreachable the vehicle keeps the one-edge route and arrives at its end.

Drives (``drive=``): ``commands`` (default) hands each plan to SUMO as a speed per 0.1 s step (``setSpeed``) and,
when the plans' lateral drift adds up to a lane change, a ``changeLane`` request (``changeSublane`` with the sublane
model); SUMO keeps its own checks on (speed mode 31: safe gaps, accel/decel limits, right of way, red lights;
lane-change mode 534: strategic changes for the route, cooperation with merging vehicles, SUMO's own overtaking while
the policy asks for no change (``lane_changes='policy'``: 518, without it), requests only into safe gaps; near the end
of a lane that does not continue its route SUMO drives its speed too), so the vehicle keeps its
route, turns, yields and arrives as SUMO does; how often SUMO overruled the policy is counted (``speed_capped`` of
``speed_commands`` vehicle-steps, ``lane_change_refused`` of ``lane_change_requests``). ``position`` places the
vehicle on its plan (below); with ``safety='krauss'`` the plan is driven no faster than a Krauss safe speed behind
the vehicle ahead, than a stop before red / yellow signals and junction links without priority with a foe
(:mod:`r1sim_sumo.sim.rules`), than the vehicle type's max speed and acceleration (braking bounded by its
emergency deceleration); plans entering a lane its class may not use are kept on the current lane, and two
controlled vehicles blocking each other at a merge are resolved (the one ahead goes); a vehicle a move left on no
lane inside a junction is snapped onto its route's lane until it is on a normal lane again (``junction_snaps``;
SUMO's drivers do not see a vehicle on no lane), and planned boxes sticking out over the carriageway's edges are
moved back to them (``carriageway_fixes``); a vehicle standing with its box over the left edge of its carriageway
(into the other direction) is snapped back onto its lane (``centre_line_snaps``); planned frames held inside their
lane by the lane-change gate or moved back over the centre line of a two-way road point along their lane; inside a
junction where lanes only split (a turn bay's taper) planned boxes stay in the internal lane SUMO has the vehicle on
(``lane_split_keeps``); a vehicle turning against its lane away from the lane's ends (heading more than 45 degrees
off it) is handed back (``against_lane``); a vehicle the policy drove,
handed back and standing inside a junction in a deadlock with its foes is let out ignoring right of way, one per
junction and only with room to leave (``junction_deadlocks``; both drives). Until the policy is taken
over and after hand-backs, SUMO drives as usual; the lifecycle below describes the position drive (the commands
drive needs no off-road, route-end or off-route hand-back).

Counters: collision events (:class:`~r1sim_sumo.sim.collision_events.CollisionCounter`, the same for native runs):
SUMO's collision report and box overlaps of any two vehicles, each pair-event once; teleports; vehicles inserted
and still waiting to insert (``waiting_to_insert``: blocked insertions); removals by reason; standing vehicle-steps;
vehicle-km.

Frames: internal (metres, x east, y north, yaw radians CCW from +x, box centre) everywhere except the
SUMO calls, which go through :mod:`r1sim_sumo.adapters.sumo_state`.
"""

from __future__ import annotations

import logging
import re
import time
import zlib
from collections import Counter, OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from r1sim_sumo.adapters.sumo_state import (
    KEEP_ROUTE_EXACT_XY,
    KEEP_ROUTE_SNAP,
    clear_static_cache,
    lane_speed_ratio,
    read_desired_speeds,
    read_vehicle_states,
    take_control,
    to_sumo_pose,
)
from r1sim_sumo.geometry import wrap_angle
from r1sim_sumo.rollout.kernel import FollowStep, PlanFollower, retime_plan
from r1sim_sumo.scenario import DT_S as STEP_LENGTH_S  # [s] SUMO step = one 10 Hz state
from r1sim_sumo.scenario import N_HISTORY_10HZ, AgentTracks
from r1sim_sumo.sim.collision_events import CollisionCounter
from r1sim_sumo.sim.free_road_speed import FreeRoadSpeed
from r1sim_sumo.sim.queue_growth import QueueGrowthTracker
from r1sim_sumo.sim.rules import LanePermissions, VehicleLimits, stop_distance
from r1sim_sumo.sim.safety_filter import SafetyFilter
from r1sim_sumo.sim.stat_fields import amount, count, label, listing, tally
from r1sim_sumo.sumo_launch import settle_remote_control

LOG = logging.getLogger(__name__)

STUCK_AFTER_S = 20.0  # [s] a controlled vehicle standing this long with nothing ahead is handed back to SUMO
STILL_SPEED_MPS = 0.3  # [m/s]
OVER_CENTRE_LINE_M = 0.2  # [m] a standing vehicle's box this far over its carriageway's left edge is snapped back
JUNCTION_DEADLOCK_S = 15.0  # [s] a vehicle the policy drove, handed back and standing this long inside a junction with
# room to leave it (no leader within its length + JUNCTION_DEADLOCK_LEAD_M beyond) is in a junction deadlock (crossing
# foes each waiting for the other; SUMO would teleport it, which `r1sim simulate` turns off): it may leave the junction
# ignoring right of way
JUNCTION_DEADLOCK_LEAD_M = 5.0  # [m] room beyond the junction a released vehicle needs (plus its length)
JUNCTION_FOE_LOOK_M = 30.0  # [m] how far along its path a released vehicle's junction foes are looked for
DEADLOCK_SPEED_MODE = 7  # safe speed behind its leader, accel / decel limits; no right of way, no red-light check
DEADLOCK_SPEED_MPS = 5.0  # [m/s] speed commanded to a vehicle let out of a junction deadlock (the speed mode bounds
# only commanded speeds: without a command its own model keeps waiting)
WRONG_LANE_AHEAD_S = 4.0  # [s] commands drive: a vehicle this far (in time at its speed, and at least WRONG_LANE_AHEAD_M)
WRONG_LANE_AHEAD_M = 40.0  # [m] from the end of a lane that does not continue its route lets SUMO drive its speed
STRATEGIC_LOOKAHEAD_S = 10.0  # [s] position drive: a vehicle in a lane that does not continue its route is handed to
# SUMO to change lanes once within this many seconds, at its lane's allowed speed, of the lane's end. SUMO's LC2013
# driver plans its strategic changes within LOOK_FORWARD = 10 s x its look-ahead speed (its recent top speed, which
# decays only slowly when it brakes: a driver in a queue keeps its approach's look-ahead) + two lengths with gap; the
# lane's allowed speed stands in for that memory here. The 40 m / 4 s x speed of session 39 left a turner queued in
# the wrong lane at a red light to change lanes in the last 40 m, into a standing queue: it stood at the stop line
# through the green and the lane behind it grew for 63-79 s (urban_grid, session 62)
OPEN_ROAD_MARGIN_M = 20.0  # [m] position drive: a plan is followed at no harder than the comfortable deceleration
# while the vehicle is farther than its braking distance plus this from the end of the open road (_lane_end_is_open)
YIELD_RECOVER_MPS = 1.0  # [m/s] merge cooperation: a yielding vehicle stays SUMO's until it is back within this of the
#                           speed it had when the yield began (or YIELD_MAX_S has passed)
YIELD_MAX_S = 10.0  # [s]
RESUME_SPEED_SHARE = 0.6  # a vehicle handed to SUMO at a standstill is taken back once it drives this share of its
# allowed speed (lane limit x speed factor): the policy speeds up from a standstill slowly, so SUMO does the
# speeding up
FINISHED_KEPT = 2000  # records of vehicles that left, kept for inspection (oldest dropped first)
DRIVES = ("commands", "position")
BRAKE_FLOORS = ("off", "open-road")
# commands drive: SUMO's own checks stay on. Speed mode 31 = safe speed, max accel, max decel, right of way at
# junctions, red lights (SUMO's default; Flow's "all_checks"). Lane-change mode 518 = strategic changes needed for
# the route even against a TraCI request (2) + cooperative changes that make room for a merging vehicle when they do
# not conflict with a request (4) + TraCI requests only when they keep the gaps of others (512, Flow's
# "no_lat_collide"); no keep-right changes of its own, and speed-gain (overtaking) changes (16) only with
# lane_changes='policy+overtaking', the default since session 32 (mode 534). Without the cooperative
# bit the main line never made room at a merge: ramp queues that never cleared (motorway_merge 95.2% of native
# arrivals with mode 514, 98.5% with 518; SUMO's game/ramp 84.0% / 92.0%, seed 0; session 21).
COMMANDS_SPEED_MODE = 31
COMMANDS_LANE_CHANGE_MODE = 2 | 4 | 512
SPEED_GAIN_LANE_CHANGES = 16  # lane-change mode bit: SUMO's own speed-gain (overtaking) changes while no TraCI
# request of the policy is pending (``lane_changes='policy+overtaking'``)
LANE_CHANGE_SOURCES = ("policy", "policy+overtaking")
# lane-change state bits of SUMO (traci.constants.LCA_*): the change is urgent (strategic, close to the lane's end) and a
# follower on the target side blocks it
LCA_URGENT, LCA_BLOCKED_BY_LEFT_FOLLOWER, LCA_BLOCKED_BY_RIGHT_FOLLOWER = 256, 1024, 4096
LCA_BLOCKED_BY_LEFT_LEADER, LCA_BLOCKED_BY_RIGHT_LEADER, LCA_OVERLAPPING = 512, 2048, 8192
LANE_CHANGE_GATES = ("sumo", "off")
JUNCTION_TURNS = ("sumo", "policy")  # SumoController(junction_turns=...): who drives a vehicle whose plan leaves its route
JUNCTION_CROSSINGS = ("sumo", "policy")  # SumoController(junction_crossings=...): who drives a vehicle through a junction
# where it may have to stop (signal, yield, crossing links)
DROP_IN_JUNCTION_CROSSINGS = {"position": "sumo", "commands": "sumo"}  # each drive's own (``junction_crossings=None``):
# the position drive's since session 63; the commands drive's since session 64 (SUMO drives the speed there), measured
# on all 8 scenarios at seeds 0-7 against "policy" (docs/simulate/junction_sumo_s63, docs/simulate/commands_crossings_s64)
CROSSING_LOOKAHEAD_S = 3.0  # [s] junction_crossings="sumo": SUMO takes a vehicle within max(CROSSING_MIN_M, this x its
CROSSING_MIN_M = 20.0  # [m] allowed speed) of such a lane end (SUMO's front bumper; docs/simulate/junction_sumo_s63)
CROSSING_CLEAR_M = 5.0  # [m] junction_crossings="sumo": a vehicle SUMO drove through a junction is taken back once its
# front bumper is its length + this into the next edge: its box has left the junction and turned onto the lane (taken
# back at once, the policy's first plans went on along the turn, into the oncoming lane beside: the roundabout's exits)
SPLIT_HANDOVER_M = 15.0  # [m] position drive: a vehicle whose route takes a lane split's other branch is handed to SUMO
# once its planned front bumper is this close to the split (at the last metres, SUMO's driver took the first branch)
OFF_ROUTE_IN_JUNCTION_M = 1.5  # [m] position drive: a plan ending this far from every lane of its vehicle's way through
# the junction it is in (the internal lane it is on and the lanes of its route's next edge that lane leads to) leaves the
# route (junction_turns="sumo")
AGAINST_LANE_RAD = np.deg2rad(45.0)  # [rad] position drive with the safety layer: a controlled vehicle whose heading
# differs this much from its lane's (a normal lane, more than AGAINST_LANE_CLEAR_M from either end) is turning around on
# the road and is handed back (reason ``against_lane``; retaken on a later edge of its route). Session 65: the
# roundabout's three position-drive events at seed 0 were one vehicle that turned left across the centre line 45 m
# before its route's end, U-turned onto the inbound lane and drove back the wrong way. At seed 0 one other controlled
# vehicle turned more than 45 degrees off its lane away from its ends on motorway_merge, none on urban_intersection,
# urban_grid, game/ramp or game/cross; on game/grid6 24 stood across their lanes in its jams. With the centre-line yaw
# rule of _keep_on_carriageway the U-turn no longer starts; this hand-back came 9 times in the 24 runs of seeds 0-2
# (game/grid6 7; docs/simulate/along_lane_s65)
TWO_WAY_REACH_M = 1.5  # [m] _two_way_lanes: a lane of the other direction this near the point one lane width left
AGAINST_LANE_CLEAR_M = 8.0  # [m] (box centre) turns at lane ends, into and out of junctions, are left to the junction rules
GATE_OVER_M = 0.05  # [m] a planned box this far over its lane's line enters the lane beside it (lane-change gate)
NEIGHBOURS_LEFT_BLOCKING_FOLLOWERS, NEIGHBOURS_RIGHT_BLOCKING_FOLLOWERS = 4, 5  # vehicle.getNeighbors modes (bit 0: right)
DROP_IN_SAMPLERS = {"commands": "quantile:0.7,0.1", "position": "median:0.1"}  # the policy's token sampler in each
# drive (``sampler=None``): commands since session 53 (docs/simulate/quantile_s53), position since session 47
# (docs/simulate/sampler_s47; the 0.7 quantile doubled its roundabout's collision events there)
DROP_IN_GUIDANCE = 0.0  # desired-speed guidance weight of the drop-in (``guidance``)
SPEED_CARRY_MODES = ("off", "gains", "free", "both")  # SumoController(speed_carry=...)
DROP_IN_SPEED_CARRY = {"commands": "gains", "position": "gains"}  # each drive's own (``speed_carry=None``), since
# session 58 (docs/simulate/speed_carry_s58: more arrivals and speed in both drives over seeds 0-2 / 0-7); "off" for the
# position drive without a safety layer (the kept speed-ups ran into leaders: motorway_merge 4,616 vs 609 collision
# events per 1000 vehicle-km at seed 0)
CARRY_LEADER_HEADWAY_S = 1.5  # [s] speed_carry="free": a leader this headway ahead or more, not slower, leaves the road free
LANE_CHANGE_TRIGGER_M = 0.6  # [m] lateral drift of the policy's plans (summed over decisions) that asks for a lane change
STOP_LINE_MARGIN_M = 1.0  # [m] position drive: the front bumper stops this far before a stop line (a vehicle placed
# right on the line is mapped by moveToXY onto the junction's internal lane)
SPEED_CAP_TOL_MPS = 0.2  # [m/s] SUMO drove this much slower than commanded: the policy was overruled
STEPS_PER_DECISION = 5  # 0.5 s per token: a plan covers 5 steps
DROP_IN_REPLAN_S = 0.5  # [s] the drop-in's default time between decisions (replan_every_s)
# [m/s] commands drive, ``junction_floor_mps``: inside a junction (on an internal lane) a controlled vehicle's speed
# command is at least this; SUMO's own checks (safe speed behind its leader, right of way, red lights) and the Krauss
# cap still stop it where they must. Why it exists: a policy vehicle that stood inside game/ramp's diverge (seed 2,
# 287.6 s) while its leader crept on was clipped by a vehicle going straight (SUMO sees no leader across the branches).
# Off (0) by default: with 2.0 m/s (0.5 m/s) game/ramp delivered 356 / 341 / 340 (340 / 341 / 340) vehicles on seeds
# 0 / 1 / 2 against 365 / 355 / 346 without it, the one event gone (docs/simulate/junction_floor_s48).
DROP_IN_JUNCTION_FLOOR_MPS = 0.0
KEEP_ROUTE_FAST = KEEP_ROUTE_SNAP | KEEP_ROUTE_EXACT_XY  # 3: exact x,y, stay on route (cheap lane search)
KEEP_ROUTE_FREE = KEEP_ROUTE_EXACT_XY  # 2: exact x,y on whatever edge is there (route becomes that edge)
SUMO_INVALID_ANGLE = -1073741824.0  # TraCI's INVALID_DOUBLE_VALUE: moveToXY takes the heading of the lane it maps to
N_STATE = 6  # x_m, y_m, yaw_rad, speed_mps, vx_mps, vy_mps
_PER_STEP = AgentTracks.PER_STEP


class StandstillTracker:
    """How long each vehicle has been standing (speed < :data:`STILL_SPEED_MPS`) in one go; fills
    ``longest_standstill_s`` and ``stood_over_60s`` of a :class:`ControllerStats` (native and policy runs alike)."""

    LONG_S = 60.0  # [s]

    def __init__(self):
        self._since: dict[str, int] = {}  # vehicle id -> steps standing so far
        self._long: set[str] = set()

    def update(self, stats, ids, speed_mps: np.ndarray) -> None:
        since = {}
        standing = np.flatnonzero(np.abs(speed_mps) < STILL_SPEED_MPS)  # only standing vehicles count
        for v in np.asarray(ids)[standing].tolist():
            n = self._since.get(v, 0) + 1
            since[v] = n
            if n * STEP_LENGTH_S > stats.longest_standstill_s:
                stats.longest_standstill_s = n * STEP_LENGTH_S
            if n * STEP_LENGTH_S > self.LONG_S and v not in self._long:
                self._long.add(v)
                stats.stood_over_60s += 1
        self._since = since


class ControllerError(ValueError):
    """Bad controller input (selection spec, step length, network). The message names the field and a fix."""


# ---------------------------------------------------------------------------- selection of controlled vehicles


@dataclass(frozen=True)
class Selection:
    """Which vehicles the policy drives: ``all``, ``vtype=a,b``, ``id=<regex>``, ``fraction=<0..1>``.

    ``fraction`` is decided per vehicle from a hash of (seed, vehicle id): reproducible and independent of
    the order vehicles depart in.
    """

    kind: str
    vtypes: frozenset[str] = frozenset()
    pattern: re.Pattern | None = None
    fraction: float = 1.0
    seed: int = 0

    @classmethod
    def parse(cls, spec: str, seed: int = 0) -> Selection:
        s = (spec or "all").strip()
        if s == "all":
            return cls("all", seed=seed)
        key, sep, val = s.partition("=")
        key, val = key.strip(), val.strip()
        if not sep or not val:
            raise ControllerError(f"control='{spec}': expected 'all', 'vtype=<id>[,<id>]', 'id=<regex>' or 'fraction=<0..1>'")
        if key == "vtype":
            return cls("vtype", vtypes=frozenset(t.strip() for t in val.split(",") if t.strip()), seed=seed)
        if key == "id":
            try:
                return cls("id", pattern=re.compile(val), seed=seed)
            except re.error as exc:
                raise ControllerError(f"control='{spec}': invalid regular expression ({exc})") from exc
        if key == "fraction":
            try:
                p = float(val)
            except ValueError:
                p = -1.0
            if not 0.0 <= p <= 1.0:
                raise ControllerError(f"control='{spec}': fraction must be a number in [0, 1]")
            return cls("fraction", fraction=p, seed=seed)
        raise ControllerError(f"control='{spec}': unknown selector '{key}'; use all, vtype=, id= or fraction=")

    def check_vtypes(self, known: set[str]) -> None:
        """Raise when a ``vtype=`` filter names a type the simulation does not define."""
        unknown = sorted(self.vtypes - known)
        if unknown:
            raise ControllerError(f"control='vtype=...': unknown vType(s) {unknown}; the simulation defines "
                                  f"{sorted(t for t in known if not t.startswith('DEFAULT_'))}")

    def selects(self, veh_id: str, type_id: str) -> bool:
        if self.kind == "all":
            return True
        if self.kind == "vtype":
            return type_id in self.vtypes or type_id.split("@", 1)[0] in self.vtypes
        if self.kind == "id":
            return self.pattern.search(veh_id) is not None
        u = zlib.crc32(f"{self.seed}:{veh_id}".encode()) / 2**32  # uniform in [0, 1)
        return u < self.fraction


# ---------------------------------------------------------------------------- nearest lane queries


def _first_min_per_group(values: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Index of the first smallest value of each contiguous group of ``values [R]``; groups begin at ``start [K]``
    (increasing, ``start[0] == 0``, none empty). The same as a stable sort by (group, value) taking each group's head,
    in O(R) instead of a sort; NaNs count as largest, as they sort last."""
    low = np.fmin.reduceat(values, start)  # NaN only where a whole group is NaN
    size = np.diff(np.r_[start, len(values)])
    idx = np.where(values == np.repeat(low, size), np.arange(len(values)), len(values))
    first = np.minimum.reduceat(idx, start)
    return np.where(first < len(values), first, start)


def route_merge_reach_m(speed_mps: float) -> float:
    """Commands drive: [m] from a lane's end within which a vehicle that must leave the lane (it does not lead on
    along its route) has SUMO drive its speed, ``max(WRONG_LANE_AHEAD_M, |speed| x WRONG_LANE_AHEAD_S)``."""
    return max(WRONG_LANE_AHEAD_M, abs(speed_mps) * WRONG_LANE_AHEAD_S)


def crossing_reach_m(allowed_mps: float) -> float:
    """``junction_crossings="sumo"``: [m] before the end of a lane that ends in a crossing junction within which SUMO
    drives a vehicle (position drive) or its speed (commands drive), ``max(CROSSING_MIN_M, CROSSING_LOOKAHEAD_S x allowed speed)`` (its lane's
    limit x its speed factor, [m/s]): room for SUMO's driver to stop at the line from the lane's speed (13.89 m/s,
    4.5 m/s^2: 21 m) and to be seen approaching by its junction model."""
    return max(CROSSING_MIN_M, CROSSING_LOOKAHEAD_S * allowed_mps) if np.isfinite(allowed_mps) else CROSSING_MIN_M


class LaneLocator:
    """Nearest drivable lane of points, heading-aware, over every lane (normal and junction-internal).

    Built once from a :class:`~r1sim_sumo.adapters.sumo_map.SumoMap` (shapely STRtree over the lane
    centrelines). ``locate(xy [N, 2], yaw [N])`` returns per point the lane index (-1 when no lane within
    ``search_m``), the distance to its centreline [m], the lane's half width [m] and the arc length of the
    projection along the lane [m]. Among lanes within ``search_m`` the one minimising
    ``distance + heading_weight_m * (1 - cos(heading difference))`` wins, so overlapping junction lanes and
    opposite carriageways resolve to the one driven along.
    """

    def __init__(self, smap, search_m: float = 8.0, heading_weight_m: float = 6.0):
        import shapely

        self._shapely = shapely
        pl = smap.polylines
        lane_rows = np.flatnonzero(pl.kind == 0)
        self.lane_id = [str(pl.lane_id[i]) for i in lane_rows]
        self.edge_id = [lid.rsplit("_", 1)[0] for lid in self.lane_id]
        self.is_internal = np.array([e.startswith(":") for e in self.edge_id], bool)
        # bit 1: no drivable lane of the same edge to its left (highest index); bit 2: none to its right (lowest; a
        # sidewalk at index 0 is not in the map, so the car lane beside it is the rightmost)
        index = np.array([int(lid.rsplit("_", 1)[1]) for lid in self.lane_id], np.int64)
        lo: dict[str, int] = {}
        hi: dict[str, int] = {}
        for e, i in zip(self.edge_id, index.tolist(), strict=True):
            lo[e], hi[e] = min(lo.get(e, i), i), max(hi.get(e, i), i)
        self._side = np.array([(i == hi[e]) | 2 * (i == lo[e]) for e, i in zip(self.edge_id, index.tolist(), strict=True)],
                              np.int64)
        self.half_width_m = 0.5 * np.asarray(pl.width_m[lane_rows], np.float64)
        self.lines = np.array([shapely.LineString(pl.polyline(i).astype(np.float64)) for i in lane_rows], dtype=object)
        self.length_m = shapely.length(self.lines)
        self.tree = shapely.STRtree(self.lines)
        self.search_m = float(search_m)
        self.heading_weight_m = float(heading_weight_m)
        # every lane's segments, flattened, for vectorised projection / interpolation (numpy, not one GEOS call per
        # point): segment j of lane k is row soff[k] + j; start point a, vector d, start arc length s0 [m]
        segs = [np.asarray(pl.polyline(i), np.float64) for i in lane_rows]
        nseg = np.array([max(len(v) - 1, 0) for v in segs], np.int64)
        if (nseg < 1).any():
            raise ValueError(f"lane {self.lane_id[int(np.argmin(nseg))]}: a lane centreline needs at least 2 points")
        self._nseg, self._soff = nseg, np.concatenate([[0], np.cumsum(nseg)[:-1]])
        self._seg_a = np.concatenate([v[:-1] for v in segs])  # [S, 2]
        self._seg_d = np.concatenate([np.diff(v, axis=0) for v in segs])  # [S, 2]
        self._seg_len = np.hypot(self._seg_d[:, 0], self._seg_d[:, 1])  # [S]
        s0 = np.concatenate([np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(v, axis=0).T))[:-1]]) for v in segs])
        self._seg_s0 = s0
        lane_len = np.array([s0[o + n - 1] + self._seg_len[o + n - 1] for o, n in zip(self._soff, nseg, strict=True)])
        self._lane_base = np.concatenate([[0.0], np.cumsum(lane_len + 1.0)[:-1]])  # lanes laid end to end, 1 m apart
        self._seg_key = np.repeat(self._lane_base, nseg) + s0  # [S] increasing

    def _interpolate(self, lane: np.ndarray, s_m: np.ndarray) -> np.ndarray:
        """Points ``[K, 2]`` at arc lengths ``s_m [K]`` [m] (clipped to the lane) along lanes ``lane [K]``."""
        s = np.clip(s_m, 0.0, self.length_m[lane])
        j = np.searchsorted(self._seg_key, self._lane_base[lane] + s, side="right") - 1
        j = np.clip(j, self._soff[lane], self._soff[lane] + self._nseg[lane] - 1)
        ln = self._seg_len[j]
        t = np.clip(np.divide(s - self._seg_s0[j], ln, out=np.zeros_like(ln), where=ln > 0), 0.0, 1.0)
        return self._seg_a[j] + t[:, None] * self._seg_d[j]

    def _project(self, xy: np.ndarray, lane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance [m] of points ``xy [K, 2]`` to lanes ``lane [K]`` and the arc length [m] of the nearest point
        (the first nearest segment on ties, as GEOS ``project`` does)."""
        n = self._nseg[lane]  # >= 1 each (checked at construction)
        row = np.repeat(np.arange(len(lane)), n)  # [R] pair of each (pair, segment) row; a pair's rows are contiguous
        start = np.concatenate([[0], np.cumsum(n)[:-1]])
        j = np.repeat(self._soff[lane], n) + (np.arange(len(row)) - np.repeat(start, n))  # [R] segment
        t, dist = self._onto_segments(xy[row], j)
        first = _first_min_per_group(dist, start)
        return dist[first], self._seg_s0[j[first]] + t[first] * self._seg_len[j[first]]

    def _onto_segments(self, p: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points ``p [R, 2]`` projected onto segments ``j [R]``: the nearest point's fraction ``t`` along the segment
        (0..1) and the distance [m]."""
        d, ln2 = self._seg_d[j], self._seg_len[j] ** 2
        rel = p - self._seg_a[j]
        t = np.clip(np.divide((rel * d).sum(1), ln2, out=np.zeros_like(ln2), where=ln2 > 0), 0.0, 1.0)
        off = rel - t[:, None] * d
        return t, np.hypot(off[:, 0], off[:, 1])

    def lateral_offset(self, lane: np.ndarray, s_m: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed lateral offset [m] (+ = left) of points ``xy [n, 2]`` from the centrelines of lanes ``lane [n]`` at
        arc lengths ``s_m [n]`` (clipped to each lane), and the lane headings there [rad] (as :meth:`along`)."""
        lane = np.asarray(lane, np.int64)
        s = np.clip(np.asarray(s_m, np.float64), 0.0, self.length_m[lane])
        p = self._interpolate(lane, s)
        a = self._interpolate(lane, np.maximum(s - 0.5, 0.0))
        b = self._interpolate(lane, np.minimum(s + 0.5, self.length_m[lane]))
        heading = np.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0])
        d = np.asarray(xy, np.float64) - p
        return d[:, 1] * np.cos(heading) - d[:, 0] * np.sin(heading), heading

    def lane_side(self, k: np.ndarray) -> np.ndarray:
        """Per lane row ``k``: bit 1 when no lane of the same edge lies to its left, bit 2 when none to its right."""
        return self._side[np.asarray(k, np.int64)]

    def index_of(self, lane_id: str) -> int:
        """Row of ``lane_id`` (-1 when the map has no such lane)."""
        if not hasattr(self, "_row"):
            self._row = {lid: i for i, lid in enumerate(self.lane_id)}
        return self._row.get(lane_id, -1)

    def along(self, k: int, s_m: np.ndarray):
        """Points ``[n, 2]`` and headings ``[n]`` [rad] at arc lengths ``s_m [n]`` [m] along lane ``k``'s centreline
        (clipped to the lane)."""
        s = np.clip(np.atleast_1d(np.asarray(s_m, np.float64)), 0.0, self.length_m[k])
        lane = np.full(len(s), int(k), np.int64)
        a = self._interpolate(lane, np.maximum(s - 0.5, 0.0))
        b = self._interpolate(lane, np.minimum(s + 0.5, self.length_m[k]))
        return self._interpolate(lane, s), np.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0])

    def _near_pairs_geos(self, xy: np.ndarray):
        """(point, lane) pairs within ``search_m`` from the STRtree (point-major, the tree's order within a point), with
        each pair's distance and arc length (:meth:`_project`): the reference :meth:`_near_pairs` reproduces."""
        qi, li = self.tree.query(self._shapely.points(xy), predicate="dwithin", distance=self.search_m)
        li = li.astype(np.int64)
        d, s = self._project(xy[qi], li)
        return qi.astype(np.int64), li, d, s

    def _build_grid(self) -> None:
        """Spatial hash of the lane segments for :meth:`_near_pairs`: square cells of ``search_m``; a segment is listed
        in every cell its bounding box grown by ``search_m`` overlaps (so every point within ``search_m`` of it finds it
        in its own cell), per cell by the STRtree's order of the lanes (their rank in a query of the whole map: within
        a point the tree lists lanes in this order) and then segment order."""
        c = self.search_m
        a, b = self._seg_a, self._seg_a + self._seg_d
        lo, hi = np.minimum(a, b) - c, np.maximum(a, b) + c  # [S, 2] grown boxes
        self._grid_origin = lo.min(0)
        i0 = np.floor((lo - self._grid_origin) / c).astype(np.int64)  # [S, 2] first / last cell per axis
        i1 = np.floor((hi - self._grid_origin) / c).astype(np.int64)
        self._grid_ny = int(i1[:, 1].max()) + 1
        self._grid_nx = int(i1[:, 0].max()) + 1
        nx, ny = i1[:, 0] - i0[:, 0] + 1, i1[:, 1] - i0[:, 1] + 1
        cnt = nx * ny
        seg = np.repeat(np.arange(len(a)), cnt)
        k = np.arange(len(seg)) - np.repeat(np.cumsum(cnt) - cnt, cnt)  # index within the segment's cells
        ix = i0[seg, 0] + k // ny[seg]
        iy = i0[seg, 1] + k % ny[seg]
        key = ix * self._grid_ny + iy
        whole = self._shapely.box(*(self._grid_origin - 1.0), *(hi.max(0) + 1.0))
        rank = np.empty(len(self.lines), np.int64)
        rank[np.asarray(self.tree.query(whole), np.int64)] = np.arange(len(self.lines))
        seg_lane = np.repeat(np.arange(len(self.lines)), self._nseg)
        order = np.lexsort((seg, rank[seg_lane[seg]], key))
        key, self._grid_seg = key[order], seg[order]
        self._grid_keys, start = np.unique(key, return_index=True)
        self._grid_start = start
        self._grid_count = np.diff(np.r_[start, len(key)])
        self._seg_lane = seg_lane

    def _near_pairs(self, xy: np.ndarray):
        """The (point, lane) pairs within ``search_m`` [m] of points ``xy [n, 2]`` (``qi``, ``li``: point-major, lanes in
        the STRtree's order within a point) with each pair's distance [m] and arc length [m] of the projection (the
        first nearest segment on ties), exactly as :meth:`_near_pairs_geos` but from a spatial hash of the segments:
        one pass over each point's cell instead of a tree query and a projection onto every segment of every lane
        found (a 700-vehicle decision of the position drive locates 3,500 planned frames)."""
        if not hasattr(self, "_grid_keys"):
            self._build_grid()
        c = self.search_m
        cell = np.floor((xy - self._grid_origin) / c)
        inside = (cell[:, 0] >= 0) & (cell[:, 0] < self._grid_nx) & (cell[:, 1] >= 0) & (cell[:, 1] < self._grid_ny)
        key = np.where(inside, cell[:, 0] * self._grid_ny + cell[:, 1], -1).astype(np.int64)
        pos = np.minimum(np.searchsorted(self._grid_keys, key), len(self._grid_keys) - 1)
        hit = inside & (self._grid_keys[pos] == key)
        cnt = np.where(hit, self._grid_count[pos], 0)
        pt = np.repeat(np.arange(len(xy)), cnt)  # [R] (point, segment) candidates, point-major
        if not len(pt):
            e = np.zeros(0, np.int64)
            return e, e, np.zeros(0), np.zeros(0)
        off = np.arange(len(pt)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        j = self._grid_seg[np.repeat(self._grid_start[pos], cnt) + off]  # [R] segment
        t, dist = self._onto_segments(xy[pt], j)
        lane = self._seg_lane[j]
        start = np.flatnonzero(np.r_[True, (pt[1:] != pt[:-1]) | (lane[1:] != lane[:-1])])  # (point, lane) groups
        first = _first_min_per_group(dist, start)  # each lane's first nearest segment
        keep = dist[first] <= c
        first = first[keep]
        return pt[first], lane[first], dist[first], self._seg_s0[j[first]] + t[first] * self._seg_len[j[first]]

    def locate(self, xy: np.ndarray, yaw: np.ndarray):
        n = len(xy)
        lane = np.full(n, -1, np.int64)
        dist = np.full(n, np.inf)
        along = np.zeros(n)
        if n == 0:
            return lane, dist, np.zeros(0), along
        qi, li, d, s = self._near_pairs(np.asarray(xy, np.float64))  # [K] pairs, distance, arc length [m]
        if len(qi):
            a = self._interpolate(li, np.maximum(s - 0.5, 0.0))
            b = self._interpolate(li, s + 0.5)
            lane_yaw = np.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0])
            cost = d + self.heading_weight_m * (1.0 - np.cos(wrap_angle(lane_yaw - yaw[qi])))
            start = np.flatnonzero(np.r_[True, qi[1:] != qi[:-1]])  # each point's first pair
            first = _first_min_per_group(cost, start)  # least cost; the first listed on ties
            lane[qi[first]], dist[qi[first]], along[qi[first]] = li[first], d[first], s[first]
        half = np.where(lane >= 0, self.half_width_m[np.maximum(lane, 0)], 0.0)
        return lane, dist, half, along


# ---------------------------------------------------------------------------- bookkeeping


@dataclass
class VehicleRecord:
    """What the controller knows of one vehicle; ``state``: sumo / controlled / handed_back / left."""

    slot: int
    type_id: str
    selected: bool
    depart_time_s: float
    state: str = "sumo"
    ever_controlled: bool = False
    reason: str = ""  # hand-back reason or how it left (arrived / removed)
    modes: tuple[int, int] = (31, 1621)  # speed mode, lane-change mode before take-over
    route: tuple[str, ...] = ()
    plan_step: int = -1  # controller step of its current plan (-1: none yet)
    free_move: bool = False  # next move uses keepRoute 2 (it left its route)
    pending_target: str = ""  # destination edge to restore after a keepRoute-2 move
    still_s: float = 0.0  # [s] how long it has been standing (speed < STILL_SPEED_MPS) under the policy
    limits: VehicleLimits | None = None  # its type's speed / acceleration limits and class (at take-over)
    lat_drift_m: float = 0.0  # commands drive: summed lateral drift of its plans [m] (+ = left)
    lc_target: tuple[str, int] | None = None  # commands drive: (edge, lane index) of a pending lane change
    last_lane: tuple[str, int] | None = None  # commands drive: (edge, lane index) at its last decision
    handback_edge: str = ""  # edge of its ``wrong_lane`` hand-back (it is retaken on a later edge of its route)
    route_merge: bool = False  # commands drive: on a lane that ends short of its route: SUMO drives its speed
    junction_still_s: float = 0.0  # [s] handed back and standing inside a junction (internal lane) in one go
    deadlock_release: bool = False  # let out of a junction deadlock: right of way ignored until it leaves the junction
    snap_in_junction: bool = False  # position drive: left on no lane inside a junction: moves snap onto its route's lane
    snap_plan: int = -1  # position drive: plan_step of the plan whose moves snap onto its lane (it stood over the centre line)


@dataclass
class ControllerStats:
    """Counters of one controller run (native runs fill the traffic ones too). Every field says its meaning and unit
    (:func:`r1sim_sumo.sim.stat_fields.legend` prints them); collision events are counted once per vehicle pair and
    event, see :data:`~r1sim_sumo.sim.collision_events.COLLISION_EVENT_GAP_S`."""

    # -- traffic
    steps: int = count("simulation steps of 0.1 s seen by the controller", "steps")
    sim_seconds: float = amount("simulated time", "s")
    departed: int = count("vehicles SUMO inserted", "vehicles")
    arrived: int = count("vehicles that completed their route", "vehicles")
    removed: int = count("vehicles that left without arriving (see removals)", "vehicles")
    removals: Counter = tally("vehicles that left without arriving", "vehicles by reason")
    loaded: int = count("vehicles SUMO loaded from the demand so far", "vehicles")
    waiting_to_insert: int = count("due to depart but not yet inserted by SUMO (now)", "vehicles")
    waiting_to_insert_max: int = count("the most waiting to insert at any step (blocked insertions)", "vehicles")
    running: int = count("vehicles in the network now", "vehicles")
    teleports: int = count("SUMO teleports", "teleports")
    warnings: Counter = tally("SUMO warnings (filled by `r1sim simulate`)", "warnings by kind")
    vkm_all: float = amount("distance driven by all vehicles", "vehicle-km")
    speed_sum_mps: float = amount("sum over vehicle-steps of speed (for the mean)", "m/s x vehicle-steps")
    vehicle_steps: int = count("one vehicle for one 0.1 s step, summed", "vehicle-steps")
    standing_steps: int = count("vehicle-steps with speed below STILL_SPEED_MPS", "vehicle-steps")
    longest_standstill_s: float = amount("the longest a vehicle stood (< STILL_SPEED_MPS) in one go", "s")
    stood_over_60s: int = count("stood more than 60 s in one go (a queue that did not clear)", "vehicles")
    longest_queue_growth_s: float = amount("the longest a queue of standing vehicles grew without clearing "
                                           "(r1sim_sumo.sim.queue_growth)", "s")
    longest_queue_head: str = label("the lane at the head of that queue", "lane id, or <insertion>")
    queues_grown_over_60s: int = count("queues that grew for more than 60 s without clearing", "queues")
    free_road_samples: int = count("vehicle-samples on a free road (r1sim_sumo.sim.free_road_speed; filled by "
                                   "`r1sim simulate`)", "vehicle-samples")
    free_road_speed_share_sum: float = amount("sum over free-road samples of speed / desired speed", "samples")
    # -- collisions, each vehicle pair and event once
    collisions_sumo: int = count("SUMO-reported collisions of any vehicles", "events")
    collisions_sumo_controlled: int = count("SUMO-reported collisions involving a controlled vehicle", "events")
    collisions_sat: int = count("box overlaps (SAT) of any two vehicles", "events")
    collisions_sat_controlled: int = count("box overlaps involving a controlled vehicle", "events")
    collisions_any: int = count("vehicle pairs colliding by either check", "events")
    collision_events: list = listing("the run's first collision events (EVENTS_LISTED), one record each: time_s, check "
                                     "(sumo / box), the pair a / b, each one's lane, speed and driver "
                                     "(controlled / handed_back / sumo)", "records")
    # -- the policy's vehicles
    drive: str = label("how the policy drives", "commands / position, empty for a native run")
    controlled_total: int = count("vehicles ever handed to the policy", "vehicles")
    controlled_arrived: int = count("controlled vehicles that completed their route", "vehicles")
    controlled_left: int = count("controlled vehicles that left the simulation (arrived or removed)", "vehicles")
    controlled_now: int = count("vehicles the policy drives now", "vehicles")
    vkm_controlled: float = amount("distance driven by controlled vehicles", "vehicle-km")
    vkm_sumo_driven: float = amount("commands drive: distance driven by controlled vehicles while SUMO drove their speed "
                                    "(route merges, junction crossings, merge yields)", "vehicle-km")
    handbacks: Counter = tally("vehicles handed back to SUMO", "vehicles by reason")
    retakes: int = count("taken back by the policy after a standstill hand-off", "vehicles")
    offroad: int = count("controlled vehicles found off every lane (then handed back)", "vehicles")
    reroutes: Counter = tally("route changes of controlled vehicles", "vehicles by changed_target / dead_end")
    # -- what SUMO or the rules overruled
    speed_commands: int = count("commands drive: steps with a commanded speed", "vehicle-steps")
    speed_capped: int = count("commands drive: SUMO drove slower than commanded", "vehicle-steps")
    lane_change_requests: int = count("commands drive: lane changes asked of SUMO", "requests")
    lane_change_refused: int = count("commands drive: lane changes not done within 0.5 s", "requests")
    lane_changes_policy: int = count("commands drive: lane changes to the lane the policy asked for (seen at its "
                                     "decisions, within an edge)", "lane changes")
    lane_changes_sumo: int = count("commands drive: lane changes SUMO made on its own (route, room for a merging "
                                   "vehicle, overtaking with lane_changes='policy+overtaking')", "lane changes")
    route_merge_decisions: int = count("commands drive: SUMO drove the speed for a lane change the route needs",
                                       "vehicle-decisions")
    crossing_decisions: int = count("commands drive, junction_crossings='sumo': SUMO drove the speed through a "
                                    "junction where the vehicle may have to stop", "vehicle-decisions")
    merge_yields: int = count("commands drive: decisions a controlled vehicle was driven by SUMO because it blocked a "
                              "vehicle that urgently needed its lane (merge cooperation)", "vehicle-decisions")
    rule_stops: Counter = tally("position drive: decisions with a stop imposed", "decisions by red / yield")
    junction_snaps: int = count("position drive: left on no lane inside a junction, then snapped onto its route's lane",
                                "vehicles")
    carriageway_fixes: int = count("position drive: plans moved sideways back onto the carriageway", "plans")
    centre_line_snaps: int = count("position drive: plans of a vehicle standing over the centre line (its box in the "
                                   "other direction's lane) that snapped it back onto its lane", "plans")
    against_lane: int = count("position drive: handed back turning against their lane (heading more than 45 degrees "
                              "off it on a normal lane, away from its ends: turning around on the road)", "vehicles")
    lane_split_keeps: int = count("position drive: plans inside a junction without conflicts (a lane split, a taper) "
                                  "moved sideways back into the internal lane SUMO has the vehicle on", "plans")
    lane_permission_fixes: int = count("position drive: kept on their lane (the next bans the class)", "plans")
    lane_changes_held: int = count("position drive: plans held inside their lane because SUMO's lane-change model "
                                   "found the change into the lane beside unsafe (a blocking leader or follower)", "plans")
    speed_limited: int = count("position drive: capped by the type's max speed or accel", "vehicle-steps")
    safety_slowdowns: int = count("the safety filter slowed a controlled vehicle", "vehicle-steps")
    decel_limited: int = count("position drive, open road: a plan braking harder than the type's comfortable "
                               "deceleration, not followed (the vehicle brakes at that deceleration)", "vehicle-steps")
    junction_deadlocks: int = count("handed-back vehicles let out of a junction they stood in (deadlock)", "vehicles")
    speed_carry_decisions: int = count("decisions of a controlled vehicle whose plan carried its speed-up (speed_carry='free')",
                                       "vehicle-decisions")
    free_road_decisions: int = count("decisions of a controlled vehicle on a free road, decoded at free_road_quantile",
                                     "vehicle-decisions")
    junction_floor_raised: int = count("commands drive: speed commands inside a junction raised to junction_floor_mps "
                                       "(SUMO's checks still apply)", "vehicle-steps")
    # -- cost
    policy_calls: int = count("policy decisions (one per 0.5 s with vehicles to drive)", "decisions")
    policy_errors: int = count("policy decisions that raised (their vehicles went back to SUMO)", "decisions")
    policy_agents: int = count("agents passed to the policy, summed over decisions", "agents")
    time_policy_s: float = amount("wall time in the policy", "s")
    time_read_s: float = amount("wall time reading SUMO's vehicle states", "s")
    time_move_s: float = amount("wall time applying moves or commands", "s")
    time_checks_s: float = amount("wall time counting events and bookkeeping, policy excluded", "s")

    @property
    def mean_speed_mps(self) -> float:
        return self.speed_sum_mps / max(self.vehicle_steps, 1)

    @property
    def collisions_per_1000_vkm(self) -> float:
        return 1000.0 * self.collisions_any / max(self.vkm_all, 1e-9)

    def summary(self) -> dict:
        """Plain dict of every counter (JSON-ready) plus derived rates."""
        d = {k: (dict(v) if isinstance(v, Counter) else v) for k, v in self.__dict__.items()}
        d["mean_speed_mps"] = self.mean_speed_mps
        d["collisions_per_1000_vkm"] = self.collisions_per_1000_vkm
        d["policy_vkm_share"] = ((self.vkm_controlled - self.vkm_sumo_driven) / self.vkm_all  # what the policy drove
                                 if self.vkm_all > 0 else None)
        d["completed_route_share"] = self.controlled_arrived / self.controlled_left if self.controlled_left else None
        left = self.arrived + self.removed
        d["arrived_of_left_share"] = self.arrived / left if left else None
        d["standing_share"] = self.standing_steps / self.vehicle_steps if self.vehicle_steps else None
        d["free_road_speed_share"] = (self.free_road_speed_share_sum / self.free_road_samples
                                      if self.free_road_samples else None)
        d["speed_capped_share"] = self.speed_capped / self.speed_commands if self.speed_commands else None
        d["lane_change_refused_share"] = (self.lane_change_refused / self.lane_change_requests
                                          if self.lane_change_requests else None)
        d["balanced"] = self.departed == self.arrived + self.removed + self.running
        return d


def removal_reason(conn, vid: str, rec: VehicleRecord) -> str:
    """Why a vehicle left without arriving, as far as the controller knows: ``offroad_removed`` (the controller's
    ``offroad_action='remove'``), ``while_policy_driven`` (SUMO or the user removed it while the policy drove it, e.g.
    a ``moveToXY`` that left it off every lane) or ``while_sumo_driven``."""
    if rec.reason == "offroad":
        return "offroad_removed"
    return "while_policy_driven" if rec.state == "controlled" else "while_sumo_driven"


def _break_mutual_blocks(ego_rows: np.ndarray, lead: np.ndarray, gap: np.ndarray, states) -> np.ndarray:
    """Two controlled vehicles that each see the other as their leader (side by side at a merge or lane drop) would
    both wait for ever: the one further ahead along its own heading ignores the other (its gap becomes ``inf``)."""
    row_to_ego = {int(r): j for j, r in enumerate(ego_rows)}
    gap = gap.copy()
    for j, r in enumerate(ego_rows):
        o = int(lead[j])
        jo = row_to_ego.get(o, -1)
        if o < 0 or jo < 0 or int(lead[jo]) != int(r) or j > jo:
            continue
        # r and o block each other: who is ahead? compare o's position along r's heading
        dx, dy = states.x_m[o] - states.x_m[r], states.y_m[o] - states.y_m[r]
        lon = dx * np.cos(states.yaw_rad[r]) + dy * np.sin(states.yaw_rad[r])
        front = jo if lon > 0 else j
        gap[front] = np.inf
    return gap


def _step_listener(conn, controller: SumoController):
    """A SUMO step listener calling ``controller.step()`` after every ``simulationStep``.

    SUMO only accepts subclasses of its own ``StepListener`` (``libsumo.StepListener`` for libsumo,
    ``traci.StepListener`` for the traci module and its connections).
    """
    base = getattr(conn, "StepListener", None)
    if base is None:
        import traci

        base = traci.StepListener

    class _Listener(base):
        def step(self, t=0) -> bool:
            controller.step()
            return True

    return _Listener()


# ---------------------------------------------------------------------------- the controller


class SumoController:
    """Attach the policy to a running SUMO and let it drive the selected vehicles.

    :param conn: the ``libsumo`` module, the ``traci`` module or a ``traci`` connection, already started
        with ``--step-length 0.1``.
    :param policy: a loaded policy (``r1sim_sumo.load_policy()``) with ``.model`` and ``.vocab``.
    :param net_file: the ``.net.xml`` SUMO runs; ``None`` = ask SUMO (``simulation.getOption('net-file')``).
    :param control: ``all`` | ``vtype=<id>[,<id>]`` | ``id=<regex>`` | ``fraction=<0..1>``.
    :param sampler: sampler spec for the policy (``quantile:0.7,0.1``, ``median:0.1``, ``greedy``, ``topk:5``,
        ``entropy:16,80``...). Default (``None``): the drive's own, :data:`DROP_IN_SAMPLERS`. The commands drive's
        ``quantile:0.7,0.1`` (since session 53, docs/simulate/quantile_s53) is the median rule below centred on the
        0.7 quantile of the policy's forward travel instead of its median: the policy continues its previous token's
        speed rather than its trend (issue 19's copying, docs/training/README.md session 27), so the median gives back
        part of every speed-up; SUMO's own checks keep each commanded speed safe. Commands drive, 8 scenarios x seeds
        0-2: 12,633 vs median's 12,582 of native's 12,746 arrivals, no collision event where native has none, the
        free-road speed still under native's (speed / desired 0.78-0.93 vs 0.85-0.96). In the position drive (the
        policy's path, only the Krauss filter between it and a crash) it raised the roundabout's collision events from
        189 to 355 per 1000 vehicle-km (seed 0), so the position drive keeps ``median:0.1``.
        ``median:0.1`` (since session 47): deterministic like greedy, but the most
        likely token among those whose 0.5 s forward travel is within 0.1 m of the distribution's median travel, so a
        move-off or speed-up the policy spreads over many tokens is not lost to a single "keep what you do" mode
        (``r1sim_sumo.rollout.samplers``). Measured against greedy (docs/simulate/sampler_s47): commands drive, 8
        scenarios x seeds 0-2, 12,607 vs 12,539 of native's 12,746 arrivals; roundabout / game/ramp / game/grid6 over
        seeds 0-7 0.981 / 0.944 / 0.974 vs 0.967 / 0.929 / 0.967 of native's; one box-overlap event (game/ramp seed 2,
        two policy vehicles at a diverge at < 2 m/s) where greedy had none. Greedy (session 32, docs/simulate/
        sampler_s32) beat ``topk:5`` by +2.7-4.5% arrivals in the position drive: a policy that follows its own recent
        speed turns each sampled slower token into a lasting slowdown. The model card and the training recipe keep
        top-5 sampling; without the safety layer deterministic tokens gridlock dense junction networks. With
        ``intent:D`` each controlled vehicle decodes greedily but may draw a move to the side its route asks for
        (SUMO's best lanes: the lane it is on does not lead on, e.g. an acceleration lane) with the policy's own
        probability of that side (:meth:`_route_sides`); see ``r1sim_sumo.rollout.samplers``.
    :param seed: seed of the sampler and of the ``fraction`` draw.
    :param context_radius_m: SUMO-driven vehicles within this distance [m] of a controlled one are given
        to the policy as context.
    :param offroad_margin_m: a controlled vehicle whose centre is farther than half a lane width plus this
        [m] from every lane centre is off road.
    :param offroad_action: ``handback`` (SUMO drives it again) or ``remove`` (``vehicle.remove``).
    :param route_end_lookahead_s: on the last edge of its route, a vehicle within ``5 m + speed x this``
        [s] of the end is handed back so that SUMO makes it arrive.
    :param check_sat: count box overlaps (SAT) of controlled vehicles every step.
    :param standstill_handoff_s: a controlled vehicle standing still (< 0.3 m/s) this long [s] is handed to SUMO
        (reason ``standstill``: queues, red lights, junction yielding) and taken back by the policy once SUMO has it
        moving at >= ``RESUME_SPEED_SHARE`` (60%) of its allowed speed (``retakes``); ``None`` or 0: the policy
        keeps standing vehicles (then only the ``stuck`` rule applies). The share of vehicle-km the policy drove is in the summary.
    :param safety: ``krauss`` (default): controlled vehicles follow their planned path but never faster than a
        Krauss safe speed behind the vehicle ahead (:mod:`r1sim_sumo.sim.safety_filter`); ``none``: the raw
        policy (for measuring the model itself). In the commands drive the Krauss cap is applied to the speed
        command too, behind SUMO's own leader (``getLeader``): SUMO's speed check is its car-following model's
        own safe speed, which for models such as IDM is not collision-free when the policy has approached a
        slow queue too fast (issue 20, session 15: two rear-end collisions in 900 s of motorway_merge).
    :param drive: ``commands`` (default): each 0.5 s plan becomes a speed command per 0.1 s step
        (``setSpeed``) and, when its lateral drift adds up to a lane change, a ``changeLane`` (``changeSublane``
        with the sublane model); SUMO executes them with its own checks (speed mode 31, lane-change mode 534 or 518,
        ``lane_changes``)
        and keeps the vehicle on its route (it arrives, turns and yields as SUMO does). ``position``: the vehicle
        is placed on the plan with ``moveToXY`` (exact paths; SUMO's checks off, the ``safety`` layer instead).
    :param device: torch device of the policy.
    :param map_cache_dir: where the policy's encoding of this network is kept between runs (``default``:
        :func:`~r1sim_sumo.sim.policy_driver.default_map_cache_dir`; ``None``: encode every time).
    :param lazy_map: encode a map tile when a vehicle first comes near it instead of the whole network at start
        (:class:`~r1sim_sumo.sim.policy_driver.PolicyDriver`).
    :param lane_changes: commands drive: ``policy`` (lane-change mode 518): a vehicle changes lanes when the policy
        asks, or when SUMO must (its route, room for a merging vehicle); ``policy+overtaking`` (534, default): also
        SUMO's own speed-gain changes while no request of the policy is pending. Counted apart in
        ``lane_changes_policy`` / ``lane_changes_sumo``. The policy asks for few lane changes (125 in 900 s of
        motorway_merge, for 1,100 vehicles): without SUMO's overtaking, queues formed behind trucks; with it
        motorway_merge delivers 0.999 / 0.986 of native's arrivals instead of 0.989 / 0.981 (greedy sampler, seeds
        0 / 1; docs/simulate/sampler_s32).
    :param guidance: desired-speed guidance weight ``w`` of the policy (:class:`~r1sim_sumo.sim.policy_driver.PolicyDriver`):
        tokens from ``log p(. | desired) + w (log p(. | desired) - log p(. | desired unknown))``, each vehicle's
        desired speed being SUMO's (lane limit x speedFactor, capped by its type's maxSpeed). ``0``: off.
    :param brake_floor: position drive with the safety layer: ``open-road``: on the open road (farther than its braking
        distance + 20 m from the end of lanes that only go straight on along major links crossing nothing) a plan is
        followed braking no harder than the vehicle type's comfortable deceleration (the nano's retimed plans brake
        at up to 16 m/s^2; ``decel_limited``); ``off`` (default): the plan's braking as it is. Seeds 0 / 1 of the 8
        full-horizon scenarios (docs/simulate/position_s39): 7,690 vs 7,547 arrivals, 0.70 vs 0.66 of native's mean
        speed, 628 vs 567 collision events (lane_drop 0.997 of native's arrivals at 0.94 of its speed); a floor at
        junctions too multiplied their collision events by 1.5-7.6 (not offered).
    :param merge_cooperation: commands drive: a controlled vehicle that SUMO names as the blocking follower of a vehicle
        that urgently needs its lane (to stay on its route: an on-ramp's end, a turn lane) is driven by SUMO for the
        next 0.5 s and on until it is back near the speed it had (:data:`YIELD_RECOVER_MPS`, at most
        :data:`YIELD_MAX_S`), so that SUMO's cooperative speed adjustment (which a speed command overrides) can make
        room and SUMO's driver, not the policy, speeds the vehicle back up (:meth:`_cooperate_with_mergers`,
        ``merge_yields``). On by default since session 49: over 8 seeds of motorway_merge / urban_grid / lane_drop /
        game/ramp it delivered 24,651 vehicles against 24,595 without it (motorway_merge 0.993 vs 0.991 of native's
        arrivals, urban_grid 0.986 vs 0.980, game/ramp 0.956 vs 0.959, lane_drop equal; no collision event where native
        has none); without it, game/ramp's on-ramp vehicles stood at the end of the acceleration lane behind policy
        vehicles that never let them in (docs/simulate/merge_cooperation_s49).
    :param lane_change_gate: position drive with the safety layer: ``sumo`` (default): a plan that takes its vehicle's
        box over the line into the lane beside it goes ahead only where SUMO's lane-change model finds the change
        safe (no leader or follower on that side blocking it: ``vehicle.getLaneChangeState``, the gaps SUMO's own
        drivers need); otherwise the plan is held inside its lane (:meth:`_gate_lane_changes`,
        ``lane_changes_held``). The safety filter only looks ahead along the path, so a cut-in in front of a vehicle
        on the next lane was not checked at all. ``off``: not checked (measured in docs/simulate/gate_s42).
    :param along_lane: position drive with the safety layer, True (default, since session 65): frames the lane-change
        gate holds inside their lane or :meth:`_keep_on_carriageway` moves back over the centre line of a two-way road
        point along their lane, and a vehicle heading more than :data:`AGAINST_LANE_RAD` off its lane away from the
        lane's ends is handed back (``against_lane``); since session 66 also, inside a junction where lanes only split,
        planned boxes are kept in the internal lane SUMO has the vehicle on (:meth:`_keep_in_lane_split`). False: the
        planned yaw is kept, no such hand-back or keeping (before session 65; the policy-history data recipe pins it).
        Measured in docs/simulate/along_lane_s65 and docs/simulate/networks_s66.
    :param junction_turns: position drive with the safety layer: ``sumo`` (default, since session 60): a vehicle inside
        a junction whose plan leaves its route (ends more than :data:`OFF_ROUTE_IN_JUNCTION_M` from the internal lane
        it is on and from the lanes of its route's next edge that lane leads to), or whose way turns off the major
        road (onto an edge of lower SUMO priority: a roundabout's exits; since session 61), is handed to SUMO (reason
        ``junction_turn``) and taken back on a later edge of its route (:meth:`_hand_over_off_route_turns`). The
        policy has no route input: leaving the bundled roundabout (never trained on) it planned on along the ring, was
        snapped onto its exit lane and crawled there, and the ring queued behind it. ``policy``: such a vehicle stays
        the policy's, snapped onto its route's lane when it leaves every lane (:meth:`_junction_snaps`; before
        session 60). Measured in docs/simulate/junction_turns_s60 and docs/simulate/roundabout_s61.
    :param junction_crossings: ``None`` (default): the drive's own, :data:`DROP_IN_JUNCTION_CROSSINGS`. Commands drive:
        ``sumo`` lets SUMO drive the speed of a controlled vehicle inside a junction and within :func:`crossing_reach_m`
        of a crossing lane end (``crossing_decisions``; the policy's commands resume on the next edge; its default since
        session 64), ``policy`` (before) sends the policy's speed commands there too. Position drive (with or without the safety layer): ``sumo`` (its default, since session 63): SUMO drives
        a vehicle through every junction where it may have to stop (its lane's links are not all open: a signal, a
        link without priority, a turn, or links that cross inside the junction; :meth:`_crossing_at_end`), from
        :func:`crossing_reach_m` (``max(20 m, 3 s x its allowed speed)``, SUMO's front bumper) before its lane's end
        (reason ``junction_crossing``), and the policy takes it back on its route's next edge outside that reach. SUMO's
        junction model then sees it approach and orders it with the foes, as it does its own drivers; the policy
        drives the links between junctions (the report's ``policy_vkm_share`` says how much). ``policy``: the policy
        drives up to and through the junction, the safety layer stopping it for red lights and foes with right of way
        (before session 63: on urban_grid 4.6-7x native's box-overlap events, nearly all inside junctions). Measured in
        docs/simulate/junction_sumo_s63.
    :param junction_floor_mps: commands drive: inside a junction (an internal lane) the speed command is at least
        this [m/s]; SUMO's checks and the Krauss cap still stop the vehicle behind its leader, for foes with right of
        way and at red lights, so it only keeps a policy vehicle from standing inside a junction by its own choice
        (``junction_floor_raised``). ``0`` (default, :data:`DROP_IN_JUNCTION_FLOOR_MPS`): off; 2.0 removed game/ramp's
        one collision event where native has none but cost it 2-4% of its arrivals on each of seeds 0-2.
    :param free_road_quantile: with a ``median`` / ``quantile`` sampler, a controlled vehicle on a free road (nothing
        within 100 m ahead to slow for, :class:`~r1sim_sumo.sim.free_road_speed.FreeRoadSpeed`) is decoded at this
        quantile of its travel, every other one at the sampler's own (``free_road_decisions`` counts them); None
        (default): the sampler's own for all. Measured in docs/simulate/free_road_s55.
    :param free_road_headway_s: with ``free_road_quantile``: a leader within 100 m at least this headway [s] ahead
        (+ 2.5 m) and not slower than the vehicle still leaves its road free (None, default: any leader does).
    :param speed_carry: ``gains``: read each token's speed change against what the vehicle drove over its last 0.5 s
        where it is faster now than that 0.5 s's mean, so that the token that repeats it keeps the speed now
        (:class:`~r1sim_sumo.sim.policy_driver.PolicyDriver`'s ``speed_carry``,
        :func:`~r1sim_sumo.rollout.kernel.carry_speed`); ``free``: the same for the controlled vehicles on a free road
        only (:class:`~r1sim_sumo.sim.free_road_speed.FreeRoadSpeed`, a leader :data:`CARRY_LEADER_HEADWAY_S` or more
        ahead and not slower leaves it free); ``both``: slow-downs too, every vehicle; ``off``: each plan ends at its
        token's end pose, which gives back half of every speed-up at the next decision. Default (``None``): the drive's
        own, :data:`DROP_IN_SPEED_CARRY` (``gains`` in both since session 58), ``off`` for the position drive with
        ``safety='none'``. Measured in docs/simulate/speed_carry_s58.
    """


    def __init__(self, conn, policy, net_file: str | Path | None = None, control: str = "all",
                 sampler: str | None = None, seed: int = 0, context_radius_m: float = 50.0,
                 offroad_margin_m: float = 2.0, offroad_action: str = "handback",
                 route_end_lookahead_s: float = 1.0, check_sat: bool = True, device: str = "cpu",
                 safety: str = "krauss", standstill_handoff_s: float | None = 5.0, drive: str = "commands",
                 map_cache_dir: str | Path | None = "default", lazy_map: bool = True,
                 lane_changes: str = "policy+overtaking", guidance: float = DROP_IN_GUIDANCE,
                 merge_cooperation: bool = True, brake_floor: str = "off", lane_change_gate: str = "sumo",
                 junction_turns: str = "sumo", junction_crossings: str | None = None,
                 replan_every_s: float = DROP_IN_REPLAN_S, junction_floor_mps: float = DROP_IN_JUNCTION_FLOOR_MPS,
                 free_road_quantile: float | None = None, free_road_headway_s: float | None = None,
                 speed_carry: str | None = None, along_lane: bool = True):
        from r1sim_sumo.adapters.sumo_map import read_sumo_map
        from r1sim_sumo.sim.policy_driver import PolicyDriver, default_map_cache_dir

        self.conn = conn
        dt = float(conn.simulation.getDeltaT())
        if abs(dt - STEP_LENGTH_S) > 1e-9:
            raise ControllerError(f"SUMO step length is {dt} s; the controller needs {STEP_LENGTH_S} s (10 Hz states): "
                                  "start SUMO with '--step-length 0.1'")
        if drive not in DRIVES:
            raise ControllerError(f"drive='{drive}': use 'commands' (SUMO executes speed / lane-change commands) or "
                                  "'position' (the vehicle is placed on the planned path)")
        self.drive = drive
        if sampler is None:
            sampler = DROP_IN_SAMPLERS[drive]
        every = float(replan_every_s) / STEP_LENGTH_S
        if not (1 - 1e-9 <= every <= STEPS_PER_DECISION + 1e-9 and abs(every - round(every)) < 1e-6):
            raise ControllerError(f"replan_every_s={replan_every_s}: use a multiple of {STEP_LENGTH_S:g} s from "
                                  f"{STEP_LENGTH_S:g} to {STEPS_PER_DECISION * STEP_LENGTH_S:g} s (a plan covers 0.5 s)")
        self.decision_every = int(round(every))  # 0.1 s steps between decisions (5: every token, the default)
        if self.decision_every != STEPS_PER_DECISION and drive != "commands":
            raise ControllerError(f"replan_every_s={replan_every_s} needs drive='commands': the position drive replanning "
                                  "every 0.2 s delivered fewer vehicles with 2.5x the collision events "
                                  "(docs/simulate/replan_s44); use 0.5 with the position drive")
        if lane_changes not in LANE_CHANGE_SOURCES:
            raise ControllerError(f"lane_changes='{lane_changes}': use 'policy' (only the policy's lane changes, plus "
                                  "those SUMO needs for the route or to let a vehicle merge) or 'policy+overtaking' "
                                  "(also SUMO's own speed-gain changes while the policy asks for none)")
        self.lane_changes = lane_changes
        self.merge_cooperation = bool(merge_cooperation)
        if brake_floor not in BRAKE_FLOORS:
            raise ControllerError(f"brake_floor='{brake_floor}': use 'off' (the plan's braking as it is) or 'open-road' "
                                  "(no harder than the comfortable deceleration on the open road, position drive)")
        self.brake_floor = brake_floor
        if lane_change_gate not in LANE_CHANGE_GATES:
            raise ControllerError(f"lane_change_gate='{lane_change_gate}': use 'sumo' (a plan enters the next lane only "
                                  "where SUMO's lane-change model finds it safe, position drive) or 'off'")
        self.lane_change_gate = lane_change_gate
        self.along_lane = bool(along_lane)
        self._no_foe_lane: dict[str, bool] = {}  # internal lane -> it has no foes (_no_foe_internal)
        self._two_way: np.ndarray | None = None  # per locator lane, on first use (_two_way_lanes)
        if junction_turns not in JUNCTION_TURNS:
            raise ControllerError(f"junction_turns='{junction_turns}': use 'sumo' (a vehicle whose plan leaves its route "
                                  "inside a junction is driven through it by SUMO, position drive) or 'policy'")
        self.junction_turns = junction_turns
        if junction_crossings is None:
            junction_crossings = DROP_IN_JUNCTION_CROSSINGS[drive]
        if junction_crossings not in JUNCTION_CROSSINGS:
            raise ControllerError(f"junction_crossings='{junction_crossings}': use 'sumo' (SUMO drives a vehicle, or in "
                                  "the commands drive its speed, through a junction where it may have to stop), "
                                  "'policy', or None (the drive's own)")
        self.junction_crossings = junction_crossings
        self._crossing_end: dict[str, bool] = {}  # lane -> its end is a crossing (_crossing_at_end)
        self._edge_crossing: dict[str, bool] = {}  # edge -> a lane of it ends in a crossing (_edge_ends_in_crossing)
        self._way_through: dict[tuple[str, str], tuple[int, ...]] = {}  # (internal lane, next route edge) -> locator lanes
        self._route_way: dict[tuple[str, str, str], tuple[int, ...]] = {}  # (split lane, next edge, edge after) -> way
        self._split_ahead: dict[tuple[str, str, str], tuple | None] = {}  # (lane, next, after) -> _split_way_ahead
        if not (0.0 <= float(junction_floor_mps) <= 10.0):
            raise ControllerError(f"junction_floor_mps={junction_floor_mps}: use 0 (off) to 10 m/s, the least speed "
                                  "commanded to a controlled vehicle inside a junction (commands drive)")
        self.junction_floor_mps = float(junction_floor_mps)
        self._yield_until: dict[str, int] = {}  # controlled vehicle -> controller step until which SUMO drives its speed
        self._yield_from: dict[str, tuple[int, float]] = {}  # yielding vehicle -> (step the yield began, speed [m/s])
        self._lc_mode = COMMANDS_LANE_CHANGE_MODE | (SPEED_GAIN_LANE_CHANGES if lane_changes == "policy+overtaking" else 0)
        if safety not in ("krauss", "none"):
            raise ControllerError(f"safety='{safety}': use 'krauss' (safe-speed filter, default) or 'none' (raw policy)")
        self.safety = SafetyFilter() if safety == "krauss" else None
        self.standstill_handoff_s = float(standstill_handoff_s) if standstill_handoff_s else None
        if offroad_action not in ("handback", "remove"):
            raise ControllerError(f"offroad_action='{offroad_action}': use 'handback' or 'remove'")
        clear_static_cache(conn)  # a new simulation may reuse vehicle type ids of an earlier one with other sizes
        self.selection = Selection.parse(control, seed)
        if self.selection.kind == "vtype":
            self.selection.check_vtypes(set(conn.vehicletype.getIDList()))
        if net_file is None:
            net_file = conn.simulation.getOption("net-file")
        self.map = read_sumo_map(net_file)
        self.locator = LaneLocator(self.map)
        # locator rows of the junction lanes that turn off the major road (junction_turns="sumo")
        self._off_major_rows = frozenset(self.locator.index_of(x) for x in self.map.turns_off_major_road) - {-1}
        if map_cache_dir == "default":
            map_cache_dir = default_map_cache_dir()
        if speed_carry is None and drive in DROP_IN_SPEED_CARRY:
            speed_carry = "off" if drive == "position" and safety == "none" else DROP_IN_SPEED_CARRY[drive]
        if speed_carry not in SPEED_CARRY_MODES:
            raise ControllerError(f"speed_carry={speed_carry!r}: use one of {', '.join(SPEED_CARRY_MODES)}")
        try:
            # the memory keeps each agent's features of the decision 0.5 s before: with replanning more often every
            # decision reads the last 1.1 s afresh (three policy steps instead of one)
            self.driver = PolicyDriver(policy, self.map.polylines, sampler=sampler, seed=seed, device=device,
                                       memory=self.decision_every == STEPS_PER_DECISION, map_cache_dir=map_cache_dir,
                                       lazy_map=lazy_map, guidance=guidance,
                                       speed_carry="gains" if speed_carry == "free" else speed_carry)
        except ValueError as exc:
            if "guidance" in str(exc):
                raise ControllerError(str(exc)) from exc
            raise
        self._intent = bool(getattr(self.driver.sampler, "needs_lateral", False))
        if free_road_quantile is not None:
            if not 0.0 < float(free_road_quantile) < 1.0:
                raise ControllerError(f"free_road_quantile={free_road_quantile}: use a travel quantile in (0, 1), e.g. "
                                      "0.7, or None (off)")
            if getattr(self.driver.sampler, "kind", "") != "median":
                raise ControllerError(f"free_road_quantile={free_road_quantile} needs a median / quantile sampler "
                                      f"(e.g. median:0.1), not '{sampler}'")
        self.free_road_quantile = None if free_road_quantile is None else float(free_road_quantile)
        self.speed_carry = speed_carry
        self._free_road = FreeRoadSpeed(conn) if self.free_road_quantile is not None or speed_carry == "free" else None
        if free_road_headway_s is not None and not 0.0 < float(free_road_headway_s) <= 10.0:
            raise ControllerError(f"free_road_headway_s={free_road_headway_s}: use a headway in (0, 10] s, or None "
                                  "(any leader within 100 m makes the road not free)")
        if free_road_headway_s is not None and self.free_road_quantile is None:
            raise ControllerError(f"free_road_headway_s={free_road_headway_s} only refines free_road_quantile (which "
                                  "vehicles count as on a free road); give free_road_quantile too (r1sim simulate "
                                  "--free-road-quantile 0.7 --free-road-headway H), or leave the headway out")
        self.free_road_headway_s = None if free_road_headway_s is None else float(free_road_headway_s)
        self._side_cache: dict[tuple[str, str], int] = {}  # (vehicle, lane) -> side its route asks for
        self.context_radius_m = float(context_radius_m)
        self.offroad_margin_m = float(offroad_margin_m)
        self.offroad_action = offroad_action
        self.route_end_lookahead_s = float(route_end_lookahead_s)
        self.check_sat = bool(check_sat)
        self.stats = ControllerStats(drive=drive)
        self.permissions = LanePermissions(conn)
        self._lane_allowed: dict[str, np.ndarray] = {}  # vehicle class -> per locator lane: 1 allowed, 0 not, -1 unknown
        self._standstill = StandstillTracker()
        self._queues = QueueGrowthTracker(STILL_SPEED_MPS, STEP_LENGTH_S)
        self.collisions = CollisionCounter(check_sat)
        try:
            self.sublane = float(conn.simulation.getOption("lateral-resolution")) > 0
        except Exception:  # noqa: BLE001 - an older SUMO without the option query: no sublane model
            self.sublane = False
        self.vehicles: dict[str, VehicleRecord] = {}  # vehicles in the simulation now
        self.finished: OrderedDict[str, VehicleRecord] = OrderedDict()  # the last FINISHED_KEPT vehicles that left
        self.last_plan = None  # (ids [A] of controlled vehicles planned, Plan rows of them)
        # slot store: history ring buffers and plans, one row per vehicle in the simulation
        cap = 64
        self._hist = np.zeros((cap, N_HISTORY_10HZ, N_STATE), np.float64)  # [S, 11, 6]
        self._hist_valid = np.zeros((cap, N_HISTORY_10HZ), bool)  # [S, 11]
        self._size = np.zeros((cap, 2), np.float64)  # [S, 2] length, width [m]
        self._agent_type = np.zeros(cap, np.int8)  # [S]
        self.follower = PlanFollower(cap)  # position drive: each slot's plan and progress along it
        self._plan_speed = np.zeros((cap, 5), np.float64)  # [S, 5] commanded speed of each 0.1 s step [m/s]
        self._cmd_speed = np.full(cap, np.nan)  # [S] speed commanded for the step SUMO just made (nan: none)
        # [S] position drive: the speed [m/s] each slot was last moved at along its plan, and the step it was moved in
        self._moved_speed = np.zeros(cap)
        self._moved_at = np.full(cap, -2, np.int64)
        self._stop_m = np.full(cap, np.inf)  # [S] position drive: distance to the next stop, from the decision pose [m]
        self._open_road_m = np.zeros(cap)  # [S] position drive: open road ahead at the decision pose [m] (_lane_end_is_open)
        # [S, 4] its type's max speed [m/s], accel, decel, emergency decel [m/s^2] (VehicleRecord.limits; NaN: unknown)
        self._limits = np.full((cap, 4), np.nan)
        self._row_of_slot = np.full(cap, -1, np.int64)  # [S] row of each slot in this step's states (-1: not in them)
        self._open_end: dict[int, tuple[int, ...] | None] = {}  # locator lane -> the lanes it leads on to (_lane_links)
        self._open_beyond: dict[int, float] = {}  # locator lane -> open road after its end [m] (_open_road_beyond)
        self._free: list[int] = list(range(cap - 1, -1, -1))
        self._k = -1  # controller step counter (0.1 s)
        self._tl = self.map.has_traffic_lights
        self._listener_id = None
        self.paused = False  # pause(): SUMO drives every vehicle, the controller only keeps their histories
        self._moved_since_step = False  # a moveToXY sent since SUMO's last step (close(): settle_remote_control)

    # ------------------------------------------------------------------ public

    def step(self) -> None:
        """Advance the controller by one 0.1 s SUMO step (call right after ``simulationStep``)."""
        self._k += 1
        self._moved_since_step = False  # SUMO's step before this call carried out the moves of the last one
        k = self._k
        st = self.stats
        st.steps += 1
        st.sim_seconds += STEP_LENGTH_S
        t0 = time.perf_counter()
        self._sync_population()
        states = read_vehicle_states(self.conn)
        slots = self._record(states)
        t1 = time.perf_counter()
        st.time_read_s += t1 - t0
        self._count_events(states, slots)
        if self.drive == "commands":
            self._count_overruled(states, slots)
        policy_s = st.time_policy_s
        if k % self.decision_every == 0:
            self._decide(states, slots)
        t2 = time.perf_counter()
        st.time_checks_s += t2 - t1 - (st.time_policy_s - policy_s)
        if self.drive == "commands":
            self._command(k, states)
        else:
            self._move(k, states)
        st.time_move_s += time.perf_counter() - t2
        st.running = len(self.vehicles)
        st.controlled_now = sum(r.state == "controlled" for r in self.vehicles.values())

    def controlled_ids(self) -> list[str]:
        return [v for v, r in self.vehicles.items() if r.state == "controlled"]

    def release_all(self, reason: str = "released") -> None:
        """Hand every controlled vehicle back to SUMO (e.g. before ending your loop early)."""
        for vid in self.controlled_ids():
            self._hand_back(vid, reason)

    def pause(self) -> None:
        """Hand every controlled vehicle to SUMO and take none until :meth:`resume` (histories keep being recorded,
        so the policy can take over again at once)."""
        self.release_all("paused")
        self.paused = True

    def resume(self) -> None:
        """Take back, at the next 0.5 s decision, every selected vehicle :meth:`pause` gave to SUMO (and any new one)."""
        self.paused = False
        for rec in self.vehicles.values():
            if rec.state == "handed_back" and rec.reason == "paused":
                rec.state, rec.reason = "sumo", ""

    def close(self) -> None:
        """End the run: detach the step listener and close the SUMO connection (use it instead of ``conn.close()``).

        With libsumo, when this controller has sent ``moveToXY`` since SUMO's last step (position drive, or a
        hand-back), SUMO takes one more step first (:func:`r1sim_sumo.sumo_launch.settle_remote_control`): libsumo
        1.28 would otherwise keep those vehicles past ``close`` and the next simulation in this process that has
        vehicles of the same IDs at its first step (added through TraCI, or a loaded state) could crash on that step."""
        try:
            self.detach_step_listener()
            if self._moved_since_step:
                settle_remote_control(self.conn)
                self._moved_since_step = False
        finally:  # a SUMO that stopped responding is still closed (its socket released)
            self.conn.close()

    def attach_step_listener(self):
        """Register a SUMO step listener that calls :meth:`step` after every ``simulationStep``; returns its id."""
        self._listener_id = self.conn.addStepListener(_step_listener(self.conn, self))
        return self._listener_id

    def detach_step_listener(self) -> None:
        if self._listener_id is not None:
            self.conn.removeStepListener(self._listener_id)
            self._listener_id = None

    # ------------------------------------------------------------------ population

    def _slot(self) -> int:
        if not self._free:
            cap = len(self._agent_type)
            grow = lambda a: np.concatenate([a, np.zeros_like(a)])  # noqa: E731
            self._hist, self._hist_valid, self._size = grow(self._hist), grow(self._hist_valid), grow(self._size)
            self._agent_type = grow(self._agent_type)
            self.follower.ensure(2 * cap)
            self._plan_speed, self._cmd_speed, self._stop_m = grow(self._plan_speed), grow(self._cmd_speed), grow(self._stop_m)
            self._open_road_m, self._limits = grow(self._open_road_m), grow(self._limits)
            self._moved_speed, self._moved_at = grow(self._moved_speed), np.concatenate([self._moved_at, np.full(cap, -2, np.int64)])
            self._row_of_slot = np.full(2 * cap, -1, np.int64)
            self._free = list(range(2 * cap - 1, cap - 1, -1))
        s = self._free.pop()
        self._hist_valid[s] = False
        self._cmd_speed[s], self._stop_m[s], self._open_road_m[s], self._limits[s] = np.nan, np.inf, 0.0, np.nan
        self._moved_at[s] = -2
        return s

    def _sync_population(self) -> None:
        """Register new vehicles, release those that left (arrived or removed)."""
        c, st = self.conn, self.stats
        present = c.vehicle.getIDList()
        now = float(c.simulation.getTime())
        present_set = set(present)
        gone = [v for v in self.vehicles if v not in present_set]
        if gone:
            arrived = set(c.simulation.getArrivedIDList())
            for vid in gone:
                rec = self.vehicles.pop(vid)
                how = "arrived" if vid in arrived else "removed"
                if how == "arrived":
                    st.arrived += 1
                else:
                    st.removed += 1
                    st.removals[removal_reason(c, vid, rec)] += 1
                    if rec.state == "controlled":
                        LOG.info("controlled vehicle %s left the simulation without arriving (removed)", vid)
                if rec.ever_controlled:
                    st.controlled_left += 1
                    st.controlled_arrived += how == "arrived"
                rec.reason = rec.reason or how
                rec.state = "left"
                self._free.append(rec.slot)
                self.finished[vid] = rec
                if len(self.finished) > FINISHED_KEPT:  # bounded: a day-long run must not grow with every vehicle
                    self.finished.popitem(last=False)
        st.teleports += len(c.simulation.getStartingTeleportIDList())
        st.loaded += c.simulation.getLoadedNumber()
        st.waiting_to_insert = len(c.simulation.getPendingVehicles())
        st.waiting_to_insert_max = max(st.waiting_to_insert_max, st.waiting_to_insert)
        for vid in present:
            if vid not in self.vehicles:
                tid = c.vehicle.getTypeID(vid)
                self.vehicles[vid] = VehicleRecord(self._slot(), tid, self.selection.selects(vid, tid), now)
                st.departed += 1

    def _record(self, states) -> np.ndarray:
        """Write this step's states into the ring buffers; returns the slot of each state row ``[N]``."""
        col = self._k % N_HISTORY_10HZ
        recs = self.vehicles
        slots = np.fromiter((recs[v].slot for v in states.ids), np.int64, len(states))
        self._row_of_slot[:] = -1
        self._row_of_slot[slots] = np.arange(len(slots))
        prev = (col - 1) % N_HISTORY_10HZ
        had_prev = self._hist_valid[slots, prev]
        self._hist_valid[:, col] = False
        row = np.stack([getattr(states, f) for f in _PER_STEP], -1)  # [N, 6]
        self._speed_as_moved(row, slots)
        self._hist[slots, col] = row
        self._hist_valid[slots, col] = True
        self._size[slots, 0], self._size[slots, 1] = states.length_m, states.width_m
        self._agent_type[slots] = states.agent_type
        st = self.stats
        step_m = np.hypot(*(row[:, :2] - self._hist[slots, prev, :2]).T) * had_prev  # [N]
        ctrl = np.fromiter((recs[v].state == "controlled" for v in states.ids), bool, len(states))
        st.vkm_all += float(step_m.sum()) / 1000.0
        st.vkm_controlled += float(step_m[ctrl].sum()) / 1000.0
        if self.drive == "commands":  # controlled, but SUMO drives the speed (route merge, crossing, merge yield)
            k, until = self._k, self._yield_until
            by_sumo = np.fromiter((recs[v].state == "controlled" and (recs[v].route_merge or until.get(v, -1) > k)
                                   for v in states.ids), bool, len(states))
            st.vkm_sumo_driven += float(step_m[by_sumo].sum()) / 1000.0
        st.speed_sum_mps += float(states.speed_mps.sum())
        st.standing_steps += int((np.abs(states.speed_mps) < STILL_SPEED_MPS).sum())
        self._standstill.update(st, states.ids, states.speed_mps)
        self._queues.update(st, self.conn, states.ids, states.speed_mps, self._k * STEP_LENGTH_S, st.waiting_to_insert)
        st.vehicle_steps += len(states)
        self._ctrl_mask = ctrl
        return slots

    def _speed_as_moved(self, row: np.ndarray, slots: np.ndarray) -> None:
        """Position drive: the history's speed [m/s] (and vx, vy) of each vehicle the last step moved is the speed it
        was moved at along its plan, not SUMO's ``getSpeed``. SUMO recomputes a moved vehicle's speed from its progress
        along its lanes and clips it to the lane's limit x speedFactor, so on entering a junction's internal lane or
        above that limit it reads low (a car moved at 3.9 m/s on the roundabout's ring read 0.8;
        session 59, docs/simulate/moved_speed_s59). That speed starts the next plan (:func:`retime_plan`'s ``v0``,
        :func:`carry_speed`): a reading too low made the plan brake first and then accelerate beyond the type's
        acceleration, and the safety layer held the vehicle below its plan. ``row [N, 6]`` is changed in place; the
        run's statistics keep SUMO's speed (as native runs are measured)."""
        moved = self._moved_at[slots] == self._k - 1  # moved by the controller's last step, carried out by SUMO's step
        if not moved.any():
            return
        v = self._moved_speed[slots[moved]]
        yaw = row[moved, 2]
        row[moved, 3], row[moved, 4], row[moved, 5] = v, v * np.cos(yaw), v * np.sin(yaw)

    def _history(self, slots: np.ndarray, ids: list[str]) -> AgentTracks:
        """``[A, 11]`` chronological history (last = now) of the vehicles in ``slots``."""
        order = (self._k + 1 + np.arange(N_HISTORY_10HZ)) % N_HISTORY_10HZ  # oldest .. newest column
        h = self._hist[slots][:, order]  # [A, 11, 6]
        tr = AgentTracks(
            ids=np.asarray(ids, dtype=str), agent_type=self._agent_type[slots].copy(),
            length_m=self._size[slots, 0].astype(np.float32), width_m=self._size[slots, 1].astype(np.float32),
            valid=self._hist_valid[slots][:, order],
            **{f: h[:, :, i].astype(np.float32) for i, f in enumerate(_PER_STEP)},
        )
        if getattr(self.driver, "wants_desired_speed", False):  # a stand-in driver (tests) may not have the property
            tr.desired_speed_mps = self._desired_speeds(ids)
        return tr

    def _desired_speeds(self, ids: list[str]) -> np.ndarray:
        """``[A]`` float32: the speed each SUMO driver wants on its current lane [m/s], the lane limit x its speedFactor
        (``getAllowedSpeed``) capped by its type's maxSpeed; NaN where SUMO cannot tell (then the policy estimates it)."""
        return read_desired_speeds(self.conn, ids)  # a failing query gives NaN: it must not crash the user's loop

    # ------------------------------------------------------------------ control hand-over / hand-back

    def _take(self, vid: str) -> bool:
        c, rec = self.conn, self.vehicles[vid]
        try:
            if rec.deadlock_release:  # its speed mode now is the deadlock one: keep the one it had
                rec.deadlock_release, rec.junction_still_s = False, 0.0
            else:
                rec.modes = (int(c.vehicle.getSpeedMode(vid)), int(c.vehicle.getLaneChangeMode(vid)))
            rec.route = tuple(c.vehicle.getRoute(vid))
            rec.limits = lim = rec.limits or VehicleLimits.of(c, vid)
            self._limits[rec.slot] = (lim.max_speed_mps, lim.accel_mps2, lim.decel_mps2, lim.emergency_decel_mps2)
            if self.drive == "commands":
                c.vehicle.setSpeedMode(vid, COMMANDS_SPEED_MODE)
                c.vehicle.setLaneChangeMode(vid, self._lc_mode)
            else:
                take_control(c, vid)
        except Exception as exc:  # noqa: BLE001 - TraCIException/libsumo error: leave it to SUMO
            LOG.warning("could not take control of %s (%s); it stays SUMO-driven", vid, exc)
            rec.state = "handed_back"
            rec.reason = "sumo_error"
            self.stats.handbacks["sumo_error"] += 1
            return False
        if rec.ever_controlled:
            self.stats.retakes += 1
        else:
            self.stats.controlled_total += 1
        rec.state, rec.ever_controlled, rec.still_s = "controlled", True, 0.0
        return True

    def _hand_back(self, vid: str, reason: str) -> None:
        rec = self.vehicles.get(vid)
        if rec is None or rec.state != "controlled":
            return
        rec.state, rec.reason, rec.route_merge = "handed_back", reason, False
        self.stats.handbacks[reason] += 1
        if reason not in ("route_end", "released", "standstill", "paused", "junction_crossing"):
            LOG.info("vehicle %s handed back to SUMO: %s", vid, reason)
        try:
            if reason == "offroad" and self.offroad_action == "remove":
                self.conn.vehicle.remove(vid)
                return
            if self.drive == "commands":  # SUMO drives on from where it is: give the speed back to its model
                self.conn.vehicle.setSpeed(vid, -1)
                self.conn.vehicle.setSpeedMode(vid, rec.modes[0])
                self.conn.vehicle.setLaneChangeMode(vid, rec.modes[1])
                return
            # put it back onto its route first: SUMO removes a vehicle left off its lanes by moveToXY. The move replaces
            # SUMO's next step of it, so it goes to where that step takes it (its pose now advanced by its speed): to
            # its pose now it stood still for 0.1 s, a stall that the policy read as braking when it took the vehicle
            # back and continued to a standstill (the acceleration lane of motorway_merge, session 39)
            x, y, yaw, v = self._hist[rec.slot, self._k % N_HISTORY_10HZ, :4]
            step_m = max(float(v), 0.0) * STEP_LENGTH_S
            x, y = x + step_m * np.cos(yaw), y + step_m * np.sin(yaw)
            x_fb, y_fb, ang = to_sumo_pose(x, y, yaw, self._size[rec.slot, 0])
            self._moved_since_step = True
            self.conn.vehicle.moveToXY(vid, "", -1, float(x_fb), float(y_fb), float(ang), KEEP_ROUTE_SNAP)
            self.conn.vehicle.setSpeedMode(vid, rec.modes[0])
            self.conn.vehicle.setLaneChangeMode(vid, rec.modes[1])
        except Exception as exc:  # noqa: BLE001
            LOG.warning("hand-back of %s failed (%s)", vid, exc)

    # ------------------------------------------------------------------ per-step checks

    def _count_events(self, states, slots) -> None:
        st = self.stats
        mask = self._ctrl_mask
        n = self.collisions.update(self.conn, states, lambda: {str(states.ids[i]) for i in np.flatnonzero(mask)})
        st.collisions_sumo += n.sumo
        st.collisions_sumo_controlled += n.sumo_marked
        st.collisions_sat += n.sat
        st.collisions_sat_controlled += n.sat_marked
        st.collisions_any += n.either
        self.collisions.list_new_events(st.collision_events, self.conn, st.sim_seconds, self._driver_of)

    def _driver_of(self, vid: str) -> str:
        """Who drives ``vid`` now: its record's state (``controlled``, ``handed_back``, ...) or ``sumo``."""
        rec = self.vehicles.get(vid)
        return "sumo" if rec is None else rec.state

    def _count_overruled(self, states, slots) -> None:
        """Commands drive: vehicle-steps in which SUMO drove slower than the speed commanded for that step."""
        cmd = self._cmd_speed[slots]  # [N]
        had = np.isfinite(cmd)
        if had.any():
            self.stats.speed_commands += int(had.sum())
            self.stats.speed_capped += int((states.speed_mps[had] < cmd[had] - SPEED_CAP_TOL_MPS).sum())
        self._cmd_speed[slots] = np.nan

    # ------------------------------------------------------------------ decisions (every 0.5 s)

    def _decide(self, states, slots) -> None:
        recs, st = self.vehicles, self.stats
        ids = [str(v) for v in states.ids]
        n_valid = self._hist_valid[slots].sum(1)  # [N]
        for i, vid in enumerate(ids):
            r = recs[vid]
            if self.paused:
                break
            if r.state == "sumo" and r.selected and n_valid[i] >= N_HISTORY_10HZ:
                if not self._sumo_crosses_here(vid):
                    self._take(vid)
            elif (r.state == "handed_back" and n_valid[i] >= N_HISTORY_10HZ and self._may_retake(vid, r, states.speed_mps[i])
                  and not self._sumo_crosses_here(vid)):
                self._take(vid)
        ctrl = np.array([recs[v].state == "controlled" for v in ids], bool)  # [N]
        self._release_junction_deadlocks(states)
        if ctrl.any():
            if self.drive == "commands":
                self._check_standing(states, ctrl)
            else:
                self._check_controlled(states, ctrl)
            ctrl = np.array([recs[v].state == "controlled" for v in ids], bool)
        self._ctrl_mask = ctrl
        if not ctrl.any():
            return
        # agents: controlled vehicles first, then SUMO-driven ones within the context radius
        ci, oi = np.flatnonzero(ctrl), np.flatnonzero(~ctrl)
        if len(oi):
            d2 = (states.x_m[oi, None] - states.x_m[None, ci]) ** 2 + (states.y_m[oi, None] - states.y_m[None, ci]) ** 2
            oi = oi[d2.min(1) <= self.context_radius_m**2]
        agents = np.concatenate([ci, oi])
        hist = self._history(slots[agents], [ids[i] for i in agents])
        tl = self.map.tl_states(self.conn) if self._tl else None
        sides = self._route_sides([ids[i] for i in ci], len(agents)) if self._intent else None
        q = self._decoding_quantiles([ids[i] for i in ci], len(agents))  # TraCI queries: not the policy's time
        carry = self._carry_mask([ids[i] for i in ci], len(agents))
        t0 = time.perf_counter()
        try:
            if carry is not None:
                plan = self.driver.plan(hist, tl, sides, q, carry)
            elif q is not None:
                plan = self.driver.plan(hist, tl, sides, q)
            else:
                plan = self.driver.plan(hist, tl) if sides is None else self.driver.plan(hist, tl, sides)
        except Exception as exc:  # noqa: BLE001 - never crash the user's loop
            st.policy_errors += 1
            LOG.warning("policy failed (%s: %s); %d vehicles handed back to SUMO", type(exc).__name__, exc, len(ci))
            for i in ci:
                self._hand_back(ids[i], "policy_error")
            return
        finally:
            st.time_policy_s += time.perf_counter() - t0
            st.policy_calls += 1
            st.policy_agents += len(agents)
        nc = len(ci)
        cs = slots[ci]
        self.follower.set_plans(cs, plan.xy_m[:nc], plan.yaw_rad[:nc])
        self._plan_speed[cs] = self._lane_speeds(plan, hist, nc) if self.drive == "commands" else plan.speed_mps[:nc]
        if self.drive == "commands":
            self._lane_change_intents([ids[i] for i in ci], states, ci, plan)
        elif self.safety is not None:
            self._apply_rules([ids[i] for i in ci], states, ci)
        for j, i in enumerate(ci):
            rec = recs[ids[i]]
            rec.plan_step = self._k
            if not plan.ok[j]:
                self._hand_back(ids[i], "plan_not_ok")
        self.last_plan = ([ids[i] for i in ci], plan)

    def _carry_mask(self, controlled: list[str], n_agents: int) -> np.ndarray | None:
        """``speed_carry="free"``: which agents' plans carry their speed-up ``[n_agents]`` (controlled vehicles first:
        those on a free road, leaders from :data:`CARRY_LEADER_HEADWAY_S`); None for every other setting."""
        if self.speed_carry != "free":
            return None
        m = np.zeros(n_agents, bool)
        for j, vid in enumerate(controlled):
            m[j] = self._free_road.is_free(vid, CARRY_LEADER_HEADWAY_S)
        self.stats.speed_carry_decisions += int(m.sum())
        return m

    def _decoding_quantiles(self, controlled: list[str], n_agents: int) -> np.ndarray | None:
        """Each agent's travel quantile for the ``median`` / ``quantile`` sampler ``[n_agents]`` (controlled vehicles
        first), or None when ``free_road_quantile`` is off: a controlled vehicle on a free road (nothing within 100 m
        ahead to slow for: no leader, signal, turn, yield or slower road; the report's free-road definition,
        :class:`~r1sim_sumo.sim.free_road_speed.FreeRoadSpeed`) is decoded at ``free_road_quantile``, every other
        agent at the sampler's own quantile. Why: the policy gives back part of every speed-up (issue 19's copying in
        speed), so after a slow-down the median of its travel creeps back to speed (position drive, docs/simulate/
        free_road_s55)."""
        if self.free_road_quantile is None:
            return None
        q = np.full(n_agents, float(self.driver.sampler.quantile), np.float32)
        for j, vid in enumerate(controlled):
            if self._free_road.is_free(vid, self.free_road_headway_s):
                q[j] = self.free_road_quantile
                self.stats.free_road_decisions += 1
        return q

    def _lane_speeds(self, plan, hist: AgentTracks, n: int) -> np.ndarray:
        """Commands drive: the speeds ``[n, 5]`` [m/s] to command SUMO for the first ``n`` agents' plans. A plan is a
        box-centre path; SUMO's speed is the front bumper's along its lane, faster in a curve by the ratio ``r`` of
        :func:`~r1sim_sumo.adapters.sumo_state.lane_speed_ratio` (each vehicle's, over its last 0.5 s). Each path is
        driven at one constant acceleration from the vehicle's box-centre speed now (SUMO's speed / r; the driver's own
        retiming starts from SUMO's speed, and so braked through every curve) and commanded x r. On a straight road r
        is 1 and the speeds are the plan's."""
        r = lane_speed_ratio(hist.x_m[:n], hist.y_m[:n], hist.speed_mps[:n], hist.valid[:n])  # [n]
        speed = plan.speed_mps[:n].astype(np.float64)
        if getattr(self.driver, "retime", False):
            v0 = np.where(hist.valid[:n, -1], hist.speed_mps[:n, -1] / r, np.nan)
            _, _, speed = retime_plan(plan.xy_m[:n], plan.yaw_rad[:n], v0, STEP_LENGTH_S)
        return (speed * r[:, None]).astype(self._plan_speed.dtype)

    def _release_junction_deadlocks(self, states) -> None:
        """At decisions: a vehicle the policy drove and handed back to SUMO that stands inside a junction (internal
        lane) for :data:`JUNCTION_DEADLOCK_S`, with nothing ahead until its length + :data:`JUNCTION_DEADLOCK_LEAD_M`
        beyond the junction (room to leave it), waits for a foe that waits for it (the policy left them in each
        other's way; SUMO drives them again but its junction model never lets either go). One such vehicle per
        junction and decision, and only one whose path holds no foe standing in a conflict area ahead of it
        (:meth:`_foe_in_the_way`), gets :data:`DEADLOCK_SPEED_MODE` (right of way ignored, still no faster than safe
        behind its leader, which includes a foe standing in its path inside the junction) and a speed command of
        :data:`DEADLOCK_SPEED_MPS` until it has left the junction; then its own speed mode and model are restored.
        Counted in ``junction_deadlocks``. Vehicles the policy never drove are SUMO's business and are left alone."""
        c, dt = self.conn, self.decision_every * STEP_LENGTH_S
        released_at: set[str] = set()  # junctions where a vehicle was let out at this decision: one at a time
        for i, v in enumerate(states.ids):
            vid = str(v)
            rec = self.vehicles[vid]
            if rec.state != "handed_back":
                continue
            try:
                lane = c.vehicle.getLaneID(vid)
                in_junction = lane.startswith(":")
                if rec.deadlock_release:
                    if not in_junction:
                        c.vehicle.setSpeed(vid, -1)
                        c.vehicle.setSpeedMode(vid, rec.modes[0])
                        rec.deadlock_release, rec.junction_still_s = False, 0.0
                    continue
                if abs(states.speed_mps[i]) >= STILL_SPEED_MPS or not in_junction:
                    rec.junction_still_s = 0.0
                    continue
                rec.junction_still_s += dt
                if rec.junction_still_s < JUNCTION_DEADLOCK_S:
                    continue
                exit_m = c.lane.getLength(lane) - c.vehicle.getLanePosition(vid) + JUNCTION_DEADLOCK_LEAD_M
                lead = c.vehicle.getLeader(vid, exit_m + float(self._size[rec.slot, 0]))
                if lead and lead[0]:  # it would stop again short of leaving the junction
                    continue
                junction = lane[1:].rsplit("_", 2)[0]
                if junction in released_at or self._foe_in_the_way(vid):
                    continue
                released_at.add(junction)
                c.vehicle.setSpeedMode(vid, DEADLOCK_SPEED_MODE)
                c.vehicle.setSpeed(vid, DEADLOCK_SPEED_MPS)
                rec.deadlock_release = True
                self.stats.junction_deadlocks += 1
                LOG.info("vehicle %s stood %.0f s inside a junction with nothing ahead: let out ignoring right of way",
                         vid, rec.junction_still_s)
            except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
                continue

    def _foe_in_the_way(self, vid: str) -> bool:
        """``vid`` may not be let out of the junction: it is not inside a conflict area of its path (then it blocks
        nobody by waiting) or a vehicle stands in a conflict area ahead of it (SUMO's junction foes: the foe between
        the area's entry and exit, ``vid`` before its entry; letting it go would drive it into that vehicle or knot
        the junction further)."""
        try:
            foes = self.conn.vehicle.getJunctionFoes(vid, JUNCTION_FOE_LOOK_M)
        except Exception:  # noqa: BLE001 - an older SUMO without the query: no release
            return True
        inside = any(f[1] <= 0.0 < f[3] for f in foes)  # ego between the entry and the exit of a conflict area
        return not inside or any(f[1] > 0.0 and f[2] <= 0.0 < f[4] for f in foes)

    def _check_controlled(self, states, ctrl: np.ndarray) -> None:
        """Off-road, end-of-route and off-route checks of the controlled vehicles (at decisions)."""
        recs, st, loc = self.vehicles, self.stats, self.locator
        ci = np.flatnonzero(ctrl)
        xy = np.stack([states.x_m[ci], states.y_m[ci]], -1)
        lane, dist, half, along = loc.locate(xy, states.yaw_rad[ci])
        against = self._against_lane(lane, along, xy, states.yaw_rad[ci])
        for j, i in enumerate(ci):
            vid = str(states.ids[i])
            rec = recs[vid]
            if lane[j] < 0 or dist[j] > half[j] + self.offroad_margin_m:
                st.offroad += 1
                self._hand_back(vid, "offroad")
                continue
            if against[j]:
                st.against_lane += 1
                road = loc.edge_id[lane[j]]
                rec.handback_edge = road if road in rec.route else self.conn.vehicle.getRoadID(vid)
                self._hand_back(vid, "against_lane")
                continue
            rec.still_s = rec.still_s + self.decision_every * STEP_LENGTH_S if abs(states.speed_mps[i]) < STILL_SPEED_MPS else 0.0
            if self.standstill_handoff_s is not None and rec.still_s >= self.standstill_handoff_s:
                self._hand_back(vid, "standstill")
                continue
            if rec.still_s >= STUCK_AFTER_S and self._nothing_ahead(vid):
                self._hand_back(vid, "stuck")
                continue
            if loc.is_internal[lane[j]]:
                self._open_road_m[rec.slot] = 0.0
                continue
            left_m = loc.length_m[lane[j]] - along[j]
            k = int(lane[j])
            if self.brake_floor == "open-road":
                self._open_road_m[rec.slot] = left_m + self._open_road_beyond(k) if self._lane_end_is_open(k) else 0.0
            edge = loc.edge_id[lane[j]]
            if edge not in rec.route:  # the policy took another way: follow it
                rec.pending_target = rec.route[-1] if rec.route else ""
                rec.route = (edge,)
                rec.free_move = True
                continue
            if edge == rec.route[-1]:
                if left_m <= 5.0 + abs(states.speed_mps[i]) * self.route_end_lookahead_s:
                    self._hand_back(vid, "route_end")
                continue
            allowed = self._allowed_speed(vid)
            if left_m <= (reach_m := STRATEGIC_LOOKAHEAD_S * allowed):
                # SUMO's lane decides (its lane may already be the next edge's while the box centre is on this one):
                # a vehicle handed back at the start of an acceleration lane was taken back 0.5 s later, being on a
                # later edge than the one it was handed back on (session 39)
                lane_now = self._near_lane_end(vid, reach_m)
                if lane_now is not None and self._wrong_lane(vid, lane_now):
                    rec.handback_edge = lane_now.rsplit("_", 1)[0]
                    self._hand_back(vid, "wrong_lane")
                    continue
            if self.junction_crossings == "sumo" and left_m <= (reach_m := crossing_reach_m(allowed)) + self._size[rec.slot, 0]:
                lane_now = self._near_lane_end(vid, reach_m)  # SUMO's front bumper within reach of its lane's end
                if lane_now is not None and self._crossing_at_end(lane_now):
                    rec.handback_edge = lane_now.rsplit("_", 1)[0]
                    self._hand_back(vid, "junction_crossing")

    def _against_lane(self, lane: np.ndarray, along: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        """``[n]`` bool: vehicles at ``xy [n, 2]`` (box centres [m]) heading ``yaw [n]`` [rad], located on ``lane`` at arc
        lengths ``along`` [m] (:meth:`LaneLocator.locate`), that turn against their lane: on a normal lane, more than
        :data:`AGAINST_LANE_CLEAR_M` from both its ends, heading more than :data:`AGAINST_LANE_RAD` off the lane's
        heading there. Position drive with the safety layer only (SUMO keeps the commands drive's vehicles along
        their lanes; the position drive without it is the policy unfiltered): all False otherwise."""
        loc = self.locator
        out = np.zeros(len(lane), bool)
        if self.drive != "position" or self.safety is None or not self.along_lane:
            return out
        k = np.maximum(lane, 0)
        clear = (along > AGAINST_LANE_CLEAR_M) & (loc.length_m[k] - along > AGAINST_LANE_CLEAR_M)
        ok = (lane >= 0) & ~loc.is_internal[k] & clear
        if ok.any():
            _, heading = loc.lateral_offset(k[ok], along[ok], xy[ok])
            out[ok] = np.abs(wrap_angle(np.asarray(yaw, np.float64)[ok] - heading)) > AGAINST_LANE_RAD
        return out

    def _lane_end_is_open(self, k: int) -> bool:
        """Locator lane ``k`` only goes straight on along major links (SUMO link state ``M``, direction ``s``) that
        cross no link from another lane inside the junction: no signal, turn, yield, crossing, lane end or network end
        where a vehicle may have to stop (cached)."""
        return self._lane_links(k) is not None

    def _lane_links(self, k: int) -> tuple[int, ...] | None:
        """Locator indices of the lanes that lane ``k``'s links lead to when its end is open, else ``None`` (cached)."""
        if k not in self._open_end:
            nxt = None
            try:
                links = self.conn.lane.getLinks(self.locator.lane_id[k])
                own = {lk[4] for lk in links}  # its links' internal lanes: a lane that splits crosses only itself
                if links and all(lk[5] == "M" and lk[6] == "s"
                                 and not (lk[4] and set(self.conn.lane.getInternalFoes(lk[4])) - own) for lk in links):
                    nxt = tuple(self.locator.index_of(lk[0]) for lk in links)
                    nxt = None if min(nxt) < 0 else nxt
            except Exception:  # noqa: BLE001 - unknown lane: treat its end as a junction
                nxt = None
            self._open_end[k] = nxt
        return self._open_end[k]

    def _open_road_beyond(self, k: int, depth: int = 4) -> float:
        """[m] open road after the end of lane ``k`` (whose end is open): the shortest of the lanes it leads to, plus
        what lies beyond each of them in turn (``depth`` lanes at most; cached per lane at the full depth)."""
        if depth == 4 and k in self._open_beyond:
            return self._open_beyond[k]
        nxt = self._lane_links(k)
        if nxt is None or depth == 0:
            d = 0.0
        else:
            d = min(float(self.locator.length_m[n]) + (self._open_road_beyond(n, depth - 1)
                                                      if self._lane_end_is_open(n) else 0.0) for n in nxt)
        if depth == 4:
            self._open_beyond[k] = d
        return d

    def _check_standing(self, states, ctrl: np.ndarray) -> None:
        """Commands drive: only the standstill hand-off, the stuck rule and the route-merge rule apply (SUMO keeps the
        vehicle on its route)."""
        rows = np.flatnonzero(ctrl)
        for vid, speed in zip(states.ids[rows].tolist(), states.speed_mps[rows].tolist(), strict=True):
            rec = self.vehicles[vid]
            self._check_route_merge(vid, rec, speed)
            rec.still_s = rec.still_s + self.decision_every * STEP_LENGTH_S if abs(speed) < STILL_SPEED_MPS else 0.0
            if self.standstill_handoff_s is not None and rec.still_s >= self.standstill_handoff_s:
                self._hand_back(vid, "standstill")
            elif rec.still_s >= STUCK_AFTER_S and self._nothing_ahead(vid):
                self._hand_back(vid, "stuck")
        if self.merge_cooperation:
            self._cooperate_with_mergers(states)

    def _merge_side(self, vid: str, speed_mps: float) -> int:
        """+1 / -1: ``vid`` is near the end of a lane that does not lead on along its route (:meth:`_near_lane_end`)
        and must change to the left / right (SUMO's best-lane offset: + = lanes to the left); 0 otherwise."""
        lane = self._near_lane_end(vid, route_merge_reach_m(speed_mps))
        best = None if lane is None else self._best_lane_entry(vid, lane)
        return 0 if best is None else int(np.sign(best[0]))

    def _cooperate_with_mergers(self, states) -> None:
        """Commands drive, at decisions: SUMO's drivers make room for a vehicle that must change lanes to stay on its
        route (an on-ramp's end, a lane that turns elsewhere) by adjusting their speed, which a speed command overrides.
        So a controlled vehicle that SUMO names as the blocking follower of such a vehicle (any driver: the policy's
        route-merging vehicles, vehicles handed back to SUMO, SUMO's own), while SUMO says that change is urgent, is
        driven by SUMO (``setSpeed(-1)``: its car-following and lane-change models, cooperation included) for the next
        0.5 s, and on until it is back within :data:`YIELD_RECOVER_MPS` of the speed it had when the yield began (at
        most :data:`YIELD_MAX_S`): the policy, handed the slowed vehicle, keeps the lower speed (issue 19's copying),
        so the road upstream of every merge lost speed yield after yield (session 49). Then the policy takes its speed
        again. Counted in ``merge_yields`` (vehicle-decisions)."""
        c, k, recs = self.conn, self._k, self.vehicles
        until, began = self._yield_until, self._yield_from
        speed_now = dict(zip(states.ids.tolist(), states.speed_mps.tolist(), strict=True))
        for vid in [v for v, u in until.items() if u <= k or v not in recs]:
            k0, v0 = began.get(vid, (k, 0.0))
            rec = recs.get(vid)
            if (rec is not None and rec.state == "controlled" and speed_now.get(vid, v0) < v0 - YIELD_RECOVER_MPS
                    and (k - k0) * STEP_LENGTH_S < YIELD_MAX_S):
                until[vid] = k + self.decision_every  # SUMO still drives it: it has not regained its speed
                self.stats.merge_yields += 1
                continue
            del until[vid]
            began.pop(vid, None)
        for vid, speed in zip(states.ids.tolist(), states.speed_mps.tolist(), strict=True):
            rec = recs.get(vid)
            if rec is None or (rec.state == "controlled" and not rec.route_merge):
                continue
            side = self._merge_side(vid, speed)
            if side == 0:
                continue
            try:
                lc_state = c.vehicle.getLaneChangeState(vid, side)[0]  # SUMO's own wish, without TraCI requests
                blocked = LCA_BLOCKED_BY_LEFT_FOLLOWER if side > 0 else LCA_BLOCKED_BY_RIGHT_FOLLOWER
                if not (lc_state & LCA_URGENT and lc_state & blocked):
                    continue
                mode = NEIGHBOURS_LEFT_BLOCKING_FOLLOWERS if side > 0 else NEIGHBOURS_RIGHT_BLOCKING_FOLLOWERS
                followers = c.vehicle.getNeighbors(vid, mode)
            except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
                continue
            for fid, _dist in followers:
                f = recs.get(fid)
                if f is None or f.state != "controlled" or f.route_merge:
                    continue
                if fid in until:  # already yielding (extended above, or named by another merger): counted once
                    continue
                try:
                    c.vehicle.setSpeed(fid, -1)  # SUMO drives its speed
                except Exception:  # noqa: BLE001
                    continue
                began[fid] = (k, speed_now.get(fid, 0.0))
                until[fid] = k + self.decision_every
                self.stats.merge_yields += 1

    def _check_route_merge(self, vid: str, rec: VehicleRecord, speed_mps: float) -> None:
        """Commands drive: a vehicle within ``max(WRONG_LANE_AHEAD_M, speed x WRONG_LANE_AHEAD_S)`` of the end of a
        lane that does not lead on along its route (an acceleration lane, a lane that turns elsewhere) must change
        lanes to stay on its route, which the policy does not know. Until it is on a lane that continues, SUMO drives
        its speed too (no speed commands, no policy lane-change requests): its lane-change model then slows or
        speeds up to find the gap and the vehicles around cooperate, as in a native run. Counted in
        ``route_merge_decisions``."""
        was = rec.route_merge
        try:
            lane = self._near_lane_end(vid, route_merge_reach_m(speed_mps))
            rec.route_merge = bool(lane is not None and self._wrong_lane(vid, lane))
            crossing = False
            if not rec.route_merge and self.junction_crossings == "sumo" and self._at_crossing(vid):
                # junction_crossings="sumo": SUMO drives the speed through a junction where it may have to stop
                rec.route_merge = crossing = True
            if rec.route_merge and not was:
                self.conn.vehicle.setSpeed(vid, -1)  # SUMO's car-following and lane-change models set the speed
        except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
            rec.route_merge = crossing = False
        if rec.route_merge:
            if crossing:
                self.stats.crossing_decisions += 1
            else:
                self.stats.route_merge_decisions += 1
            rec.lat_drift_m, rec.lc_target = 0.0, None

    def _lane_change_intents(self, vids: list[str], states, rows: np.ndarray, plan) -> None:
        """Commands drive: turn each plan's lateral motion into a lane-change request (or a sublane shift).

        The plan's point at the next decision (frame ``decision_every``: 5, its end, unless it replans more often) is
        expressed in the vehicle's frame; its lateral offset [m] (+ = left) is added to the vehicle's drift. Once the
        drift passes :data:`LANE_CHANGE_TRIGGER_M` the neighbouring lane on that side is requested for the next 0.5 s
        (``changeLane``); a request whose lane was not reached by the next decision counts as refused. With the
        sublane model the offset is handed over as is (``changeSublane``)."""
        c, st = self.conn, self.stats
        yaw = states.yaw_rad[rows]  # [n]
        d = plan.xy_m[: len(vids), self.decision_every] - plan.xy_m[: len(vids), 0]  # [n, 2] what is driven of it
        lats = (-np.sin(yaw) * d[:, 0] + np.cos(yaw) * d[:, 1]).tolist()  # [m] + = left
        for vid, lat in zip(vids, lats, strict=True):
            rec = self.vehicles[vid]
            if rec.state != "controlled" or rec.route_merge:
                continue
            try:
                if self.sublane:
                    if abs(lat) > 0.05:
                        c.vehicle.changeSublane(vid, lat)
                    continue
                lane = c.vehicle.getLaneID(vid)
                edge, idx = lane.rsplit("_", 1) if lane else ("", "0")
                idx = int(idx)
                if rec.last_lane is not None and rec.last_lane[0] == edge and rec.last_lane[1] != idx:
                    if rec.lc_target == (edge, idx):
                        st.lane_changes_policy += 1
                    else:
                        st.lane_changes_sumo += 1
                rec.last_lane = (edge, idx)
                if rec.lc_target is not None:  # the outcome of the last request
                    if (edge, idx) != rec.lc_target and edge == rec.lc_target[0]:
                        st.lane_change_refused += 1
                    rec.lc_target, rec.lat_drift_m = None, 0.0
                if edge.startswith(":"):  # no lane changes inside junctions
                    rec.lat_drift_m = 0.0
                    continue
                rec.lat_drift_m = rec.lat_drift_m + lat if lat * rec.lat_drift_m >= 0 else lat  # a reversal restarts it
                if abs(rec.lat_drift_m) < LANE_CHANGE_TRIGGER_M:
                    continue
                target = idx + (1 if rec.lat_drift_m > 0 else -1)
                rec.lat_drift_m = 0.0
                if not 0 <= target < c.edge.getLaneNumber(edge):
                    continue
                c.vehicle.changeLane(vid, target, STEPS_PER_DECISION * STEP_LENGTH_S)
                st.lane_change_requests += 1
                rec.lc_target = (edge, target)
            except Exception as exc:  # noqa: BLE001 - a failing request must not stop the others
                LOG.info("lane change request of %s failed (%s)", vid, exc)

    def _command(self, k: int, states=None) -> None:
        """Commands drive (every 0.1 s): the plan's speed for this step, as ``setSpeed`` (SUMO caps it by its checks),
        with ``safety='krauss'`` no faster than a Krauss safe speed behind SUMO's leader (:meth:`_krauss_caps`, one
        vectorised call for all vehicles). ``states``: this step's :func:`read_vehicle_states` (their speeds are SUMO's
        ``getSpeed`` now, read once instead of again per vehicle)."""
        todo: list[tuple[str, VehicleRecord]] = []
        yielding = {v for v, u in self._yield_until.items() if u > k}  # SUMO drives their speed (merge cooperation)
        plan_rows: list[int] = []
        plan_cols: list[int] = []
        for vid, rec in self.vehicles.items():
            if rec.state != "controlled" or rec.route_merge:
                continue
            j = k - rec.plan_step + 1
            if rec.plan_step < 0 or not 1 <= j <= 5 or vid in yielding:
                continue
            todo.append((vid, rec))
            plan_rows.append(rec.slot)
            plan_cols.append(j - 1)
        if not todo:
            return
        v = self._plan_speed[plan_rows, plan_cols].astype(np.float64)  # [n] this step's planned speeds [m/s]
        if self.junction_floor_mps > 0:
            v = self._junction_floor(todo, v)
        if self.safety is not None:
            speeds = None if states is None else dict(zip(states.ids.tolist(), states.speed_mps.tolist(), strict=True))
            v = self._krauss_caps(todo, v, speeds)
        set_speed = self.conn.vehicle.setSpeed
        cmd = self._cmd_speed
        for (vid, rec), vi in zip(todo, v.tolist(), strict=True):
            try:
                set_speed(vid, vi)
            except Exception as exc:  # noqa: BLE001
                LOG.warning("setSpeed of %s failed (%s)", vid, exc)
                self._hand_back(vid, "sumo_error")
                continue
            cmd[rec.slot] = vi

    def _junction_floor(self, todo: list[tuple[str, VehicleRecord]], v_cmd: np.ndarray) -> np.ndarray:
        """``v_cmd [n]`` [m/s] raised to ``junction_floor_mps`` for the vehicles inside a junction (SUMO road id
        starting with ``:``), counted in ``junction_floor_raised``. A vehicle whose road cannot be read keeps its
        command."""
        get_road = self.conn.vehicle.getRoadID
        low = np.flatnonzero(v_cmd < self.junction_floor_mps)
        if not len(low):
            return v_cmd
        out = v_cmd.copy()
        for i in low.tolist():
            try:
                inside = get_road(todo[i][0]).startswith(":")
            except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
                continue
            if inside:
                out[i] = self.junction_floor_mps
                self.stats.junction_floor_raised += 1
        return out

    def _krauss_caps(self, todo: list[tuple[str, VehicleRecord]], v_cmd: np.ndarray, speeds: dict | None = None) -> np.ndarray:
        """``v_cmd [n]`` [m/s], each capped by a Krauss safe speed behind the leader SUMO sees on the vehicle's route
        (gap net of its minGap, within the distance it needs to stop plus a reaction time and a margin), braking at its
        type's deceleration; SUMO's max-deceleration check still bounds how fast it slows. A vehicle whose query fails
        keeps its command (SUMO's own checks still apply). ``speeds``: id -> SUMO speed now [m/s] where already read."""
        c, sf = self.conn, self.safety
        speeds = speeds or {}
        get_speed, get_leader = c.vehicle.getSpeed, c.vehicle.getLeader
        n = len(todo)
        b = np.array([rec.limits.decel_mps2 if rec.limits else sf.decel_mps2 for _, rec in todo], np.float64)
        now = [speeds.get(vid) for vid, _ in todo]
        for i, v0 in enumerate(now):
            if v0 is None:
                try:
                    now[i] = get_speed(todo[i][0])
                except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
                    now[i] = np.nan  # no cap for it (as before: its command stands)
        v_now = np.asarray(now, np.float64)
        reach = (v_now * v_now / (2.0 * b) + v_now * sf.tau_s + 20.0).tolist()  # [m] how far each looks for a leader
        gap, v_lead = np.full(n, np.inf), np.zeros(n)
        for i, (vid, _rec) in enumerate(todo):
            if reach[i] != reach[i]:  # NaN: its speed could not be read
                continue
            try:
                lead = get_leader(vid, reach[i])
                if lead and lead[0] and lead[1] >= -1e3:
                    vl = speeds.get(lead[0])
                    gap[i], v_lead[i] = max(lead[1], 0.0), get_speed(lead[0]) if vl is None else vl
            except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
                gap[i], v_lead[i] = np.inf, 0.0
                continue
        v_now = np.nan_to_num(v_now, nan=0.0)
        v_safe = sf.safe_speed(v_now, gap, v_lead, b, min_gap_m=0.0)
        capped = v_safe < v_cmd
        self.stats.safety_slowdowns += int(capped.sum())
        return np.where(capped, v_safe, v_cmd)

    def _apply_rules(self, vids: list[str], states, rows: np.ndarray) -> None:
        """Position drive with the safety layer (at decisions): the distance to the next place each vehicle must
        stop (red / yellow signal, junction link without priority with a foe), and plans that would enter a lane
        its class may not use are pulled back onto its current lane (same arc lengths)."""
        c, st, loc = self.conn, self.stats, self.locator
        # speed of each vehicle: its planned speed or its own motion over the last 0.1 s (SUMO's getSpeed of a moved
        # vehicle lags it), whichever is higher; stops are looked for as far as it needs to brake from it, and more
        slots_ = np.array([self.vehicles[v].slot for v in vids], np.int64)
        col, prev = self._k % N_HISTORY_10HZ, (self._k - 1) % N_HISTORY_10HZ
        moved = np.hypot(*(self._hist[slots_, col, :2] - self._hist[slots_, prev, :2]).T) / STEP_LENGTH_S
        v_est = np.maximum(np.maximum(self._plan_speed[slots_].max(1), moved), np.abs(states.speed_mps[rows]))
        reach = np.maximum(self.safety.min_lookahead_m,
                           np.maximum(v_est * self.safety.lookahead_s, v_est**2 / (2.0 * self.safety.decel_mps2) + 10.0))
        for j, vid in enumerate(vids):
            rec = self.vehicles[vid]
            lim = rec.limits
            try:
                d, why = stop_distance(c, vid, float(v_est[j]), lim.decel_mps2 if lim else 4.5, float(reach[j]))
            except Exception:  # noqa: BLE001 - a query failing must not crash the user's loop
                d, why = np.inf, ""
            self._stop_m[rec.slot] = d
            if why:
                st.rule_stops[why] += 1
        if not len(vids):
            return
        slots = np.array([self.vehicles[v].slot for v in vids], np.int64)
        fol = self.follower
        xy = fol.xy[slots]  # [n, 6, 2]
        yaw = fol.yaw[slots]
        n = len(vids)
        located = loc.locate(xy[:, 1:].reshape(-1, 2), yaw[:, 1:].reshape(-1))  # lane, dist, half, along [n * 5] each
        lane = located[0].reshape(n, 5)
        fixed = np.zeros(n, bool)
        for j in np.flatnonzero(self._enters_forbidden_lane(vids, lane)).tolist():
            vid = vids[j]
            cur = c.vehicle.getLaneID(vid)
            k = loc.index_of(cur)
            if k < 0:
                continue
            s0 = float(c.vehicle.getLanePosition(vid)) - 0.5 * self._size[slots[j], 0]  # box centre along the lane
            p, a = loc.along(k, s0 + fol.arc[slots[j]])  # the same arc lengths (and timing) along the lane
            fol.xy[slots[j]], fol.yaw[slots[j]] = p, a
            fixed[j] = True
            st.lane_permission_fixes += 1
        if self.lane_change_gate == "sumo":
            fixed |= self._gate_lane_changes(vids, slots, located, fixed)
        self._keep_on_carriageway(slots, located, fixed)
        if self.along_lane:
            self._keep_in_lane_split(vids, slots)
        self._snap_standing_over_centre_line(slots)
        if self.junction_turns == "sumo":
            self._hand_over_off_route_turns(vids, slots)

    def _hand_over_off_route_turns(self, vids: list[str], slots: np.ndarray) -> None:
        """Position drive, at decisions (``junction_turns="sumo"``): each vehicle ``vids[j]`` on a junction's internal
        lane that turns off the major road (:attr:`SumoMap.turns_off_major_road`: a roundabout's exits; since session
        61) or whose new plan (``slots[j]``) ends more than :data:`OFF_ROUTE_IN_JUNCTION_M` from its way through the
        junction (:meth:`_way_through_lanes`; session 60) is handed to SUMO (reason ``junction_turn``);
        :meth:`_may_retake` takes it back once it is on a later edge of its route than the one it came from."""
        loc, fol = self.locator, self.follower
        for vid, slot in zip(vids, slots.tolist(), strict=True):
            rec = self.vehicles[vid]
            if rec.state != "controlled":
                continue
            found = self._junction_way(vid)
            if found is None:
                continue
            from_edge, way = found
            if way[0] not in self._off_major_rows:  # way[0]: the internal lane it is on; a turn off the major road: SUMO's
                end = np.repeat(fol.xy[slot, -1][None].astype(np.float64), len(way), 0)  # [w, 2] the plan's end (centre)
                if float(loc._project(end, np.asarray(way, np.int64))[0].min()) <= OFF_ROUTE_IN_JUNCTION_M:
                    continue  # its plan stays on its way: the policy's
            self._hand_back(vid, "junction_turn")
            rec.handback_edge = from_edge

    def _junction_way(self, vid: str) -> tuple[str, tuple[int, ...]] | None:
        """For a vehicle on a junction's internal lane: (the route edge it comes from, the locator rows of its way
        through the junction, :meth:`_way_through_lanes`); None elsewhere, at its route's end or when the way is
        unknown."""
        c = self.conn
        try:
            lane = c.vehicle.getLaneID(vid)
            if not lane.startswith(":"):
                return None
            route, i = c.vehicle.getRoute(vid), int(c.vehicle.getRouteIndex(vid))
        except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
            return None
        if not 0 <= i < len(route) - 1:
            return None
        way = self._way_through_lanes(lane, route[i + 1])
        if way and i + 2 < len(route) and self._no_foe_internal(lane):
            way = self._way_on_route(lane, route[i + 1], route[i + 2], way)
        return (route[i], way) if way else None

    def _way_on_route(self, lane: str, next_edge: str, after_edge: str, way: tuple[int, ...]) -> tuple[int, ...]:
        """In a lane split (:meth:`_no_foe_internal` ``lane``): ``way`` (through ``lane``) when its lane on ``next_edge``
        connects to ``after_edge``, the edge the route takes after it; else the way through the first of the split's
        other lanes (``lane``'s foes, which start where it starts) whose lane does (cached). SUMO maps a moved vehicle
        onto the internal lane nearest its position, and where a turn bay opens all start on the same line: a
        left-turner the policy drove straight was put on the through lane's branch, the lane-split keeper held it
        there, and on the short bay it stood waiting for a gap into the full left-turn lane, blocking the through lane
        for whole greens (session 67, urban_intersection: a queue growing 108 s)."""
        key = (lane, next_edge, after_edge)
        got = self._route_way.get(key)
        if got is None:
            got = way
            try:
                if not self._way_reaches(way, next_edge, after_edge):
                    for sib in self.conn.lane.getInternalFoes(lane):
                        w = self._way_through_lanes(sib, next_edge)
                        if w and self._way_reaches(w, next_edge, after_edge):
                            got = w
                            break
            except Exception:  # noqa: BLE001 - unknown lane: the way SUMO has it on
                got = way
            self._route_way[key] = got
        return got

    def _way_reaches(self, way: tuple[int, ...], next_edge: str, after_edge: str) -> bool:
        """Whether a lane of ``next_edge`` in ``way`` (locator rows) has a connection to ``after_edge``."""
        for r in way:
            lid = self.locator.lane_id[r]
            if lid.rsplit("_", 1)[0] == next_edge and any(
                    lk[0].rsplit("_", 1)[0] == after_edge for lk in self.conn.lane.getLinks(lid)):
                return True
        return False

    def _way_through_lanes(self, lane: str, next_edge: str) -> tuple[int, ...]:
        """Locator rows of internal ``lane``, of the internal lanes it leads on to (an internal junction splits a
        junction's way in two) and of the lanes of ``next_edge`` they lead to; empty when none of ``next_edge`` is
        reached or the map lacks one of them (cached)."""
        key = (lane, next_edge)
        if key not in self._way_through:
            way, after, todo = [lane], [], [lane]
            try:
                for _ in range(3):  # internal lanes in a row: 2 at most in SUMO's networks
                    nxt = []
                    for x in todo:
                        for lk in self.conn.lane.getLinks(x):
                            if lk[0].rsplit("_", 1)[0] == next_edge:
                                after.append(lk[0])
                            elif lk[0].startswith(":") and lk[0] not in way:
                                way.append(lk[0])
                                nxt.append(lk[0])
                    todo = nxt
                    if not todo:
                        break
            except Exception:  # noqa: BLE001 - unknown lane: no way known, no hand-over
                after = []
            rows = tuple(self.locator.index_of(x) for x in [*way, *after])
            self._way_through[key] = rows if after and min(rows) >= 0 else ()
        return self._way_through[key]

    def _enters_forbidden_lane(self, vids: list[str], lane: np.ndarray) -> np.ndarray:
        """Per vehicle ``vids[j]``: whether a planned frame lies on a lane (``lane [n, 5]``, locator rows, -1 none) its
        vehicle class may not use. SUMO's permissions are asked once per (lane, class) and kept in a table per class."""
        vclass = np.array([lim.vclass if (lim := self.vehicles[v].limits) is not None else "" for v in vids], object)
        bad = np.zeros(len(vids), bool)
        for vc in set(vclass.tolist()) - {""}:
            rows = np.flatnonzero(vclass == vc)
            table = self._lane_allowed.get(vc)
            if table is None:
                table = self._lane_allowed[vc] = np.full(len(self.locator.lane_id), -1, np.int8)  # -1: not asked yet
            k = lane[rows]
            on = k >= 0
            for q in np.unique(k[on & (table[np.maximum(k, 0)] < 0)]).tolist():
                table[q] = self.permissions.allows(self.locator.lane_id[q], vc)
            bad[rows] = (on & (table[np.maximum(k, 0)] == 0)).any(1)
        return bad

    def _gate_lane_changes(self, vids: list[str], slots: np.ndarray, located: tuple, fixed: np.ndarray) -> np.ndarray:
        """Position drive with the safety layer (at decisions, ``lane_change_gate="sumo"``): a plan whose box crosses
        the line of the lane it starts on (the lane of its first planned frame in ``located``,
        :meth:`LaneLocator.locate` of frames 1..5 of every plan; SUMO must have the vehicle on that lane too) by more
        than :data:`GATE_OVER_M` into a lane of the same edge beside it enters only if SUMO's lane-change model finds
        no leader or follower on that side blocking the change (and no vehicle overlapping the spot):
        ``vehicle.getLaneChangeState(vid, side)``, the safe gaps SUMO's own drivers keep.
        Otherwise every planned frame is moved sideways back inside the lane (same arc lengths and timing) and the
        frames moved point along it (since session 65), so the vehicle waits at the line as a SUMO driver waits for a
        gap. Plans already moved (``fixed``) are left alone.
        Returns ``[n]`` bool, the plans moved; counted in ``lane_changes_held``."""
        n = len(vids)
        held = np.zeros(n, bool)
        loc, fol, c = self.locator, self.follower, self.conn
        lane, dist, half = (np.asarray(a).reshape(n, 5) for a in located[:3])
        lane1 = lane[:, 0].copy()
        # a vehicle whose front bumper (SUMO's position) has left a junction while its box centre is still over the
        # junction's internal lane: the lane it starts on is SUMO's. Gating only from the first box centre on a normal
        # lane let plans cross into the next lane in the first metres after a bay taper, in front of a vehicle there
        # (session 67, urban_intersection: SUMO reported the change blocked)
        inside = np.flatnonzero((lane1 >= 0) & loc.is_internal[np.maximum(lane1, 0)] & ~fixed)
        for j in inside.tolist():
            try:
                k = loc.index_of(c.vehicle.getLaneID(vids[j]))
            except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
                continue
            if k >= 0 and not loc.is_internal[k]:
                lane1[j] = k
        ok = (lane1 >= 0) & ~fixed
        ok[ok] = ~loc.is_internal[lane1[ok]]
        # only a plan with a frame on another lane, or a box that can reach its lane's line, can cross it (cheap
        # pre-filter: a box yawed against its lane reaches at most half its diagonal across it)
        reach_n = 0.5 * np.hypot(self._size[slots, 0], self._size[slots, 1])
        ok &= (lane != lane1[:, None]).any(1) | ((dist + reach_n[:, None] - half).max(1) > GATE_OVER_M)
        rows = np.flatnonzero(ok)
        if not len(rows):
            return held
        k = np.repeat(lane1[rows], 5)  # [m * 5]: every frame against its first frame's lane
        xy = fol.xy[slots[rows]][:, 1:].reshape(-1, 2)
        _d, s = loc._project(xy, k)
        lat, heading = loc.lateral_offset(k, s, xy)  # [m] + = left of the lane's centreline
        hw = 0.5 * np.repeat(self._size[slots[rows], 1], 5)
        hl = 0.5 * np.repeat(self._size[slots[rows], 0], 5)
        half = loc.half_width_m[k]
        # the box's extent across its lane counts its yaw against it: a 12 m truck yawed 21 degrees reaches 2 m further
        # with its front corner, and SUMO maps a moved vehicle by its front bumper (session 67: such frames, their
        # centres inside the lane, put a truck onto the vehicle beside it)
        d = np.abs(np.angle(np.exp(1j * (fol.yaw[slots[rows]][:, 1:].reshape(-1) - heading))))  # [rad] yaw vs lane
        ext = hw * np.cos(np.minimum(d, 0.5 * np.pi)) + hl * np.sin(np.minimum(d, 0.5 * np.pi))  # [m]
        over_left = (lat + ext - half).reshape(-1, 5)
        over_right = (-lat + ext - half).reshape(-1, 5)
        # a held frame that points along its lane needs only its width inside the line
        back_left = (lat + (hw if self.along_lane else ext) - half).reshape(-1, 5)
        back_right = (-lat + (hw if self.along_lane else ext) - half).reshape(-1, 5)
        side_bits = loc.lane_side(lane1[rows])  # bit 1: no lane to its left; bit 2: none to its right
        want = np.where((over_left.max(1) > GATE_OVER_M) & ~(side_bits & 1).astype(bool), 1,
                        np.where((over_right.max(1) > GATE_OVER_M) & ~(side_bits & 2).astype(bool), -1, 0))
        for r in np.flatnonzero(want != 0):
            j, side = int(rows[r]), int(want[r])
            vid = vids[j]
            try:
                if c.vehicle.getLaneID(vid) != loc.lane_id[lane1[j]]:
                    continue  # SUMO already has it on another lane: the change is under way
                state = int(c.vehicle.getLaneChangeState(vid, side)[0])
            except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
                continue
            blocking = LCA_OVERLAPPING | (LCA_BLOCKED_BY_LEFT_LEADER | LCA_BLOCKED_BY_LEFT_FOLLOWER if side > 0
                                          else LCA_BLOCKED_BY_RIGHT_LEADER | LCA_BLOCKED_BY_RIGHT_FOLLOWER)
            if not state & blocking:
                continue
            over = np.maximum(over_left[r] if side > 0 else over_right[r], 0.0)  # [5] [m]
            back = np.where(over > 0.0, np.maximum(back_left[r] if side > 0 else back_right[r], 0.0), 0.0)  # [5] [m]
            hd = heading.reshape(-1, 5)[r]
            normal = np.stack([-np.sin(hd), np.cos(hd)], -1)  # [5, 2] left of the lane
            fol.xy[slots[j], 1:] -= side * back[:, None] * normal
            # a held frame points along its lane: left yawed towards the gap, its front corner (and SUMO's front
            # bumper, where moveToXY maps the vehicle) reached into the lane beside, onto the vehicle there (session 65)
            if self.along_lane:
                fol.yaw[slots[j], 1:] = np.where(over > 0.0, hd, fol.yaw[slots[j], 1:])
            held[j] = True
        self.stats.lane_changes_held += int(held.sum())
        return held

    def _keep_on_carriageway(self, slots: np.ndarray, located: tuple, fixed: np.ndarray) -> None:
        """Position drive with the safety layer (at decisions): planned boxes that would stick out over the left edge
        of their edge's leftmost lane (into the other direction's lane of a two-way road) or the right edge of its
        rightmost lane (off the road) are moved sideways to the edge, same arc lengths (a box's extent across its lane
        is its width, so a box yawed against its lane can keep a corner over the edge); those moved from over the left
        edge of a two-way road (:meth:`_two_way_lanes`) also point along their lane (session 65). Junction-internal
        lanes are left alone. The policy drifts sideways leaving curves and the roundabout; an oncoming vehicle beside the ego is
        no leader (:class:`~r1sim_sumo.sim.safety_filter.SafetyFilter`), so a drift over the centre line was a head-on
        side-swipe. ``located``: :meth:`LaneLocator.locate` of frames 1..5 of every plan before the lane-permission
        fixes; the plans moved by those (``fixed [n]``) are located again. (Session 67: counting the frames still over a
        junction of a vehicle whose front SUMO has on a normal lane on that lane, as the lane-change gate does, changed
        urban_intersection's events by one over seeds 0-7 and cost motorway_merge's speed at seed 0 0.879 -> 0.859 of
        native's: not kept, docs/simulate/lane_splits_s67.)"""
        if not len(slots):
            return
        fol, loc = self.follower, self.locator
        n = len(slots)
        xy = fol.xy[slots][:, 1:].reshape(-1, 2)  # [n * 5, 2] box centres of frames 1..5
        lane, _dist, half, along = (np.array(a, copy=True) for a in located)
        if fixed.any():
            rows = np.flatnonzero(np.repeat(fixed, 5))
            again = loc.locate(xy[rows], fol.yaw[slots][:, 1:].reshape(-1)[rows])
            lane[rows], half[rows], along[rows] = again[0], again[2], again[3]
        self._inherit_lanes(lane, half, along, xy)
        ok = (lane >= 0) & ~loc.is_internal[np.maximum(lane, 0)]
        if not ok.any():
            return
        side = np.where(ok, loc.lane_side(np.maximum(lane, 0)), 0)  # bit 1: leftmost lane of its edge; bit 2: rightmost
        rows = np.flatnonzero(side > 0)
        if not len(rows):
            return
        lat, heading = loc.lateral_offset(lane[rows], along[rows], xy[rows])  # [m] + = left of the centreline, [rad]
        # the box's width across its lane, not its yaw against it: a box yawed d against its lane can still have a
        # corner up to (L / 2) sin(d) over the edge. Counting the yaw towards the left edge (session 60) cost the
        # eclipse-sumo game/cross 18 of 81 arrivals over seeds 0-2, towards both edges it pushed kerb-crossing boxes into
        # the other direction (8x the roundabout's collision events): not kept (docs/simulate/junction_turns_s60)
        hw = 0.5 * np.repeat(self._size[slots, 1], 5)[rows]  # vehicle half widths [m]
        over_left, over_right = lat + hw - half[rows], -lat + hw - half[rows]
        shift = np.where((side[rows] & 1).astype(bool) & (over_left > 0), -over_left,
                         np.where((side[rows] & 2).astype(bool) & (over_right > 0), over_right, 0.0))
        xy[rows] += shift[:, None] * np.stack([-np.sin(heading), np.cos(heading)], -1)
        # frames moved back from over the centre line of a two-way road also point along their lane (session 65): left
        # yawed, the box's front corner and SUMO's front bumper (where moveToXY maps the vehicle) crossed into the
        # oncoming lane (the roundabout's exits beside the queue waiting to enter; a turn across the centre line into a
        # U-turn). Not at the right edge (it cost game/ramp 45 of 969 arrivals over seeds 0-2) and not at the left edge
        # of one-way roads (motorways, ramps: motorway_merge's mean speed fell on four of five seeds)
        yaw = fol.yaw[slots][:, 1:].reshape(-1).copy()  # [n * 5]
        if self.along_lane:
            yaw[rows] = np.where((shift < 0.0) & self._two_way_lanes()[lane[rows]], heading, yaw[rows])
        shift = np.bincount(rows // 5, weights=np.abs(shift), minlength=n)  # per vehicle
        moved = shift > 0
        if moved.any():
            fol.xy[slots[moved], 1:] = xy.reshape(n, 5, 2)[moved]
            fol.yaw[slots[moved], 1:] = yaw.reshape(n, 5)[moved]
            self.stats.carriageway_fixes += int(moved.sum())

    def _keep_in_lane_split(self, vids: list[str], slots: np.ndarray) -> None:
        """Position drive with the safety layer and ``along_lane`` (at decisions, since session 66): a vehicle SUMO has
        on an internal lane of a junction without conflicts (:meth:`_no_foe_internal`: a lane split, the taper where a
        turn bay opens, a lane added by an on-ramp) keeps its planned boxes inside that lane and the lanes of its
        route's next edge it leads to (:meth:`_way_through_lanes`): each of frames 1..5 whose box (its centre's offset
        from the nearest of those lanes plus half its width) sticks out of it is moved sideways back in and points
        along it (``lane_split_keeps``). SUMO changes lanes on normal lanes only, and on internal lanes the lane-change
        gate and the carriageway rule do not act: the policy drifted across such junctions towards the diverging bay
        lane and into vehicles on the parallel lane, or cut in ahead of them (session 66, urban_intersection's 14 m bay
        tapers: most of that network's collision events). A plan ending more than :data:`OFF_ROUTE_IN_JUNCTION_M`
        from the way takes another of the split's lanes: it is left to :meth:`_hand_over_off_route_turns` (pulled
        onto lane_drop's 8 m taper, where the decelerating lane branches off a full lane to the right, such plans put
        exiting vehicles onto the branch at 40 degrees and into the next lane's traffic).
        Session 67: the way is the branch its route continues from (:meth:`_junction_way`, :meth:`_way_on_route`); a
        vehicle SUMO has on another branch is kept on its route's branch's centreline; and a vehicle still before a
        split whose route takes a branch other than the one SUMO maps it onto is handed to SUMO once its planned
        front is within :data:`SPLIT_HANDOVER_M` of the split (``split_branch``, :meth:`_split_way_ahead`; taken back
        with its body past the split, :meth:`_may_retake`). Keeping such a vehicle on its branch itself swept the lane
        beside with long vehicles on the 14 m tapers (urban_intersection: 23-32 vs 4-5 collision events per 1000
        vehicle-km pooled, docs/simulate/lane_splits_s67)."""
        loc, fol = self.locator, self.follower
        get_lane = self.conn.vehicle.getLaneID
        for vid, slot in zip(vids, slots.tolist(), strict=True):
            try:
                lane = get_lane(vid)
            except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
                continue
            xy = fol.xy[slot, 1:].astype(np.float64)  # [5, 2] box centres of frames 1..5
            if lane.startswith(":"):
                if not self._no_foe_internal(lane):
                    continue
                found = self._junction_way(vid)
                if found is None:
                    continue
                way = np.asarray(found[1], np.int64)  # [w] locator rows
                rerouted = loc.lane_id[way[0]] != lane  # SUMO has it on a branch its route cannot go on: the route's
            else:
                # before a lane split: a vehicle whose route takes a branch SUMO would not map it onto (the
                # branches start on one line; SUMO takes the first) is handed to SUMO's driver, as turns are (a 12 m
                # truck kept on urban_intersection's 14 m bay taper swept the lane beside). Where its route takes the
                # first branch, its plan is left as it is: keeping its frames past the lane end on the branch's
                # centreline put lane_drop's exits onto the 8 m S-curve taper at 40 degrees, and the filter, looking
                # along the main lane, found the queue on the branch too late (19 vs 1 events per 1000 vehicle-km)
                ahead = self._split_way_ahead(vid, lane) if self.junction_turns == "sumo" else None
                if ahead is None or ahead[1]:
                    continue
                _, s_lane = loc._project(xy, np.full(5, ahead[0], np.int64))
                if not (s_lane + 0.5 * self._size[slot, 0] >= loc.length_m[ahead[0]] - SPLIT_HANDOVER_M).any():
                    continue  # its planned front bumpers are not yet within SPLIT_HANDOVER_M of the split
                self._hand_back(vid, "split_branch")
                self.vehicles[vid].handback_edge = lane.rsplit("_", 1)[0]
                try:  # the lanes it needs ahead, as from where it is now (handed over in the split's last metres,
                    # SUMO's driver took the first branch with or without this; 15 m before it, it takes its route's)
                    self.conn.vehicle.updateBestLanes(vid)
                except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
                    pass
                continue
            k = np.repeat(way, 5)  # [w * 5]: every frame against every lane of the way
            d, s = loc._project(np.tile(xy, (len(way), 1)), k)
            d = d.reshape(len(way), 5)
            if float(d[:, -1].min()) > OFF_ROUTE_IN_JUNCTION_M and not rerouted:
                continue  # the plan takes another of the split's lanes: the junction-turn hand-over's (SUMO's way)
            best = d.argmin(0)  # [5] the nearest lane of the way per frame
            pick = best * 5 + np.arange(5)
            lane_k, s_k = k[pick], s[pick]
            lat, heading = loc.lateral_offset(lane_k, s_k, xy)  # [m] + = left, [rad]
            room = np.maximum(loc.half_width_m[lane_k] - 0.5 * self._size[slot, 1], 0.0)  # [m] the centre's leeway
            if rerouted:  # onto its route's branch: along its centreline, as SUMO's drivers take it (with the leeway,
                room = 0.0  # a vehicle went on straight until the branches were apart and was then pulled over at once)
            shift = np.clip(lat, -room, room) - lat  # [5] [m]
            moved = np.abs(shift) > 1e-6
            if not moved.any():
                continue
            fol.xy[slot, 1:] = xy + shift[:, None] * np.stack([-np.sin(heading), np.cos(heading)], -1)
            fol.yaw[slot, 1:] = np.where(moved, heading, fol.yaw[slot, 1:])
            self.stats.lane_split_keeps += 1

    def _split_way_ahead(self, vid: str, lane: str) -> tuple[int, bool, tuple[int, ...]] | None:
        """For a vehicle on normal ``lane`` that leads into a lane split (two or more of its connections to its route's
        next edge run over internal lanes without foes, :meth:`_no_foe_internal`): the locator row of ``lane``, whether
        its route's branch is the split's first (the one SUMO maps a vehicle entering the split onto: the branches
        start on one line and it takes the first of equally near lanes), and the locator rows of that branch's way (the
        internal lane its route continues from, :meth:`_way_on_route`, and the lane of the next edge it leads to);
        None elsewhere (cached)."""
        c = self.conn
        try:
            route, i = c.vehicle.getRoute(vid), int(c.vehicle.getRouteIndex(vid))
        except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
            return None
        if not 0 <= i < len(route) - 2:
            return None
        key = (lane, route[i + 1], route[i + 2])
        if key not in self._split_ahead:
            got = None
            try:
                vias = [lk[4] for lk in c.lane.getLinks(lane)
                        if lk[0].rsplit("_", 1)[0] == route[i + 1] and len(lk) > 4 and lk[4]]
                if len(vias) > 1 and all(self._no_foe_internal(v) for v in vias):
                    way = self._way_through_lanes(vias[0], route[i + 1])
                    way = self._way_on_route(vias[0], route[i + 1], route[i + 2], way) if way else ()
                    row = self.locator.index_of(lane)
                    if way and row >= 0 and self._way_reaches(way, route[i + 1], route[i + 2]):
                        got = (row, self.locator.lane_id[way[0]] == vias[0], way)
            except Exception:  # noqa: BLE001 - unknown lane: nothing kept
                got = None
            self._split_ahead[key] = got
        return self._split_ahead[key]

    def _no_foe_internal(self, lane: str) -> bool:
        """Internal ``lane`` crosses and merges with no other lane of its junction: every one of its foes
        (``lane.getInternalFoes``) starts where it starts, a lane diverging from the same incoming lane (a lane
        split, the taper where a bay opens, a lane added); cached."""
        got = self._no_foe_lane.get(lane)
        if got is None:
            c = self.conn
            try:
                x0, y0 = c.lane.getShape(lane)[0]
                got = all(np.hypot(*np.subtract(c.lane.getShape(f)[0], (x0, y0))) < 0.1
                          for f in c.lane.getInternalFoes(lane))
            except Exception:  # noqa: BLE001 - unknown lane: not kept
                got = False
            self._no_foe_lane[lane] = got
        return got

    def _two_way_lanes(self) -> np.ndarray:
        """``[L]`` bool per locator lane: a lane of the other direction runs beside the left edge of its edge's leftmost
        lane (a two-way road: oncoming traffic beyond the centre line; not a motorway, a ramp or a roundabout's ring).
        Looked for once, on first use, at the middle of each leftmost normal lane: the nearest lane heading the other
        way one lane width to the left, within :data:`TWO_WAY_REACH_M` of that point."""
        if self._two_way is None:
            loc = self.locator
            rows = np.flatnonzero(~loc.is_internal & (loc.lane_side(np.arange(len(loc.lane_id))) & 1).astype(bool))
            out = np.zeros(len(loc.lane_id), bool)
            if len(rows):
                mid = 0.5 * loc.length_m[rows]  # [m] each lane's middle
                p = loc._interpolate(rows, mid)  # [m, 2] [m]
                _, h = loc.lateral_offset(rows, mid, p)  # [m] the lanes' headings there [rad]
                q = p + (2.0 * loc.half_width_m[rows])[:, None] * np.stack([-np.sin(h), np.cos(h)], -1)
                lane, dist, _half, along = loc.locate(q, h + np.pi)
                ok = (lane >= 0) & (dist <= TWO_WAY_REACH_M)
                ok[ok] &= ~loc.is_internal[lane[ok]]
                if ok.any():
                    _, h2 = loc.lateral_offset(lane[ok], along[ok], q[ok])
                    ok[ok] = np.cos(wrap_angle(h2 - h[ok] - np.pi)) > np.cos(np.deg2rad(30.0))
                out[rows[ok]] = True
            self._two_way = out
        return self._two_way

    def _inherit_lanes(self, lane: np.ndarray, half: np.ndarray, along: np.ndarray, xy: np.ndarray) -> None:
        """Frames of a plan (``[n * 5]`` rows, 5 per vehicle) that no lane is near enough to be located on (farther
        than the locator's search radius beside the road) take the lane of the plan's last located frame before them,
        with their arc length and half width on it (in place), so that :meth:`_keep_on_carriageway` moves them back
        too. (Session 59: a plan drifting 1.5 m per 0.1 s sideways had its last frames located on no lane and left
        them beside the road, and the vehicle drove off it.)"""
        lost = np.flatnonzero(lane < 0)
        if not len(lost):
            return
        n5 = lane.reshape(-1, 5)
        for r in lost.tolist():
            v, f = divmod(r, 5)
            before = n5[v, :f][n5[v, :f] >= 0]
            if len(before):
                lane[r] = before[-1]
        got = lost[lane[lost] >= 0]
        if len(got):
            loc = self.locator
            _, along[got] = loc._project(xy[got], lane[got])
            half[got] = loc.half_width_m[lane[got]]

    def _snap_standing_over_centre_line(self, slots: np.ndarray) -> None:
        """Position drive with the safety layer (at decisions): a vehicle standing (< :data:`STILL_SPEED_MPS` per its
        history) whose box sticks more than :data:`OVER_CENTRE_LINE_M` over the left edge of its edge's leftmost lane
        (into the other direction's lane; SUMO's lane and lateral position of it) is snapped onto its lane for this
        plan's moves (``keepRoute`` 1 with the lane's heading, as :meth:`_junction_snaps`). Why:
        :meth:`_keep_on_carriageway` moves the planned frames back, but a standing vehicle makes no progress along them
        and stays where it is, its corridor pointing into the oncoming lane, whose vehicles it waits for and which clip
        its box one after another (session 59: 16 of 25 box events of the roundabout's position drive at seed 0 were
        such head-on pairs at exits, the first of them a 12 m bus that had left the ring 9 degrees off its lane's
        heading; docs/simulate/moved_speed_s59)."""
        col = self._k % N_HISTORY_10HZ
        standing = slots[np.abs(self._hist[slots, col, 3]) < STILL_SPEED_MPS]
        if not len(standing):
            return
        c, loc = self.conn, self.locator
        vid_of = {r.slot: v for v, r in self.vehicles.items() if r.state == "controlled"}
        for s in standing.tolist():
            vid = vid_of.get(s)
            if vid is None:
                continue
            try:
                lane = c.vehicle.getLaneID(vid)
                k = loc.index_of(lane) if lane and not lane.startswith(":") else -1
                if k < 0 or not loc.lane_side(np.array([k]))[0] & 1:
                    continue
                over = c.vehicle.getLateralLanePosition(vid) + 0.5 * (self._size[s, 1] - c.lane.getWidth(lane))
            except Exception:  # noqa: BLE001 - a query failing must not crash the user's loop
                continue
            if over > OVER_CENTRE_LINE_M:
                self.vehicles[vid].snap_plan = self._k  # the plan made at this decision (its plan_step once set)
                self.stats.centre_line_snaps += 1

    def _route_sides(self, controlled: list[str], n_agents: int) -> np.ndarray:
        """``[n_agents]`` int8 for an ``intent`` sampler: +1 / -1 where a controlled vehicle (the first
        ``len(controlled)`` agents) is on a lane that does not lead on along its route and the lanes that do lie to
        its left / right (SUMO's best-lane offset), else 0 (greedy decoding; the context agents are SUMO's). The
        offset is asked of SUMO once per vehicle and lane (cached), and on junction-internal lanes not at all."""
        sides = np.zeros(n_agents, np.int8)
        cache = self._side_cache
        for j, vid in enumerate(controlled):
            try:
                lane = self.conn.vehicle.getLaneID(vid)
            except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
                continue
            if not lane or lane.startswith(":"):
                continue
            key = (vid, lane)
            if key not in cache:
                best = self._best_lane_entry(vid, lane)
                cache[key] = 0 if best is None else int(np.sign(best[0]))
            sides[j] = cache[key]
        if len(cache) > 8 * max(len(self.vehicles), 64):  # forget departed vehicles' lanes now and then
            cache.clear()
        return sides

    def _wrong_lane(self, vid: str, lane: str | None = None) -> bool:
        """``vid``'s lane (``lane``, or the one it is on) does not lead on along its route (SUMO's best lanes ask for a
        lane change).
        The policy does not know the route, so it may queue at a stop line in a lane that turns elsewhere; two such
        vehicles side by side block each other for good. SUMO takes the vehicle over in time to change lanes."""
        best = self._best_lane_entry(vid, lane)
        return best is not None and (best[0] != 0 or not best[1])

    def _best_lane_entry(self, vid: str, lane: str | None = None) -> tuple[int, bool] | None:
        """(offset, allowed) of ``vid``'s lane (``lane``, or the one it is on) in SUMO's best lanes for its route:
        offset = lanes to change to continue (+ = to the left); ``None`` if not listed or a query fails."""
        try:
            lane = self.conn.vehicle.getLaneID(vid) if lane is None else lane
            for lane_id, _len, _occ, offset, allows, _nxt in self.conn.vehicle.getBestLanes(vid):
                if lane_id == lane:
                    return int(offset), bool(allows)
        except Exception:  # noqa: BLE001 - a query failing must not crash the user's loop
            return None
        return None

    def _near_lane_end(self, vid: str, reach_m: float) -> str | None:
        """The normal lane ``vid`` is on when SUMO has it within ``reach_m`` [m] of the lane's end (``None``
        otherwise: farther, on a junction-internal lane, or a query failed)."""
        try:
            lane = self.conn.vehicle.getLaneID(vid)
            if not lane or lane.startswith(":"):
                return None
            left_m = float(self.locator.length_m[self.locator.index_of(lane)]) - float(self.conn.vehicle.getLanePosition(vid))
        except Exception:  # noqa: BLE001 - a query failing must not crash the user's loop
            return None
        return lane if left_m <= reach_m else None

    def _may_retake(self, vid: str, rec: VehicleRecord, speed_mps: float) -> bool:
        """A vehicle handed back at a standstill is taken back once SUMO has it moving at RESUME_SPEED_SHARE of its
        allowed speed; one handed back to change lanes (``wrong_lane``) or to turn (``junction_turn``) once it is on a
        later edge of its route (with ``junction_crossings="sumo"`` and a crossing junction just passed, once its front
        bumper is its length + :data:`CROSSING_CLEAR_M` into that edge); one handed back at a lane split
        (``split_branch``, :meth:`_keep_in_lane_split`) likewise once its whole body is past the split."""
        if rec.reason == "standstill":
            return speed_mps >= RESUME_SPEED_SHARE * self._allowed_speed(vid)
        if rec.reason in ("wrong_lane", "junction_turn", "junction_crossing", "against_lane", "split_branch"):
            try:
                road = self.conn.vehicle.getRoadID(vid)
                route = rec.route
                if not (road in route and rec.handback_edge in route and route.index(road) > route.index(rec.handback_edge)):
                    return False
                if rec.reason == "split_branch":  # its whole body past the split's taper
                    return float(self.conn.vehicle.getLanePosition(vid)) >= self._size[rec.slot, 0] + CROSSING_CLEAR_M
                if (self.junction_crossings == "sumo" and self.drive == "position"
                        and self._edge_ends_in_crossing(route[route.index(road) - 1])):
                    return float(self.conn.vehicle.getLanePosition(vid)) >= self._size[rec.slot, 0] + CROSSING_CLEAR_M
            except Exception:  # noqa: BLE001
                return False
            return True
        return False

    def _crossing_at_end(self, lane: str) -> bool:
        """Normal ``lane``'s end is a junction where a vehicle may have to stop (``junction_crossings``): it has links
        and they are not all open (:meth:`_lane_end_is_open`: a signal, a link without priority, a turn or a link
        that crosses another lane's inside the junction). A lane that just ends (a lane drop) is not one (cached)."""
        if lane not in self._crossing_end:
            k = self.locator.index_of(lane)
            try:
                has_links = bool(self.conn.lane.getLinks(lane))
            except Exception:  # noqa: BLE001 - unknown lane: not a crossing
                has_links = False
            self._crossing_end[lane] = has_links and k >= 0 and not self._lane_end_is_open(k)
        return self._crossing_end[lane]

    def _edge_ends_in_crossing(self, edge: str) -> bool:
        """A lane of ``edge`` ends in a junction where a vehicle may have to stop (:meth:`_crossing_at_end`; cached)."""
        if edge not in self._edge_crossing:
            try:
                n = int(self.conn.edge.getLaneNumber(edge))
            except Exception:  # noqa: BLE001 - unknown edge: not a crossing
                n = 0
            self._edge_crossing[edge] = any(self._crossing_at_end(f"{edge}_{i}") for i in range(n))
        return self._edge_crossing[edge]

    def _sumo_crosses_here(self, vid: str) -> bool:
        """Position drive, ``junction_crossings="sumo"``: SUMO has ``vid`` at a crossing (:meth:`_at_crossing`), where
        SUMO drives it: not taken (or taken back) there."""
        return self.junction_crossings == "sumo" and self.drive == "position" and self._at_crossing(vid)

    def _at_crossing(self, vid: str) -> bool:
        """SUMO has ``vid`` inside a junction or within :func:`crossing_reach_m` of a crossing lane end
        (:meth:`_crossing_at_end`)."""
        try:
            lane = self.conn.vehicle.getLaneID(vid)
        except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
            return False
        if lane.startswith(":"):
            return True
        near = self._near_lane_end(vid, crossing_reach_m(self._allowed_speed(vid)))
        return near is not None and self._crossing_at_end(near)

    def _allowed_speed(self, vid: str) -> float:
        """SUMO's allowed speed of ``vid`` on its lane [m/s] (lane limit x speed factor); inf when unknown."""
        try:
            return float(self.conn.vehicle.getAllowedSpeed(vid))
        except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
            return float("inf")

    def _nothing_ahead(self, vid: str) -> bool:
        """No leader within 15 m and no red / yellow signal within 30 m: a standing vehicle has no reason to wait
        (an undertrained policy may never restart from standing still); SUMO takes it over."""
        try:
            leader = self.conn.vehicle.getLeader(vid, 15.0)
            if leader and leader[0]:
                return False
            for tls in self.conn.vehicle.getNextTLS(vid):
                if tls[2] <= 30.0 and tls[3] in "rRyYuU":
                    return False
        except Exception:  # noqa: BLE001 - a query failing must not crash the user's loop
            return False
        return True

    # ------------------------------------------------------------------ moving (every 0.1 s)

    def _move(self, k: int, states) -> None:
        c, recs = self.conn, self.vehicles
        todo: list[tuple[str, VehicleRecord, bool]] = []  # (id, record, keepRoute-2 move) of vehicles within a plan
        for vid, rec in recs.items():
            if rec.state != "controlled":
                continue
            if rec.pending_target and not rec.free_move:  # its keepRoute-2 move has been applied
                self._retarget(vid, rec)
            free, rec.free_move = rec.free_move, False
            j = k - rec.plan_step + 1
            if rec.plan_step >= 0 and 1 <= j <= 5:
                todo.append((vid, rec, free))
        if not todo:
            return
        slots = np.fromiter((t[1].slot for t in todo), np.int64, len(todo))
        v_allowed, v_floor = (None, None) if self.safety is None else self._allowed_speeds(states, [t[0] for t in todo], slots)
        out = self._follow(slots, v_allowed, v_floor)
        keep = [KEEP_ROUTE_FREE if free else KEEP_ROUTE_FAST for _, _, free in todo]
        if self.safety is not None:
            keep = self._junction_snaps(todo, keep)
        x_fb, y_fb, ang = to_sumo_pose(out.xy[:, 0], out.xy[:, 1], out.yaw, self._size[slots, 0])  # vectorised, [n] each
        move = c.vehicle.moveToXY
        self._moved_since_step = True
        self._moved_speed[slots], self._moved_at[slots] = out.speed, k
        for (vid, rec, _free), xf, yf, a, kr in zip(todo, x_fb.tolist(), y_fb.tolist(), ang.tolist(), keep, strict=True):
            try:  # a snapped move takes its lane's heading (SUMO's "invalid" angle: from the lane)
                move(vid, "", -1, xf, yf, SUMO_INVALID_ANGLE if kr == KEEP_ROUTE_SNAP else a, kr)
            except Exception as exc:  # noqa: BLE001
                LOG.warning("moveToXY of %s failed (%s)", vid, exc)
                self._moved_at[rec.slot] = -2
                self._hand_back(vid, "sumo_error")

    def _junction_snaps(self, todo: list[tuple[str, VehicleRecord, bool]], keep: list[int]) -> list[int]:
        """Position drive with the safety layer: the ``keepRoute`` flags of this step's moves, with vehicles left on no
        lane inside a junction snapped onto their route's lane.

        A plan that cuts a corner inside a junction leaves the vehicle on no lane (``getLaneID`` empty, ``getRoadID``
        a junction's), where SUMO's drivers do not see it and drive into it when it stands (most collisions of the
        position drive on the bundled roundabout, session 31). From then until it is on a normal lane again its moves
        snap onto its route's lane nearest the planned point with the lane's heading (``keepRoute`` 1: the plan's
        progress, SUMO's lane). Measured (``examples/full_horizon_runs.py``, session 31, README): roundabout 83 -> 11
        collision events, 159 -> 276 arrivals (before the carriageway rule); keeping the plan's heading, or moving along
        the internal lane by the plan's distance instead, collided more often."""
        get_lane, get_road = self.conn.vehicle.getLaneID, self.conn.vehicle.getRoadID
        keep = list(keep)
        for i, (vid, rec, free) in enumerate(todo):
            try:
                lane = get_lane(vid)
                in_junction = not lane and get_road(vid).startswith(":")
            except Exception:  # noqa: BLE001 - a query failing must not crash the user's loop
                continue
            if in_junction:
                if not rec.snap_in_junction:
                    self.stats.junction_snaps += 1
                rec.snap_in_junction = True
            elif not lane.startswith(":"):
                rec.snap_in_junction = False
            if (rec.snap_in_junction or rec.snap_plan == rec.plan_step) and not free:
                keep[i] = KEEP_ROUTE_SNAP
        return keep

    def _follow(self, slots: np.ndarray, v_allowed: np.ndarray | None, v_floor: np.ndarray | None = None) -> FollowStep:
        """One 0.1 s step of ``slots`` along their plans (the shared :class:`~r1sim_sumo.rollout.kernel.PlanFollower`),
        no faster than ``v_allowed [n]`` and no slower than ``v_floor [n]`` [m/s] (``None``: the plan as it is)."""
        out = self.follower.follow(slots, STEP_LENGTH_S, v_allowed, v_floor)
        if v_floor is not None:
            self.stats.decel_limited += int((out.speed > out.v_plan + 1e-9).sum())
        self.stats.safety_slowdowns += int(out.slowed.sum())
        return out

    def _allowed_speeds(self, states, vids, slots) -> tuple[np.ndarray, np.ndarray | None]:
        """The most each vehicle may drive over this step [m/s] ``[n]``: a Krauss safe speed behind its leader and
        before its next stop, its type's max speed and acceleration, slowing by at most its emergency deceleration;
        and with ``brake_floor="open-road"`` the least [m/s] ``[n]`` (else ``None``): on the open road (farther than its
        braking distance plus
        :data:`OPEN_ROAD_MARGIN_M` from its end, :meth:`_lane_end_is_open`) its speed less its type's comfortable
        deceleration over the step, where that is allowed, elsewhere 0 (the plan's braking as it is). Session 39
        (docs/simulate/position_s39): the nano's retimed plans braked at up to 16 m/s^2 and the Krauss safe speed of
        a follower assumes its leader brakes comfortably; a floor at junctions too pushed vehicles the policy stopped
        for crossing traffic into the junction.
        A vehicle held below its plan's speed lags behind the plan's timing until the next decision re-plans from
        where it really is (:class:`~r1sim_sumo.rollout.kernel.PlanFollower`). ``vids``: their ids (kept for the
        diagnostics that wrap this method; the state rows come from ``slots``)."""
        rows = self._row_of_slot[slots]  # this step's state row of each (vehicles that left have none: -1)
        v_plan = self.follower.plan_speed(slots, STEP_LENGTH_S)
        known = rows >= 0
        gap, v_lead, lead = self.safety.leader_gap(rows[known], states.x_m, states.y_m, states.yaw_rad, states.length_m,
                                                   states.width_m, states.speed_mps, self.follower.kappa[slots[known]])
        gap = _break_mutual_blocks(rows[known], lead, gap, states)
        lim = self._limits[slots]  # [n, 4]; NaN where its type's limits are unknown: no cap / the filter's defaults
        unknown = np.isnan(lim)
        vmax, acc = (np.where(unknown[:, i], np.inf, lim[:, i]) for i in (0, 1))
        dec = np.where(unknown[:, 2], self.safety.decel_mps2, lim[:, 2])
        edec = np.where(unknown[:, 3], self.safety.emergency_decel_mps2, lim[:, 3])
        v_safe = np.full(len(slots), np.inf)
        # the ego's speed: what the last step moved it at (_speed_as_moved; a snap onto its lane inside a junction
        # shifts its position, so its displacement would read a jump or a sudden stop), else its own last 0.1 s of
        # motion (SUMO's getSpeed of a moved vehicle can lag it)
        col = self._k % N_HISTORY_10HZ
        prev = (col - 1) % N_HISTORY_10HZ
        moved = np.hypot(*(self._hist[slots, col, :2] - self._hist[slots, prev, :2]).T) / STEP_LENGTH_S
        v_now = np.where(self._hist_valid[slots, col] & self._hist_valid[slots, prev], moved, v_plan)
        v_now = np.where(self._moved_at[slots] == self._k - 1, self._moved_speed[slots], v_now)
        v_safe[known] = self.safety.safe_speed(v_now[known], gap, v_lead, dec[known])
        stop = self._stop_m[slots] - self.follower.prog_m[slots]  # [n] metres left to the stop line from the front bumper
        ahead = np.isfinite(stop)
        if ahead.any():
            v_stop = self.safety.safe_speed(v_now[ahead], np.maximum(stop[ahead], 0.0), np.zeros(int(ahead.sum())),
                                            dec[ahead], min_gap_m=STOP_LINE_MARGIN_M)
            v_safe[ahead] = np.minimum(v_safe[ahead], v_stop)
        v_cap = np.minimum(vmax, v_now + acc * STEP_LENGTH_S)  # the vehicle type's max speed and acceleration
        self.stats.speed_limited += int((v_plan > v_cap + 1e-9).sum())
        v_safe = np.minimum(v_safe, v_cap)
        # never above the type's max speed, even when braking is impossible
        allowed = np.minimum(self.safety.allowed(v_now, v_safe, STEP_LENGTH_S, edec), vmax)
        if self.brake_floor == "off":
            return allowed, None
        open_road = self._open_road_m[slots] - self.follower.prog_m[slots]  # [m] left of it from where it is now
        firm = open_road > v_now**2 / (2.0 * dec) + OPEN_ROAD_MARGIN_M
        return allowed, np.minimum(np.where(firm, np.maximum(v_now - dec * STEP_LENGTH_S, 0.0), 0.0), allowed)

    def _retarget(self, vid: str, rec: VehicleRecord) -> None:
        """After a keepRoute-2 move the vehicle's route is its current edge: route it to its destination again."""
        dest, rec.pending_target = rec.pending_target, ""
        try:
            if rec.route[0] != dest:
                self.conn.vehicle.changeTarget(vid, dest)
            rec.route = tuple(self.conn.vehicle.getRoute(vid))
            self.stats.reroutes["changed_target"] += 1
        except Exception:  # noqa: BLE001 - destination unreachable from here: keep the one-edge route
            self.stats.reroutes["dead_end"] += 1
