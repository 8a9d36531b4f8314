"""Collision events counted the same way for every run (SUMO-native or policy-driven).

Two checks, each counted once per *event* of a vehicle pair (a pair touching again within
:data:`COLLISION_EVENT_GAP_S` is the same event): SUMO's own collision report (``simulation.getCollisions``,
lane based; start SUMO with ``--collision.action warn --collision.mingap-factor 0 --collision.check-junctions``)
and box overlaps (:func:`~r1sim_sumo.geometry.boxes_overlap`, SAT) between any two vehicles, found with a
k-d tree over the box centres. ``either`` counts the union of both (an event seen by both counts once).

Frames: internal (metres, box centres, yaw radians CCW from +x).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from r1sim_sumo.geometry import boxes_overlap
from r1sim_sumo.scenario import DT_S as STEP_LENGTH_S  # [s] one step of the counted simulation

COLLISION_EVENT_GAP_S = 3.0  # [s] a vehicle pair colliding again within this time is the same collision event
EVENTS_LISTED = 20  # collision events a run describes one by one (``describe_onsets``; the counts go on beyond)


class CollisionCount(NamedTuple):
    """New events of one step: SUMO-reported, of them involving a marked (controlled) vehicle, SAT, either."""

    sumo: int
    sumo_marked: int
    sat: int
    sat_marked: int
    either: int


class CollisionCounter:
    """Per-step collision events (see module doc); ``check_sat=False`` uses SUMO's report only."""

    def __init__(self, check_sat: bool = True):
        self.check_sat = bool(check_sat)
        self._k = -1
        self._gap = int(round(COLLISION_EVENT_GAP_S / STEP_LENGTH_S))
        self._seen: dict[str, dict[tuple[str, str], int]] = {"sumo": {}, "sat": {}, "either": {}}
        self.onsets: dict[str, set] = {"sumo": set(), "sat": set()}
        """The vehicle-id pairs (sorted) of the last :meth:`update`'s new events, by check."""

    def _onsets(self, now: set, which: str) -> set:
        seen, k = self._seen[which], self._k
        new = {p for p in now if k - seen.get(p, -(10**9)) > self._gap}
        for p in now:
            seen[p] = k
        if k % 200 == 0:  # forget pairs that have not touched for a while (bounded memory on long runs)
            for p in [p for p, t in seen.items() if k - t > self._gap]:
                del seen[p]
        return new

    def update(self, conn, states, marked=None) -> CollisionCount:
        """Count this step's new events. ``states``: :func:`~r1sim_sumo.adapters.sumo_state.read_vehicle_states`
        of every vehicle now; ``marked``: ids whose events are also counted apart (the controlled ones), a set or a
        callable returning it (called only in a step with a new event: building a set of ~700 ids every 0.1 s cost
        more than the rest of the count)."""
        self._k += 1
        sumo = {tuple(sorted((str(c.collider), str(c.victim)))) for c in conn.simulation.getCollisions()}
        new_sumo = self._onsets(sumo, "sumo")
        sat = self._overlaps(states) if self.check_sat else set()
        new_sat = self._onsets(sat, "sat")
        self.onsets = {"sumo": new_sumo, "sat": new_sat}
        if not (new_sumo or new_sat):
            marked = set()
        elif callable(marked):
            marked = marked()
        marked = marked or set()
        return CollisionCount(sumo=len(new_sumo), sumo_marked=sum(1 for a, b in new_sumo if a in marked or b in marked),
                              sat=len(new_sat), sat_marked=sum(1 for a, b in new_sat if a in marked or b in marked),
                              either=len(self._onsets(sumo | sat, "either")))

    def describe_onsets(self, conn, time_s: float, driver_of=None) -> list[dict]:
        """The last :meth:`update`'s new events, one record each: ``time_s`` [s], ``check`` (``sumo``: SUMO's report,
        ``box``: box overlap; an event both saw is listed under each), the pair ``a`` / ``b`` and, per vehicle, its
        lane then (``a_lane``: SUMO's lane id, ``:``-prefixed inside a junction, empty on none), its speed [m/s]
        and who drove it (``driver_of(id)``: e.g. ``controlled`` / ``handed_back`` / ``sumo``; ``sumo`` when not
        given). Call it only in a step with an event (it asks SUMO about the pair)."""
        out = []
        for check, key in (("sumo", "sumo"), ("box", "sat")):
            for a, b in sorted(self.onsets[key]):
                rec = {"time_s": round(float(time_s), 1), "check": check, "a": a, "b": b}
                for tag, vid in (("a", a), ("b", b)):
                    try:
                        rec[f"{tag}_lane"] = conn.vehicle.getLaneID(vid)
                        rec[f"{tag}_speed_mps"] = round(float(conn.vehicle.getSpeed(vid)), 2)
                    except Exception:  # noqa: BLE001  (a vehicle SUMO removed in this step)
                        rec[f"{tag}_lane"], rec[f"{tag}_speed_mps"] = "", None
                    rec[f"{tag}_driver"] = driver_of(vid) if driver_of is not None else "sumo"
                out.append(rec)
        return out

    def list_new_events(self, events: list, conn, time_s: float, driver_of=None) -> None:
        """Append the last :meth:`update`'s new events (:meth:`describe_onsets`) to a run's ``events`` list while it
        holds fewer than :data:`EVENTS_LISTED`; asks SUMO nothing in a step without a new event."""
        if (self.onsets["sumo"] or self.onsets["sat"]) and len(events) < EVENTS_LISTED:
            events.extend(self.describe_onsets(conn, time_s, driver_of)[: EVENTS_LISTED - len(events)])

    def step_box_onsets(self, states) -> set[tuple[str, str]]:
        """One step of the box-overlap count alone (no SUMO report): the vehicle-id pairs (sorted) whose boxes
        overlap now and had not within :data:`COLLISION_EVENT_GAP_S`, i.e. this step's new ``sat`` events. For
        diagnostics that look at each event; do not mix with :meth:`update` on the same counter."""
        self._k += 1
        return self._onsets(self._overlaps(states), "sat")

    @staticmethod
    def _overlaps(states) -> set:
        n = len(states)
        if n < 2:
            return set()
        from scipy.spatial import cKDTree

        x, y, yaw = states.x_m, states.y_m, states.yaw_rad
        ln, wd = states.length_m, states.width_m
        reach = 0.5 * np.hypot(ln, wd)  # [N] circumscribed radius [m]
        pairs = cKDTree(np.stack([x, y], -1)).query_pairs(2.0 * float(reach.max()), output_type="ndarray")  # [P, 2]
        if not len(pairs):
            return set()
        i, j = pairs[:, 0], pairs[:, 1]
        close = np.hypot(x[i] - x[j], y[i] - y[j]) <= reach[i] + reach[j]
        i, j = i[close], j[close]
        hit = boxes_overlap(x[i], y[i], yaw[i], ln[i], wd[i], x[j], y[j], yaw[j], ln[j], wd[j])
        ids = states.ids
        return {tuple(sorted((str(ids[a]), str(ids[b])))) for a, b in zip(i[hit], j[hit], strict=True)}
