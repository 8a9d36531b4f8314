"""Golden fixtures of the realism metric from the official WOSAC code (issue 16).

Two stages, in two environments (the official package pins TensorFlow 2.13 / numpy 1.23 and is no project dependency):

1. ``bundles`` (project environment, torch): picks one scene per network from a dataset (a straight motorway with a
   lane drop, a merge, a signalised junction, a roundabout), keeps the ``--max-agents`` agents nearest the scene's
   centre, adds one agent that enters the log after the current step (a copy of a kept agent's track shifted 6 m
   sideways, valid from step 40: never simulated), rolls out the shipped policy ``--rollouts`` times and writes the
   bundles (:mod:`r1sim_sumo.wosac_export`) into ``--out``::

       nice -n 19 python scripts/wosac_golden.py bundles --data DATA --out tests/fixtures/wosac_golden

2. ``official`` (a venv with ``waymo-open-dataset-tf-2-12-0==1.6.7`` and shapely; r1sim_sumo from the repository via
   PYTHONPATH): converts every bundle to the official protos, validates them with ``submission_specs``, runs
   ``metrics.compute_scenario_metrics_for_bundle`` with the 2024 and 2025 configs and writes ``<id>.official.json``
   (per-feature likelihoods, meta-metrics, rates, and what the scene contains: collisions, offroad excursions, late
   and leaving agents) beside the bundles::

       PYTHONPATH=. nice -n 19 /work/wosac_venv/bin/python scripts/wosac_golden.py official --bundles tests/fixtures/wosac_golden

``tests/test_wosac_golden.py`` recomputes our metric on the bundles and compares it with these values.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

NETWORKS = ("lane_drop", "motorway_merge", "urban_intersection", "roundabout")
LATE_FROM_STEP = 40
FEATURES = ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration", "distance_to_nearest_object",
            "collision_indication", "time_to_collision", "distance_to_road_edge", "offroad_indication",
            "traffic_light_violation")


def _crop_with_late_agent(sc, max_agents: int):
    """The ``max_agents`` agents nearest the median position at the current step, plus a late-entering copy."""
    from r1sim_sumo.scenario import AgentTracks, Scenario

    a, ci = sc.agents, sc.current_index
    live = np.flatnonzero(a.valid[:, ci])
    c = np.median(np.stack([a.x_m[live, ci], a.y_m[live, ci]], 1), 0)
    d = np.hypot(a.x_m[live, ci] - c[0], a.y_m[live, ci] - c[1])
    keep = np.sort(live[np.argsort(d)[:max_agents]])
    sub = a.select(keep)
    src = int(np.argmax(sub.valid.sum(1)))  # the longest track is copied
    late = sub.select([src])
    late.ids = np.array([f"{late.ids[0]}_late"])
    off = 6.0
    nx, ny = -np.sin(late.yaw_rad[0]), np.cos(late.yaw_rad[0])
    late.x_m = (late.x_m + off * nx).astype(np.float32)
    late.y_m = (late.y_m + off * ny).astype(np.float32)
    late.valid[0, :LATE_FROM_STEP] = False
    for f in AgentTracks.PER_STEP:
        getattr(late, f)[0, :LATE_FROM_STEP] = 0.0
    merged = AgentTracks(**{f: np.concatenate([getattr(sub, f), getattr(late, f)]) for f in AgentTracks.FIELDS})
    return Scenario(merged, sc.map, dict(sc.metadata), sc.current_index, sc.dt_s).validate()


def make_bundles(args) -> int:
    import torch

    from r1sim_sumo import load_policy
    from r1sim_sumo.evaluate import rollouts_to_sim
    from r1sim_sumo.metrics.types import SimTrajectories
    from r1sim_sumo.rollout.engine import rollout
    from r1sim_sumo.rollout.samplers import parse_sampler
    from r1sim_sumo.scenario import ScenarioDataset
    from r1sim_sumo.tokens.batch import collate, tokenize_scenario
    from r1sim_sumo.wosac_export import save_bundle

    torch.set_num_threads(2)
    data = ScenarioDataset(args.data)
    pol = load_policy(args.checkpoint)
    first = {}
    for i in range(len(data)):
        net = data[i].metadata.get("network")
        if net in NETWORKS and net not in first:
            first[net] = i
    missing = [n for n in NETWORKS if n not in first]
    if missing:
        raise SystemExit(f"{args.data}: no scene of networks {missing}; generate them with `r1sim generate sumo`")
    for net in NETWORKS:
        sc = _crop_with_late_agent(data[first[net]], args.max_agents)
        scene = tokenize_scenario(sc, pol.vocab)
        r = rollout(pol.model.eval(), pol.vocab, collate([scene]), args.rollouts, parse_sampler(args.sampler),
                    generator=torch.Generator().manual_seed(args.seed))
        sim = rollouts_to_sim(r.xy_10hz[:, 0], r.yaw_10hz[:, 0], r.valid_10hz()[:, 0], scene.agent_index, sc)
        sim = SimTrajectories(*(np.asarray(getattr(sim, f), np.float32) for f in ("x_m", "y_m", "yaw_rad")), sim.valid)
        sc_path, ro_path = save_bundle(args.out, net, sc, sim)
        print(f"{net}: scene {first[net]} of {args.data}, {sc.agents.num_agents} agents -> {sc_path.name}, {ro_path.name}")
    return 0


def _official_metrics(scenario, sim, sid: str) -> dict:
    """Official likelihoods / meta-metrics (2024 and 2025 configs) of one bundle."""
    from google.protobuf import text_format
    from waymo_open_dataset.protos import sim_agents_metrics_pb2
    from waymo_open_dataset.utils.sim_agents import submission_specs
    from waymo_open_dataset.wdl_limited.sim_agents_metrics import metric_features, metrics

    from r1sim_sumo.wosac_export import rollouts_to_proto, scenario_to_proto

    sp, rp = scenario_to_proto(scenario, sid), rollouts_to_proto(scenario, sim, sid)
    submission_specs.validate_scenario_rollouts(rp, sp)
    cfg_dir = Path(metrics.__file__).parent
    out = {}
    log_f, sim_f = metric_features.compute_scenario_rollouts_features(sp, rp, submission_specs.ChallengeType.SIM_AGENTS)
    for year, name in (("2024", "challenge_2024_config.textproto"), ("2025", "challenge_2025_sim_agents_config.textproto")):
        cfg = text_format.Parse((cfg_dir / name).read_text(), sim_agents_metrics_pb2.SimAgentMetricsConfig())
        m = metrics.compute_scenario_metrics_for_features_bundle(cfg, sid, log_f, sim_f)
        out[f"metametric_{year}"] = float(m.metametric)
        if year == "2024":
            out["likelihoods"] = {f: float(getattr(m, f"{f}_likelihood")) for f in FEATURES}
            out["simulated_collision_rate"] = float(m.simulated_collision_rate)
            out["simulated_offroad_rate"] = float(m.simulated_offroad_rate)
            out["simulated_traffic_light_violation_rate"] = float(m.simulated_traffic_light_violation_rate)
            out["average_displacement_error"] = float(m.average_displacement_error)
            out["min_average_displacement_error"] = float(m.min_average_displacement_error)
    # what the scene holds (official features): collisions and offroad in the rollouts, late / leaving agents
    coll = np.asarray(sim_f.collision_per_step).any(-1)  # [R, A]
    off = np.asarray(sim_f.offroad_per_step).any(-1)
    a, ci = scenario.agents, scenario.current_index
    out["contents"] = {
        "rollouts": int(sim.num_rollouts), "sim_agents": int(a.valid[:, ci].sum()),
        "rollout_agent_pairs_with_collision": int(coll.sum()), "rollout_agent_pairs_offroad": int(off.sum()),
        "late_entering_agents": int((~a.valid[:, ci] & a.valid[:, ci + 1:].any(1)).sum()),
        "agents_leaving_in_log": int((a.valid[:, ci] & ~a.valid[:, -1]).sum()),
        "has_signals": bool(np.isin(np.asarray(scenario.map.tl_state), (1, 2, 3)).any()),
    }
    return out


def official(args) -> int:
    from r1sim_sumo.metrics.realism import compute_realism
    from r1sim_sumo.wosac_export import load_bundle

    files = sorted(Path(args.bundles).glob("*.scenario.npz"))
    if not files:
        raise SystemExit(f"{args.bundles}: no bundles; run the `bundles` stage first")
    import waymo_open_dataset

    version = getattr(waymo_open_dataset, "__version__", "1.6.7")
    for f in files:
        sid, sc, sim = load_bundle(f)
        res = _official_metrics(sc, sim, sid)
        ours = compute_realism(sc, sim)
        res["generated_by"] = {"script": "scripts/wosac_golden.py official", "package": f"waymo-open-dataset-tf-2-12-0 {version}"}
        p = f.with_name(f"{sid}.official.json")
        p.write_text(json.dumps(res, indent=1, sort_keys=True) + "\n")
        diffs = {k: round(ours.likelihoods.get(k, float("nan")) - v, 5) for k, v in res["likelihoods"].items()}
        print(f"{sid}: official metametric 2024 {res['metametric_2024']:.4f} ours {ours.rmm:.4f}; ours - official {diffs}")
        print(f"  contents {res['contents']}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="stage", required=True)
    b = sub.add_parser("bundles", help="roll out and write bundles (project environment)")
    b.add_argument("--data", required=True)
    b.add_argument("--out", default="tests/fixtures/wosac_golden")
    b.add_argument("--checkpoint", default=None)
    b.add_argument("--rollouts", type=int, default=32)
    b.add_argument("--max-agents", type=int, default=16)
    b.add_argument("--sampler", default="topk:32")
    b.add_argument("--seed", type=int, default=0)
    o = sub.add_parser("official", help="official metric on the bundles (WOSAC venv)")
    o.add_argument("--bundles", default="tests/fixtures/wosac_golden")
    args = ap.parse_args(argv)
    return make_bundles(args) if args.stage == "bundles" else official(args)


if __name__ == "__main__":
    sys.exit(main())
