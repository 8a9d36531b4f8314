"""Commands drive: policy-driven vehicles make room for a vehicle that must merge into their lane.

SUMO's lane-change model (LC2013) lets a vehicle that must change lanes to stay on its route (an acceleration lane
ending, a lane that turns elsewhere) ask the vehicle behind it in the target lane to slow down and let it in. A
vehicle whose speed is set over TraCI (``setSpeed``, the commands drive) drives the commanded speed instead: with
speed mode 31 SUMO still keeps it from hitting its own leader, but no longer slows it for a merging neighbour. On
SUMO's game/ramp (session 28) the mergers then stood at the end of the acceleration lane while the policy's main-line
vehicles drove past one after the other, and the queue grew back over the on-ramp and the motorway's off-ramp for the
rest of the run.

This module gives that request back: every 0.5 s, :func:`find_mergers` lists the vehicles SUMO drives (handed back,
in a route merge, not selected) whose lane-change model wants an urgent strategic change and is blocked by a follower
in the target lane; every 0.1 s, :func:`yield_gaps` walks back from each merger along the target lane and picks the
first vehicle that can still slow to the merger's speed within its gap at its type's deceleration (the ones too close
drive on, as they would in SUMO); if the policy drives it, the controller caps its speed by a Krauss safe speed behind
the merger as if the merger were already its leader.

Units: metres, m/s, m/s^2. Gaps are SUMO's (``getLeftFollowers`` / ``getFollower``: from the front of the follower,
net of its minGap, to the back of the vehicle ahead, measured along the lanes).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

# SUMO's lane-change state bits (traci.constants; the same in libsumo)
LCA_STRATEGIC = 8
LCA_URGENT = 256
LCA_BLOCKED_BY_LEFT_FOLLOWER = 1024
LCA_BLOCKED_BY_RIGHT_FOLLOWER = 4096

YIELD_LOOK_BACK_M = 120.0  # [m] how far back along the target lane a vehicle may be asked to make room
YIELD_CHAIN = 4  # at most this many vehicles back along the target lane are looked at per merger
YIELD_MARGIN_M = 2.0  # [m] a vehicle yields when it can slow to the merger's speed within its gap plus this


@dataclass(frozen=True)
class Merger:
    """A vehicle that must change lanes now (``direction`` +1 left, -1 right) and is blocked by a follower there;
    ``lane`` is the lane it was on when found (it no longer merges once it left it)."""

    vid: str
    direction: int
    lane: str


def find_mergers(conn, ids) -> list[Merger]:
    """The vehicles of ``ids`` whose lane-change model (SUMO's own wish, TraCI aside) wants an urgent strategic
    change and is blocked by a follower in the target lane. Two ``getLaneChangeState`` calls per vehicle."""
    v = conn.vehicle
    found = []
    for vid in ids:
        try:
            for d, blocked in ((1, LCA_BLOCKED_BY_LEFT_FOLLOWER), (-1, LCA_BLOCKED_BY_RIGHT_FOLLOWER)):
                s = int(v.getLaneChangeState(vid, d)[0])
                if s & LCA_STRATEGIC and s & LCA_URGENT and s & blocked:
                    found.append(Merger(vid, d, v.getLaneID(vid)))
                    break
        except Exception:  # noqa: BLE001 - a vehicle that just left, or a failing query: not a merger
            continue
    return found


def yield_gaps(conn, mergers: list[Merger], driven: Callable[[str], bool], speed: Callable[[str], float],
               decel: Callable[[str], float]) -> dict[str, tuple[float, float]]:
    """Per policy-driven vehicle that should make room: ``(gap_m, merger_speed_mps)``, the gap [m] from its front to
    the back of the merger along the target lane (net of its minGap) and the merger's speed; the smallest gap where
    several mergers ask the same vehicle.

    :param driven: whether the controller sets this vehicle's speed (the ones to cap).
    :param speed: a vehicle's speed now [m/s]; ``decel``: its comfortable deceleration [m/s^2] (its type's).
    """
    v = conn.vehicle
    out: dict[str, tuple[float, float]] = {}
    for m in mergers:
        try:
            if v.getLaneID(m.vid) != m.lane:
                continue  # it changed lanes (or left): nothing to make room for
            fol = v.getLeftFollowers(m.vid, True) if m.direction > 0 else v.getRightFollowers(m.vid, True)
            if not fol:
                continue
            vm = max(float(speed(m.vid)), 0.0)
            f, gap = fol[0][0], float(fol[0][1])
            for _ in range(YIELD_CHAIN):
                if not f or gap > YIELD_LOOK_BACK_M:
                    break
                vf = max(float(speed(f)), 0.0)
                can = gap >= 0.0 and (vf * vf - vm * vm) / (2.0 * float(decel(f))) <= gap + YIELD_MARGIN_M
                if can:
                    if driven(f) and gap < out.get(f, (float("inf"), 0.0))[0]:
                        out[f] = (gap, vm)
                    break  # the first one able to make room does (SUMO's own vehicles by their lane-change model)
                nxt = v.getFollower(f, YIELD_LOOK_BACK_M - max(gap, 0.0))
                if not nxt or not nxt[0]:
                    break
                gap = gap + float(v.getLength(f)) + float(v.getMinGap(f)) + max(float(nxt[1]), 0.0)
                f = nxt[0]
        except Exception:  # noqa: BLE001 - a failing query must not crash the user's loop
            continue
    return out
