"""Commands drive: the vehicle that makes room for a merging vehicle is the first one back along the target lane
that can still slow to the merger's speed within its gap (r1sim_sumo.sim.merge_yield), on a scripted SUMO."""

from r1sim_sumo.sim.merge_yield import (
    LCA_BLOCKED_BY_LEFT_FOLLOWER,
    LCA_STRATEGIC,
    LCA_URGENT,
    Merger,
    find_mergers,
    yield_gaps,
)


class _Vehicle:
    """The few ``conn.vehicle`` queries merge_yield makes, answered from a table."""

    def __init__(self, lane, lc, left_followers, follower, length=5.0, min_gap=2.5):
        self.lane, self.lc, self.lf, self.fol = lane, lc, left_followers, follower
        self.length, self.min_gap = length, min_gap

    def getLaneID(self, v):
        return self.lane[v]

    def getLaneChangeState(self, v, d):
        return (self.lc.get((v, d), 0), 0)

    def getLeftFollowers(self, v, blocking_only=False):
        return self.lf.get(v, ())

    def getRightFollowers(self, v, blocking_only=False):
        return ()

    def getFollower(self, v, dist=0.0):
        return self.fol.get(v, ("", -1.0))

    def getLength(self, v):
        return self.length

    def getMinGap(self, v):
        return self.min_gap


class _Conn:
    def __init__(self, vehicle):
        self.vehicle = vehicle


URGENT_LEFT = LCA_STRATEGIC | LCA_URGENT | LCA_BLOCKED_BY_LEFT_FOLLOWER | 2


def _world():
    # merger "m" stands at the end of an acceleration lane; behind it on the main lane: a (10 m back, 20 m/s),
    # b (a's follower, 20 m further), c (b's follower, 30 m further)
    lane = {"m": "acc_0", "a": "main_1", "b": "main_1", "c": "main_1", "s": "main_0"}
    lc = {("m", 1): URGENT_LEFT, ("s", 1): LCA_STRATEGIC | 2}  # s wants left, but neither urgent nor blocked
    return _Vehicle(lane, lc, {"m": (("a", 10.0),)}, {"a": ("b", 20.0), "b": ("c", 30.0)})


def test_only_urgent_strategic_changes_blocked_by_a_follower_are_mergers():
    conn = _Conn(_world())
    assert find_mergers(conn, ["m", "s", "a"]) == [Merger("m", 1, "acc_0")]


def test_the_first_vehicle_able_to_slow_in_time_yields_and_the_ones_too_close_drive_on():
    conn = _Conn(_world())
    speeds = {"m": 0.0, "a": 20.0, "b": 20.0, "c": 20.0}
    got = yield_gaps(conn, [Merger("m", 1, "acc_0")], lambda v: True, speeds.__getitem__, lambda v: 4.5)
    # a needs 20^2 / 9 = 44 m to stop: it passes; b's gap = 10 + 5 + 2.5 + 20 = 37.5 m: too short as well;
    # c's = 37.5 + 7.5 + 30 = 75 m: c makes room
    assert list(got) == ["c"]
    assert abs(got["c"][0] - 75.0) < 1e-9 and got["c"][1] == 0.0
    # slower main line: a itself can stop within 10 m + margin
    speeds.update(a=6.0)
    got = yield_gaps(conn, [Merger("m", 1, "acc_0")], lambda v: True, speeds.__getitem__, lambda v: 4.5)
    assert list(got) == ["a"]


def test_a_vehicle_sumo_drives_makes_room_itself_and_a_merger_that_moved_on_asks_nobody():
    conn = _Conn(_world())
    speeds = {"m": 0.0, "a": 20.0, "b": 10.0, "c": 20.0}
    got = yield_gaps(conn, [Merger("m", 1, "acc_0")], lambda v: v != "b", speeds.__getitem__, lambda v: 4.5)
    assert got == {}  # b (SUMO's) can stop in time: its own lane-change model lets the merger in; c is not asked
    conn.vehicle.lane["m"] = "main_1"
    assert yield_gaps(conn, [Merger("m", 1, "acc_0")], lambda v: True, speeds.__getitem__, lambda v: 4.5) == {}
