"""The diagnostics' input ablations (scripts/policy_map_ablation): which polylines the policy's map loses or gains."""

import numpy as np

from r1sim_sumo.adapters.sumo_map import read_sumo_map
from r1sim_sumo.resources import network_files


def test_junction_curbs_outline_the_roundabout_and_leave_its_mouths_open(repo_script):
    ablation = repo_script("scripts/policy_map_ablation/sitecustomize.py")
    net = network_files("roundabout")["net"]
    curbs = ablation.junction_curbs(net)
    assert len(curbs) == 12  # 4 junctions x (the island's side + the two outer corners); dead ends give none
    lanes = read_sumo_map(net).polylines
    ends = [lanes.polyline(i)[k] for i in range(lanes.num_polylines) if lanes.kind[i] == 0
            and not str(lanes.lane_id[i]).startswith(":") for k in (0, -1)]
    pts = np.concatenate(curbs)
    gaps = np.linalg.norm(pts[:, None] - np.asarray(ends)[None], axis=-1).min(0)
    near = gaps[np.linalg.norm(np.asarray(ends), axis=1) < 30.0]  # lane ends at the ring (the far ends are dead ends)
    assert near.min() > 1.5  # no curb point in a mouth: every lane that meets the ring keeps a way in or out
    assert near.max() < 4.0  # and the curbs reach the mouths' sides


def test_dropped_road_edges_leave_the_policys_map_only(repo_script, monkeypatch):
    import r1sim_sumo.sim.policy_driver as policy_driver

    seen = []
    monkeypatch.setattr(policy_driver, "PolicyDriver", lambda policy, road_map, *a, **k: seen.append(road_map))
    ablation = repo_script("scripts/policy_map_ablation/sitecustomize.py")
    ablation.drop_road_edges_from_policy_map(["_in#"])
    full = read_sumo_map(network_files("roundabout")["net"]).polylines
    policy_driver.PolicyDriver(None, full)
    kept = seen[0]
    ids = set(kept.lane_id.astype(str))
    assert not any("_in#" in i for i in ids)
    assert {i for i in full.lane_id.astype(str) if "_in#" not in i} == ids  # lanes and the other edges all kept
    assert kept.num_polylines == full.num_polylines - 8


def test_junction_curbs_read_no_signal_in_the_hosts_traffic_light_rows(repo_script, monkeypatch):
    """The host passes one signal row per polyline of its own map; the curbs' rows are added as TL_NONE (a shorter
    array made every policy call of a signalised network fail)."""
    import r1sim_sumo.sim.policy_driver as policy_driver
    from r1sim_sumo.scenario import TL_NONE, TL_RED

    class Driver:
        def __init__(self, policy, road_map, *a, **k):
            self.map, self.seen = road_map, []

        def plan(self, hist, tl=None):
            self.seen.append(tl)
            return "plan"

    monkeypatch.setattr(policy_driver, "PolicyDriver", Driver)
    ablation = repo_script("scripts/policy_map_ablation/sitecustomize.py")
    net = network_files("roundabout")["net"]
    ablation.add_junction_curbs_to_policy_map(net)
    full = read_sumo_map(net).polylines
    driver = policy_driver.PolicyDriver(None, full)
    assert driver.map.num_polylines == full.num_polylines + 12
    tl = np.full(full.num_polylines, TL_RED, np.int8)
    assert driver.plan(None, tl) == "plan"
    got = driver.seen[0]
    assert got.shape == (driver.map.num_polylines,)
    assert (got[: full.num_polylines] == TL_RED).all() and (got[full.num_polylines:] == TL_NONE).all()
    driver.plan(None, None)
    assert driver.seen[1] is None
