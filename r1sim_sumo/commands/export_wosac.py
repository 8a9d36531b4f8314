"""``r1sim export-wosac``: roll out a policy on scenarios and write them in the official WOSAC format.

Writes a bundle per scene (``<id>.scenario.npz`` + ``<id>.rollouts.npz``, :mod:`r1sim_sumo.wosac_export`) and, when the
official package is importable, the ``Scenario`` / ``ScenarioRollouts`` protos beside them; otherwise it prints the
command that writes them from an environment with ``waymo-open-dataset-tf-2-12-0``. Example::

    r1sim export-wosac --data data/generated/default/test --scenes 0,7 --rollouts 32 --out wosac_out
"""

from __future__ import annotations

import argparse

HELP = "Roll out a policy and export scenarios + rollouts to the official Waymo Open Sim Agents protos."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True, help="scenario dataset folder (manifest.json + shards)")
    p.add_argument("--scenes", default="0", help="comma-separated scenario indices [default 0]")
    p.add_argument("--checkpoint", default=None, help="policy checkpoint (default: the shipped one)")
    p.add_argument("--rollouts", type=int, default=32, help="rollouts per scene [default 32, as WOSAC]")
    p.add_argument("--sampler", default="topk:32", help="sampler spec [default topk:32]")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output folder")


def run(args: argparse.Namespace) -> int:
    import torch

    from r1sim_sumo import load_policy
    from r1sim_sumo.evaluate import rollouts_to_sim
    from r1sim_sumo.rollout.engine import rollout
    from r1sim_sumo.rollout.samplers import parse_sampler
    from r1sim_sumo.scenario import ScenarioDataset
    from r1sim_sumo.tokens.batch import collate, tokenize_scenario
    from r1sim_sumo.wosac_export import export_dir, save_bundle

    try:
        idx = [int(s) for s in args.scenes.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"r1sim export-wosac: --scenes '{args.scenes}' is not a comma-separated list of integers") from None
    data = ScenarioDataset(args.data)
    bad = [i for i in idx if not 0 <= i < len(data)]
    if bad:
        raise SystemExit(f"r1sim export-wosac: --scenes {bad} out of range for {args.data} ({len(data)} scenarios)")
    pol = load_policy(args.checkpoint)
    for i in idx:
        sc = data[i]
        scene = tokenize_scenario(sc, pol.vocab)
        r = rollout(pol.model.eval(), pol.vocab, collate([scene]), args.rollouts, parse_sampler(args.sampler),
                    generator=torch.Generator().manual_seed(args.seed * 1_000_003 + i))
        sim = rollouts_to_sim(r.xy_10hz[:, 0], r.yaw_10hz[:, 0], r.valid_10hz()[:, 0], scene.agent_index, sc)
        sid = f"{sc.metadata.get('network', 'scene')}_{i}"
        paths = save_bundle(args.out, sid, sc, sim)
        print(f"{sid}: {paths[0]} + {paths[1].name}")
    try:
        written = export_dir(args.out)
        print(f"wrote {len(written)} proto files to {args.out}")
    except ImportError as exc:
        print(f"bundles written; protos not written: {exc}")
    return 0
