"""The queues of a drop-in run that grow without clearing for longer than a bound: each such episode's standing vehicles
per lane, every second from its start, so that one sees which lane holds the queue up (a head that never moves while
the lane beside discharges, a spill-back to the entry).

    python scripts/diag_queue_episode.py --scenario urban_intersection --drive position --seed 0 --end 900 --over 60

The queues are the report's own (``r1sim_sumo/sim/queue_growth.py``, sampled every 1 s); an episode is printed once,
when its growth passes ``--over`` [s]. Scenarios, drives and the controller's defaults as in
``scripts/diag_following_headway.py``. Then ``scripts/diag_pair_trace.py`` or a look at the lane at a chosen time
(``libsumo.lane.getLastStepVehicleIDs``) names the vehicle at the head.
"""

from __future__ import annotations

import sys

from diag_following_headway import drop_in_parser, start_run

from r1sim_sumo.sim import queue_growth


def main(argv=None) -> int:
    ap = drop_in_parser(__doc__.splitlines()[0])
    ap.add_argument("--over", type=float, default=queue_growth.LONG_GROWTH_S, help="growth [s] from which to print")
    a = ap.parse_args(argv)
    seen: dict[str, list[tuple[float, int, dict[str, int]]]] = {}
    printed: set[tuple[str, float]] = set()
    tracker = queue_growth.QueueGrowthTracker
    queues, update = tracker._queues, tracker.update

    def record(self, conn, count):  # the tracker's own grouping, with the lanes' counts kept per head
        sizes = queues(self, conn, count)
        for head, n in sizes.items():
            seen.setdefault(head, []).append((self._n / self.every * queue_growth.SAMPLE_EVERY_S, n, dict(count)))
        return sizes

    def report(self, stats, conn, ids, speed_mps, now_s, waiting_to_insert):
        update(self, stats, conn, ids, speed_mps, now_s, waiting_to_insert)
        for head, ep in self._open.items():
            if ep.growth_s > a.over and (head, ep.start_s) not in printed:
                printed.add((head, ep.start_s))
                print(f"queue {head}: from {ep.start_s:.0f} s, smallest {ep.min_n} at {ep.min_at_s:.0f} s, grown for "
                      f"{ep.growth_s:.0f} s at {now_s:.0f} s")
                road = head.rsplit("_", 1)[0].split("_")[0]
                for t, n, count in seen.get(head, []):
                    if t >= ep.start_s - 1:
                        lanes = " ".join(f"{lane}:{c}" for lane, c in sorted(count.items()) if lane.startswith(road))
                        print(f"  {t:6.0f} s  {n:3d} standing   {lanes}")

    tracker._queues, tracker.update = record, report
    libsumo, ctrl = start_run(a.scenario, a.drive, a.end, a.seed, a.checkpoint, sampler=a.sampler)
    if ctrl is None:
        print("the native run has no controller and no queue tracker here: use --drive commands or position")
        libsumo.close()
        return 1
    try:
        for _ in range(int(round(a.end * 10))):
            libsumo.simulationStep()
            ctrl.step()
    finally:
        ctrl.close()
    if not printed:
        print(f"no queue grew for more than {a.over:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
