"""CollisionCounter: events of SUMO's report and of box overlaps, and those of marked (controlled) vehicles."""

from types import SimpleNamespace

import numpy as np

from r1sim_sumo.sim.collision_events import CollisionCounter


class _States(SimpleNamespace):
    def __len__(self):
        return len(self.ids)


def states(xs):
    """Cars 5 m x 2 m heading east at x = ``xs`` [m] (box centres, internal frame)."""
    n = len(xs)
    return _States(ids=np.array([f"v{i}" for i in range(n)]), x_m=np.asarray(xs, float), y_m=np.zeros(n),
                   yaw_rad=np.zeros(n), length_m=np.full(n, 5.0), width_m=np.full(n, 2.0))


class Conn:
    def __init__(self):
        self.pairs = []
        self.simulation = SimpleNamespace(getCollisions=lambda: [SimpleNamespace(collider=a, victim=b) for a, b in self.pairs])


def test_marked_ids_are_asked_for_only_when_a_new_event_happens_and_counted():
    conn, cc, asked = Conn(), CollisionCounter(), []

    def marked():
        asked.append(1)
        return {"v1"}

    n = cc.update(conn, states([0.0, 20.0, 40.0]), marked)  # nobody touches
    assert n == (0, 0, 0, 0, 0) and not asked
    n = cc.update(conn, states([0.0, 3.0, 40.0]), marked)  # v0 and v1 overlap: one SAT event with a marked vehicle
    assert (n.sat, n.sat_marked, n.either) == (1, 1, 1) and len(asked) == 1
    n = cc.update(conn, states([0.0, 3.0, 40.0]), marked)  # the same event, still touching: not new, not asked
    assert n.sat == 0 and len(asked) == 1
    conn.pairs = [("v2", "v0")]  # SUMO reports another pair, no marked vehicle in it
    n = cc.update(conn, states([0.0, 3.0, 40.0]), {"v1"})  # a plain set works too
    assert (n.sumo, n.sumo_marked) == (1, 0)


def test_step_box_onsets_gives_each_new_box_overlap_event_once():
    """The box-overlap count alone, as id pairs: a pair touching again within 3 s is the same event."""
    cc = CollisionCounter()
    assert cc.step_box_onsets(states([0.0, 20.0, 40.0])) == set()
    assert cc.step_box_onsets(states([0.0, 3.0, 40.0])) == {("v0", "v1")}
    apart = [cc.step_box_onsets(states([0.0, 20.0, 40.0])) for _ in range(10)]  # 1 s apart
    assert apart == [set()] * 10
    assert cc.step_box_onsets(states([0.0, 3.0, 40.0])) == set()  # touching again within 3 s: the same event
    for _ in range(31):
        cc.step_box_onsets(states([0.0, 20.0, 40.0]))
    assert cc.step_box_onsets(states([0.0, 3.0, 40.0])) == {("v0", "v1")}  # more than 3 s later: a new event


def test_describe_onsets_lists_each_new_event_with_lanes_speeds_and_drivers():
    conn = Conn()
    lanes = {"v0": "main_0", "v1": ":j_0_0", "v2": "ramp_0"}
    conn.vehicle = SimpleNamespace(getLaneID=lambda v: lanes[v], getSpeed=lambda v: {"v0": 12.0, "v1": 3.5, "v2": 0.0}[v])
    cc = CollisionCounter()
    cc.update(conn, states([0.0, 20.0, 40.0]))
    assert cc.describe_onsets(conn, 1.0) == []  # no new event
    conn.pairs = [("v2", "v0")]
    cc.update(conn, states([0.0, 3.0, 40.0]))  # SUMO reports v0-v2, the boxes of v0 and v1 overlap
    recs = cc.describe_onsets(conn, 12.34, lambda v: "controlled" if v == "v1" else "sumo")
    assert [(r["check"], r["a"], r["b"]) for r in recs] == [("sumo", "v0", "v2"), ("box", "v0", "v1")]
    box = recs[1]
    assert box["time_s"] == 12.3 and box["a_lane"] == "main_0" and box["b_lane"] == ":j_0_0"
    assert (box["a_speed_mps"], box["b_speed_mps"]) == (12.0, 3.5)
    assert (box["a_driver"], box["b_driver"]) == ("sumo", "controlled")
    cc.update(conn, states([0.0, 3.0, 40.0]))  # the same events, still touching: nothing new to describe
    assert cc.describe_onsets(conn, 12.4) == []
