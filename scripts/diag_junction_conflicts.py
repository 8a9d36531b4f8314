#!/usr/bin/env python3
"""Whether the drop-in's collisions inside junctions break SUMO's right of way or happen off SUMO's lanes.

    python scripts/diag_junction_conflicts.py [--network urban_grid] [--drive position] [--end 900] [--seed 0]
        [--checkpoint r1sim-nano] [--sampler greedy] [--list 25]

Runs ``r1sim simulate``'s loop (libsumo, the drop-in's defaults: safety layer ``krauss``, lane-change gate, standstill
hand-off after 5 s) and after every 0.1 s step finds the vehicle pairs whose boxes overlap (the separating-axis test
of the report's ``collisions_boxes``; a pair touching again within 3 s is the same event). For each event with at
least one vehicle on a junction-internal lane it records, per vehicle: who drives it (``controlled``,
``handed_back:<reason>@junction|lane``: handed back inside a junction or on a normal lane, with ``+released`` within 5 s of being let out of a junction deadlock ignoring right of way,
``sumo``), SUMO's lane, the lane it entered the junction from, how far its front bumper (SUMO's position;
a ``moveToXY``-placed vehicle's is where it was placed) is from the centreline of the lane SUMO has it on [m] (SUMO's
own lateral position of such a vehicle reads 0) and whether that approach lane has a link to the
internal lane SUMO has it on (``wrong-lane``: SUMO's lane mapping put it on an internal lane its approach lane does
not lead to: its box crossed from another lane). The pair is then classed:

- ``foes``: both on internal lanes that SUMO's junction model lists as foes (``lane.getInternalFoes``): a right-of-way
  conflict (one vehicle should have waited for the other);
- ``same-lane``: both on the same internal lane (a rear-end or side-swipe in one link);
- ``not-foes``: on internal lanes SUMO does not consider conflicting (links that do not cross): they met because a box
  was off its lane (the lateral offsets say which);
- ``internal+lane``: one inside the junction, one on a normal lane (entering or leaving).

Prints the counts by class and by the pair of drivers, the mean absolute lateral offsets per class, how many events
per class have a vehicle at a turn's waiting place inside the junction (an internal lane reached through another
internal lane: where a left-turner waits for the oncoming stream), and the first ``--list`` events.
"""

from __future__ import annotations

import argparse
from collections import Counter, defaultdict

