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
