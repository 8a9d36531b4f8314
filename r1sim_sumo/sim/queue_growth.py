"""Queues that grow without clearing: the jam measure of the drop-in report (native and policy runs alike).

A *queue* is a chain of lanes, each holding at least one standing vehicle (speed below ``STILL_SPEED_MPS``), joined
along SUMO's lane connections (a lane, its internal junction lanes and the lane they lead to): a queue that spills
back from a junction over the lanes upstream stays one queue. It is named after its head, the lane furthest
downstream (no connection leads on to a lane of the same queue; the alphabetically first when there are several).
Vehicles that are due to depart but that SUMO could not insert form one more queue, ``<insertion>``.

Sampled every :data:`SAMPLE_EVERY_S` of simulated time. A queue *clears* when no queue with its head is found at a
sample. While it has not cleared, it *grows* from its earliest smallest size to each later new largest size, once that
is at least :data:`GROW_MIN_VEHICLES` standing vehicles more; its growth time is the longest such span [s] (a queue
that stops growing and stands is not growing any more: ``stood_over_60s`` sees that one). A red
light's queue grows for the red phase and clears in the green; a jam that grows back to the network entry grows for as
long as the run lasts. ``queues_grown_over_60s`` counts the queues whose growth time passed 60 s, the acceptance
bound of the drop-in issue.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["GROW_MIN_VEHICLES", "INSERTION", "LONG_GROWTH_S", "SAMPLE_EVERY_S", "QueueGrowthTracker"]

SAMPLE_EVERY_S = 1.0  # [s] simulated time between samples
GROW_MIN_VEHICLES = 3  # a queue has grown once it holds this many more standing vehicles than at its smallest
LONG_GROWTH_S = 60.0  # [s] growth time that counts as a queue that did not clear
INSERTION = "<insertion>"  # the queue of vehicles SUMO could not insert yet


@dataclass
class _Episode:
    start_s: float
    min_n: int
    min_at_s: float
    max_n: int = 0  # the largest size since the smallest
    growth_s: float = 0.0
    counted_long: bool = False


class QueueGrowthTracker:
    """Feeds ``longest_queue_growth_s``, ``longest_queue_head`` and ``queues_grown_over_60s`` of a stats object.

    ``update`` is called every simulation step with the step's vehicle ids and speeds [m/s]; it samples every
    :data:`SAMPLE_EVERY_S` and asks SUMO (``vehicle.getLaneID`` of the standing vehicles only, ``lane.getLinks`` once
    per lane) where the standing vehicles are."""

    def __init__(self, still_speed_mps: float, step_length_s: float = 0.1):
        self.still_speed_mps = float(still_speed_mps)
        self.every = max(1, round(SAMPLE_EVERY_S / step_length_s))
        self._n = 0
        self._next: dict[str, tuple[str, ...]] = {}  # lane -> the lanes a vehicle enters next (internal lanes included)
        self._open: dict[str, _Episode] = {}  # queue head -> its episode since it last cleared

    def update(self, stats, conn, ids, speed_mps: np.ndarray, now_s: float, waiting_to_insert: int) -> None:
        self._n += 1
        if self._n % self.every:
            return
        standing = [v for v, sp in zip(ids, np.abs(np.asarray(speed_mps)).tolist(), strict=True) if sp < self.still_speed_mps]
        count: dict[str, int] = {}
        for v in standing:
            try:
                lane = conn.vehicle.getLaneID(v)
            except Exception:  # noqa: BLE001 - a vehicle that just left: not part of any queue
                continue
            if lane:
                count[lane] = count.get(lane, 0) + 1
        sizes = self._queues(conn, count)
        if waiting_to_insert > 0:
            sizes[INSERTION] = int(waiting_to_insert)
        for head in [h for h in self._open if h not in sizes]:
            del self._open[head]  # cleared
        for head, n in sizes.items():
            ep = self._open.get(head)
            if ep is None:
                self._open[head] = _Episode(now_s, n, now_s, n)
                continue
            if n < ep.min_n:
                ep.min_n, ep.min_at_s, ep.max_n = n, now_s, n
            elif n > ep.max_n:
                ep.max_n = n
                if n >= ep.min_n + GROW_MIN_VEHICLES:
                    ep.growth_s = max(ep.growth_s, round(now_s - ep.min_at_s, 1))
            if ep.growth_s > stats.longest_queue_growth_s:
                stats.longest_queue_growth_s = ep.growth_s
                stats.longest_queue_head = head
            if ep.growth_s > LONG_GROWTH_S and not ep.counted_long:
                ep.counted_long = True
                stats.queues_grown_over_60s += 1

    def _successors(self, conn, lane: str) -> tuple[str, ...]:
        nxt = self._next.get(lane)
        if nxt is None:
            out = []
            try:
                for link in conn.lane.getLinks(lane):
                    out.append(str(link[0]))
                    if len(link) > 4 and link[4]:
                        out.append(str(link[4]))  # the internal (junction) lane the connection runs over
            except Exception:  # noqa: BLE001 - an unknown lane: no successors
                pass
            nxt = self._next[lane] = tuple(out)
        return nxt

    def _queues(self, conn, count: dict[str, int]) -> dict[str, int]:
        """``{head lane: standing vehicles}`` of the queues formed by the lanes in ``count``."""
        parent = {lane: lane for lane in count}

        def find(a: str) -> str:
            while parent[a] != a:
                parent[a] = parent[parent[a]]
                a = parent[a]
            return a

        has_next: set[str] = set()
        for lane in count:
            for nxt in self._successors(conn, lane):
                if nxt in count and nxt != lane:
                    has_next.add(lane)
                    ra, rb = find(lane), find(nxt)
                    if ra != rb:
                        parent[ra] = rb
        heads: dict[str, str] = {}
        first: dict[str, str] = {}  # a queue closed in a ring (a roundabout) has no head: its first lane names it
        sizes: dict[str, int] = {}
        for lane in sorted(count):
            r = find(lane)
            sizes[r] = sizes.get(r, 0) + count[lane]
            first.setdefault(r, lane)
            if lane not in has_next and r not in heads:
                heads[r] = lane
        return {heads.get(r, first[r]): n for r, n in sizes.items()}
