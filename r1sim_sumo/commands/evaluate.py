"""``r1sim evaluate``: closed-loop realism evaluation of a checkpoint (and baselines) on a dataset split.

``--workers N`` shards the scene batches over N workers (``--backend process`` on this machine, ``ray`` for a
Ray cluster); every batch is seeded from (seed, batch index), so the report equals a single-process run.
"""

from __future__ import annotations

HELP = "roll out a checkpoint on held-out scenarios and score realism (RMM, collisions, offroad...)"


def add_arguments(p) -> None:
    p.add_argument("--checkpoint", default=None, help="checkpoint name or folder (default: the shipped r1sim-nano)")
    p.add_argument("--data", required=True, help="dataset folder (manifest.json + shards), e.g. data/generated/default/test")
    p.add_argument("--sampler", nargs="+", default=["topk:32"], help="one or more: greedy, topk:K, entropy:KMIN,KMAX, entropy-norm:KMIN,KMAX")
    p.add_argument("--rollouts", type=int, default=32, help="rollouts per scenario")
    p.add_argument("--max-scenarios", type=int, default=None, help="evaluate only the first N scenarios (evenly spaced)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="sampling seeds; several give mean ± std per sampler")
    p.add_argument("--batch-scenes", type=int, default=2, help="scenes rolled out together")
    p.add_argument("--no-baselines", action="store_true", help="skip log replay and constant velocity")
    p.add_argument("--sumo-again", choices=["seed", "redraw"], default=None,
                   help="also the 'SUMO again' baseline: SUMO rerun from each scene's saved state with another seed "
                        "(redraw: and new desired-speed factors); needs data generated with --save-states")
    p.add_argument("--metric", choices=["wosac", "legacy"], default="wosac",
                   help="realism computation: wosac (the official one, default) or legacy (before issue 16, for old figures)")
    p.add_argument("--decoding", choices=["central", "tokens"], default="central",
                   help="10 Hz states between the rollouts' token boundaries: central (default; each token's path "
                        "retimed from the mean of the previous and current token speeds) or tokens (the token's own frames)")
    p.add_argument("--out", default="runs/evaluate", help="output folder for report.json / report.md / plots")
    p.add_argument("--threads", type=int, default=2, help="torch threads (split between workers with --backend process)")
    from r1sim_sumo.workers import add_pool_arguments

    add_pool_arguments(p, default_workers=1, what="evaluation batches")


def _subset(ds, n):
    import numpy as np

    if n is None or n >= len(ds):
        return [ds[i] for i in range(len(ds))]
    idx = np.linspace(0, len(ds) - 1, n).round().astype(int)
    return [ds[int(i)] for i in idx]


def run(args) -> int:
    import sys

    import numpy as np
    import torch

    import r1sim_sumo
    from r1sim_sumo.evaluate import evaluate_baselines, evaluate_policy, rollouts_to_sim, write_report
    from r1sim_sumo.rollout.engine import rollout
    from r1sim_sumo.rollout.samplers import parse_sampler
    from r1sim_sumo.scenario import ScenarioDataset, ScenarioError
    from r1sim_sumo.tokens.batch import collate, tokenize_scenario

    torch.set_num_threads(args.threads)
    try:
        samplers = [parse_sampler(s) for s in args.sampler]
        ds = ScenarioDataset(args.data)
        policy = r1sim_sumo.load_policy(args.checkpoint)
    except (ValueError, ScenarioError, FileNotFoundError) as exc:
        print(f"r1sim evaluate: {exc}", file=sys.stderr)
        return 2
    scenarios = _subset(ds, args.max_scenarios)
    from r1sim_sumo.workers import TaskFailedError, pool_from_args

    worker_threads = max(1, args.threads // args.workers) if (args.backend or "") != "ray" else None
    results = {}
    try:
        with pool_from_args(args, threads_per_worker=worker_threads) as pool:
            for s in samplers:
                results[s.spec] = [evaluate_policy(policy, scenarios, s, args.rollouts, seed, args.batch_scenes, pool=pool,
                                                   worker_threads=worker_threads, metric=args.metric, decoding=args.decoding)
                                  for seed in args.seeds]
            if not args.no_baselines:
                base = evaluate_baselines(scenarios, args.rollouts, pool=pool, sumo_again=args.sumo_again or False,
                                          state_root=ds.root if args.sumo_again else None, metric=args.metric)
                results.update({v.name: v for v in base.values()})
            pool_stats = pool.stats.to_dict()
    except (TaskFailedError, ValueError, ImportError) as exc:
        print(f"r1sim evaluate: {exc}", file=sys.stderr)
        return 1
    # example scene: the first scenario with its rollouts under the first sampler
    sc = scenarios[0]
    scene = tokenize_scenario(sc, policy.vocab)
    r = rollout(policy.model, policy.vocab, collate([scene]), args.rollouts, samplers[0], generator=torch.Generator().manual_seed(args.seeds[0]),
                decoding=args.decoding)
    sim = rollouts_to_sim(r.xy_10hz[:, 0], r.yaw_10hz[:, 0], r.valid_10hz()[:, 0], scene.agent_index, sc)
    xy = np.stack([sim.x_m, sim.y_m], -1)
    xy[~sim.valid] = np.nan
    meta = {"data": args.data, "checkpoint": args.checkpoint or "r1sim-nano (shipped)", "rollouts": args.rollouts, "seed": args.seeds,
            "samplers": [s.spec for s in samplers], "metric": args.metric, "decoding": args.decoding, "num_scenarios": len(scenarios), "pool": pool_stats,
            "wall_s": {k: sum(r.wall_s for r in (v if isinstance(v, list) else [v])) for k, v in results.items()}}
    out = write_report(args.out, results, meta, example=(sc, xy))
    print((out / "report.md").read_text())
    print(f"[evaluate] wrote {out / 'report.json'}")
    return 0
