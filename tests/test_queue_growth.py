"""The jam measure of the drop-in report: a queue that spills back over lanes is one queue; it grows until it
clears; a red-light queue that clears within a minute is not a queue that grew for over 60 s."""

from types import SimpleNamespace

import numpy as np

from r1sim_sumo.sim.queue_growth import INSERTION, QueueGrowthTracker
from r1sim_sumo.sim.sumo_controller import ControllerStats

# a corridor a_0 -> (junction :j_0_0) -> b_0 -> c_0; queues form at the end of c_0 and spill back
LINKS = {"a_0": [("b_0", True, True, "M", ":j_0_0")], ":j_0_0": [("b_0", True, True, "M", "")],
         "b_0": [("c_0", True, True, "M", ":k_0_0")], ":k_0_0": [("c_0", True, True, "M", "")], "c_0": []}


class FakeConn:
    def __init__(self):
        self.where: dict[str, str] = {}
        self.vehicle = SimpleNamespace(getLaneID=lambda v: self.where[v])
        self.lane = SimpleNamespace(getLinks=lambda lane: LINKS[lane])


def run(tracker, stats, conn, plan, waiting=lambda t: 0):
    """``plan(t)`` -> {vehicle: lane} of the standing vehicles at second t (each second = 10 steps of 0.1 s)."""
    for t in range(len_s := 400):
        standing = plan(t)
        conn.where = dict(standing)
        moving = ["m1", "m2"]  # vehicles driving: never part of a queue
        ids = list(standing) + moving
        speed = np.array([0.0] * len(standing) + [12.0] * len(moving))
        for k in range(10):
            tracker.update(stats, conn, ids, speed, t + 0.1 * (k + 1), waiting(t))
    return len_s


def test_a_spillback_over_three_lanes_is_one_queue_growing_until_it_clears():
    stats, conn = ControllerStats(), FakeConn()
    tr = QueueGrowthTracker(0.3)

    def plan(t):  # one more standing vehicle every 4 s from t=10 to t=130 (30 vehicles: c_0 holds 12, b_0 12, a_0 6)
        if not 10 <= t < 200:
            return {}
        n = min((t - 10) // 4 + 1, 30)
        lanes = ["c_0"] * 12 + ["b_0"] * 12 + ["a_0"] * 6
        return {f"v{i}": lanes[i] for i in range(n)}

    run(tr, stats, conn, plan)
    assert stats.longest_queue_head == "c_0"  # the head, not a lane upstream: the three lanes are one queue
    assert 110.0 <= stats.longest_queue_growth_s <= 125.0  # from 1 vehicle at ~10 s to 30 at ~126 s
    assert stats.queues_grown_over_60s == 1


def test_red_light_queues_that_clear_each_cycle_do_not_count():
    stats, conn = ControllerStats(), FakeConn()
    tr = QueueGrowthTracker(0.3)

    def plan(t):  # 40 s red: a vehicle joins every 3 s; 20 s green: all leave
        phase = t % 60
        if phase >= 40:
            return {}
        return {f"v{t // 60}_{i}": "c_0" for i in range(phase // 3 + 1)}

    run(tr, stats, conn, plan)
    assert 35.0 <= stats.longest_queue_growth_s < 60.0
    assert stats.queues_grown_over_60s == 0


def test_a_growing_insertion_backlog_is_a_queue():
    stats, conn = ControllerStats(), FakeConn()
    tr = QueueGrowthTracker(0.3)
    run(tr, stats, conn, lambda t: {}, waiting=lambda t: 1 + t // 20)  # one more vehicle waits every 20 s, never clears
    assert stats.longest_queue_head == INSERTION
    assert stats.longest_queue_growth_s > 300.0
    assert stats.queues_grown_over_60s == 1


def test_a_steady_queue_that_does_not_grow_is_not_counted():
    stats, conn = ControllerStats(), FakeConn()
    tr = QueueGrowthTracker(0.3)
    run(tr, stats, conn, lambda t: {f"v{i}": "c_0" for i in range(5 + (t % 3))})  # 5-7 vehicles all run long
    assert stats.longest_queue_growth_s == 0.0
    assert stats.queues_grown_over_60s == 0