OFF_LANE_M = 1.0  # [m] a front bumper this far from the centreline of SUMO's lane counts as off its lane


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="urban_grid")
    ap.add_argument("--drive", default="position", choices=("position", "commands", "native"),
                    help="native: SUMO drives every vehicle (the same count on SUMO's own traffic)")
    ap.add_argument("--end", type=float, default=900.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sampler", default="greedy")
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--list", type=int, default=25, help="print the first N events")
    a = ap.parse_args(argv)

    # isort: off
    import r1sim_sumo  # noqa: F401 - first: it sets the OpenMP wait policy before torch loads, as `r1sim simulate`
    import libsumo as conn
    import numpy as np
    import torch
    # isort: on

    from r1sim_sumo._sumo_env import ensure_sumo_home
    from r1sim_sumo.adapters.sumo_state import read_vehicle_states
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim.collision_events import CollisionCounter
    from r1sim_sumo.sim.sumo_controller import STEP_LENGTH_S, SumoController
    from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

    torch.set_num_threads(1)
    ensure_sumo_home()
    conn.start(sumo_command(a.seed, sumocfg=network_files(a.network)["sumocfg"], end_s=a.end + 1.0))
    ctrl = None if a.drive == "native" else SumoController(
        conn, load_policy(a.checkpoint), control="all", sampler=a.sampler, seed=a.seed, safety="krauss", drive=a.drive,
        standstill_handoff_s=5.0)
    foes_of: dict[str, frozenset] = {}
    links_of: dict[str, frozenset] = {}

    def internal_foes(lane: str) -> frozenset:
        if lane not in foes_of:
            try:
                foes_of[lane] = frozenset(conn.lane.getInternalFoes(lane))
            except Exception:  # noqa: BLE001 - not an internal lane
                foes_of[lane] = frozenset()
        return foes_of[lane]

    def vias(lane: str) -> frozenset:
        """Internal lanes reachable from ``lane``'s end (the via lane of each link and its follow-ups)."""
        if lane not in links_of:
            out: set[str] = set()
            todo = [link[4] for link in conn.lane.getLinks(lane) if link[4]]
            while todo:  # an internal lane's link leads on through a second internal lane (``via``, e.g. a left
                via = todo.pop()  # turn's waiting position) or to the next normal lane
                if via in out:
                    continue
                out.add(via)
                todo += [lk[4] or lk[0] for lk in conn.lane.getLinks(via) if (lk[4] or lk[0]).startswith(":")]
            links_of[lane] = frozenset(out)
        return links_of[lane]

    def off_lane_m(vid: str, lane: str) -> float:
        """Distance [m] of ``vid``'s front bumper (SUMO's position; a ``moveToXY``-placed vehicle's is where it was
        placed) from the centreline of the lane SUMO has it on."""
        shape = np.asarray(conn.lane.getShape(lane), np.float64)
        p = np.asarray(conn.vehicle.getPosition(vid), np.float64)
        a0, d = shape[:-1], np.diff(shape, axis=0)
        t = np.clip(((p - a0) * d).sum(1) / np.maximum((d * d).sum(1), 1e-12), 0.0, 1.0)
        return float(np.hypot(*(a0 + t[:, None] * d - p).T).min())

    waiting_lanes: set[str] = set()  # internal lanes reached through another internal lane (a left turn's waiting place)
    for lane in conn.lane.getIDList():
        if lane.startswith(":"):
            waiting_lanes.update(lk[4] for lk in conn.lane.getLinks(lane) if lk[4])

    released: set[str] = set()  # vehicles let out of a junction deadlock (right of way ignored) within the last 5 s
    released_at: dict[str, int] = {}
    came_from: dict[str, str] = {}
    handed_in: dict[str, str] = {}  # SUMO's lane of each vehicle at its latest hand-back
    was_controlled: set[str] = set()

    def driver(vid: str) -> str:
        rec = None if ctrl is None else ctrl.vehicles.get(vid)
        if rec is None:
            return "sumo"
        if rec.state != "handed_back":
            return rec.state
        where = "@junction" if handed_in.get(vid, "").startswith(":") else "@lane"
        return f"handed_back:{rec.reason}{where}" + ("+released" if rec.deadlock_release or vid in released else "")

    counter = CollisionCounter()  # the report's box-overlap events (one per pair within 3 s)
    events = []
    try:
        for k in range(int(round(a.end / STEP_LENGTH_S))):
            conn.simulationStep()
            if ctrl is not None:
                ctrl.step()
            for v, rec in ({} if ctrl is None else ctrl.vehicles).items():
                if rec.deadlock_release:
                    released_at[v] = k
            released = {v for v, k0 in released_at.items() if k - k0 <= 50}
            s = read_vehicle_states(conn)
            lanes = {str(v): conn.vehicle.getLaneID(str(v)) for v in s.ids}
            if ctrl is not None:
                now = {v for v, rec in ctrl.vehicles.items() if rec.state == "controlled"}
                for v in was_controlled - now:
                    if v in lanes:
                        handed_in[v] = lanes[v]
                was_controlled = now
            for v, ln in lanes.items():
                if ln and not ln.startswith(":"):
                    came_from[v] = ln
            row = {str(v): r for r, v in enumerate(s.ids)}
            for pair in sorted(counter.step_box_onsets(s), key=lambda p: (row[p[0]], row[p[1]])):
                i, j = row[pair[0]], row[pair[1]]
                if i > j:
                    i, j, pair = j, i, (pair[1], pair[0])
                la, lb = lanes[pair[0]], lanes[pair[1]]
                if not (la.startswith(":") or lb.startswith(":")):
                    continue
                per = []
                for v, ln in zip(pair, (la, lb), strict=True):
                    lat = off_lane_m(v, ln) if ln else float("nan")
                    src = came_from.get(v, "")
                    wrong = bool(ln.startswith(":") and src and ln not in vias(src))
                    per.append((v, driver(v), ln, src, lat, wrong))
                if la.startswith(":") and lb.startswith(":"):
                    kind = "same-lane" if la == lb else "foes" if (lb in internal_foes(la) or la in internal_foes(lb)) else "not-foes"
                else:
                    kind = "internal+lane"
                d = (np.degrees(s.yaw_rad[j] - s.yaw_rad[i]) + 180.0) % 360.0 - 180.0
                events.append((k * STEP_LENGTH_S, kind, per, abs(float(d))))
    finally:
        settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        conn.close()

    def short(drv: str) -> str:
        return drv.split(":")[0] + ("@junction" if "@junction" in drv else "")

    print(f"{a.network} {a.drive} {a.end:.0f} s seed {a.seed}: {len(events)} box-overlap events with a vehicle inside a "
          f"junction (SUMO internal lane)")
    by_kind = Counter(e[1] for e in events)
    offs: dict[str, list[float]] = defaultdict(list)
    off_lane: Counter = Counter()
    wrong: Counter = Counter()
    for _t, kind, per, _d in events:
        for _v, _drv, ln, _src, lat, _w in per:
            if ln.startswith(":") and lat == lat:
                offs[kind].append(abs(lat))
        off_lane[kind] += any(ln.startswith(":") and abs(lat) > OFF_LANE_M for _v, _drv, ln, _src, lat, _w in per)
        wrong[kind] += any(w for *_x, w in per)
    print(f"  by class: events | with a vehicle > {OFF_LANE_M:g} m off its internal lane's centre | with a vehicle on an "
          "internal lane its approach lane does not lead to | mean |lateral offset| inside [m]")
    for kind, n in by_kind.most_common():
        o = offs[kind]
        print(f"    {kind:14s} {n:5d} | {off_lane[kind]:4d} | {wrong[kind]:4d} | {np.mean(o) if o else float('nan'):.2f}")
    at_wait = Counter(e[1] for e in events if any(p[2] in waiting_lanes for p in e[2]))
    print("  with a vehicle at a turn's waiting place inside the junction (an internal lane reached through another, "
          "where a left-turner waits for the oncoming stream): " + ", ".join(f"{k} {at_wait[k]}" for k in by_kind))
    print(f"  junction deadlocks released by the controller (right of way ignored): {0 if ctrl is None else ctrl.stats.junction_deadlocks}; "
          f"events with such a vehicle (within 5 s of its release): "
          f"{sum(any('+released' in p[1] for p in e[2]) for e in events)}")
    print("  by class and drivers:")
    pairs = Counter((e[1], " + ".join(sorted(short(p[1]) for p in e[2]))) for e in events)
    for (kind, drv), n in sorted(pairs.items(), key=lambda x: (-x[1], x[0])):
        print(f"    {n:5d}  {kind:14s} {drv}")
    reasons = Counter(p[1].split("+")[0] for e in events for p in e[2] if p[1].startswith("handed_back"))
    print("  hand-back reasons (and where: SUMO's lane one step after the hand-back, inside a junction or on a lane) of "
          "the handed-back vehicles in these events: "
          + ", ".join(f"{r.split(':', 1)[1]} {n}" for r, n in reasons.most_common()))
    print("  heading difference [deg] by class: " + "; ".join(
        f"{kind} " + ", ".join(f"{lo}-{lo + 45}: {n}" for lo, n in sorted(Counter(int(min(e[3], 179.9) // 45) * 45
                                                                               for e in events if e[1] == kind).items()))
        for kind in by_kind))
    for t, kind, per, d in events[: a.list]:
        desc = "  x  ".join(f"{v}:{drv} on {ln or '-'} from {src or '-'} lat {lat:.1f}{' WRONG-LANE' if w else ''}"
                            for v, drv, ln, src, lat, w in per)
        print(f"    t={t:6.1f} s  {kind:13s} dpsi {d:5.1f}  {desc}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
