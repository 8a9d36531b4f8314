#!/usr/bin/env python3
"""GRPO checkpoint vs the pretrained one on held-out SUMO test scenes (8 scenes, 16 rollouts, entropy:16,80 or ``--sampler``, 5 seeds).

``--seeds`` / ``--num-scenes`` give replicates: other rollout seeds on the same scenes, or more scenes (the first 8 are
always the default's).

Needs the default dataset (``r1sim dataset build --out data/generated/default``).
``--data DIR`` takes the scenes from another split (e.g. ``data/generated/default/val`` to choose among checkpoints
without looking at the test split); ``--reuse-pretrained FILE.json`` takes the pretrained side from an earlier output
of the same data, scenes, seeds and metric instead of rolling it out again (samplers it lacks are rolled out).

Run: ``python scripts/eval_grpo_vs_pretrained.py [--pretrained DIR] [--grpo DIR] [--metric wosac|legacy] [--out FILE.json]``
(``--grpo`` default: the shipped ``r1sim-grpo``; a run's export, e.g. ``runs/grpo_b/final``, compares that fine-tune
with its own start given as ``--pretrained``).

The shipped ``r1sim-grpo`` (session 13) was fine-tuned from today's shipped ``r1sim-nano``, so the comparison of
its card (``docs/eval_grpo_g75_vs_nano.json``) is the default ``--pretrained`` with
``--grpo r1sim-grpo --sampler entropy:16,80 topk:5``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.evaluate import evaluate_policy, summarize_runs
from r1sim_sumo.scenario import ScenarioDataset

SAMPLER = "entropy:16,80"
DATA = "data/generated/default/test"
OLD_DEFAULTS = {"data": DATA, "seeds": list(range(5))}  # what outputs without these fields were run with
KEYS = ["realism/rmm", "realism/collision_rate", "realism/offroad_rate"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pretrained", default=None, help="pretrained checkpoint folder (default: the shipped r1sim-nano)")
    ap.add_argument("--grpo", default="r1sim-grpo", help="GRPO checkpoint folder or bundled name (default: r1sim-grpo)")
    ap.add_argument("--metric", choices=["wosac", "legacy"], default="wosac", help="realism computation")
    ap.add_argument("--out", default="eval_grpo_vs_pretrained.json")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sampler", nargs="+", default=[SAMPLER],
                    help=f"samplers to compare under (default {SAMPLER}, the one GRPO trains with; e.g. also topk:5, the model card's)")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(5)),
                    help="rollout seeds (default 0-4; other seeds are an independent replicate on the same scenes)")
    ap.add_argument("--num-scenes", type=int, default=8,
                    help="held-out SUMO scenes (default 8: the first 8 of the fixed draw; more add scenes after them)")
    ap.add_argument("--data", default=DATA, help=f"split the scenes are drawn from (default {DATA}, the held-out test split)")
    ap.add_argument("--reuse-pretrained", default=None, metavar="FILE.json",
                    help="an earlier output of this script whose pretrained results are taken instead of new rollouts "
                         "(it must match --pretrained, --data, --seeds, --metric and the scenes; samplers it lacks are "
                         "rolled out)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    ds = ScenarioDataset(args.data)
    idx = np.random.default_rng(1).choice(len(ds), 80, replace=False)  # the default's draw, kept as the prefix
    if args.num_scenes > 8:  # then the rest of the split in a fixed order
        rest = np.setdiff1d(np.arange(len(ds)), idx)
        idx = np.concatenate([idx, np.random.default_rng(2).permutation(rest)])
    scenes = []
    for i in idx:
        s = ds[int(i)]
        if s.metadata.get("source") == "sumo":
            scenes.append(s)
            if len(scenes) == args.num_scenes:
                break
    out = {}
    scene_keys = [str(s.metadata) for s in scenes]
    pre_name = f"pretrained ({args.pretrained or 'r1sim-nano'})"
    reused = reused_pretrained(args, pre_name, scene_keys) if args.reuse_pretrained else {}
    for name, ck in [(pre_name, args.pretrained), (args.grpo, args.grpo)]:
        pol = None
        for sampler in args.sampler:
            if name == pre_name and f"{name} / {sampler}" in reused:
                out[f"{name} / {sampler}"] = s = reused[f"{name} / {sampler}"]
                print(name, sampler, "(reused from", args.reuse_pretrained + ")",
                      {k.split("/")[1]: f"{s[k]:.4f} +- {s[k + '/std']:.4f}" for k in KEYS}, flush=True)
                continue
            pol = pol or r1sim_sumo.load_policy(ck)
            runs = [evaluate_policy(pol, scenes, sampler, 16, seed, batch_scenes=2, progress=False, metric=args.metric)
                    for seed in args.seeds]
            s = summarize_runs(runs)
            out[f"{name} / {sampler}"] = s
            print(name, sampler, {k.split("/")[1]: f"{s[k]:.4f} +- {s[k + '/std']:.4f}" for k in KEYS}, flush=True)
    change = {}
    for sampler in args.sampler:
        a, b = out[f"{pre_name} / {sampler}"], out[f"{args.grpo} / {sampler}"]
        c0, c1 = a["realism/collision_rate"], b["realism/collision_rate"]
        change[sampler] = {"collision_rate_change": (c1 - c0) / c0 if c0 > 0 else None,
                           "rmm_change": b["realism/rmm"] - a["realism/rmm"]}
        rel = change[sampler]["collision_rate_change"]
        print(f"{sampler}: collision rate {c0:.4f} -> {c1:.4f} ({'n/a' if rel is None else f'{rel:+.1%}'}), "
              f"RMM {a['realism/rmm']:.4f} -> {b['realism/rmm']:.4f}", flush=True)
    Path(args.out).write_text(json.dumps({"metric": args.metric, "pretrained": args.pretrained or "r1sim-nano", "grpo": args.grpo,
                                          "data": args.data, "seeds": args.seeds, "samplers": args.sampler,
                                          "scenes": scene_keys, "results": out, "change": change}, indent=1, default=str))


def reused_pretrained(args, pre_name: str, scene_keys: list[str]) -> dict:
    """The pretrained side's results from ``args.reuse_pretrained``; a clear error when that run differs."""
    path = Path(args.reuse_pretrained)
    old = json.loads(path.read_text())
    want = {"pretrained": args.pretrained or "r1sim-nano", "data": args.data, "seeds": args.seeds, "metric": args.metric,
            "scenes": scene_keys}
    for key, value in want.items():
        have = old.get(key, OLD_DEFAULTS.get(key))  # outputs written before --data / --seeds existed
        if have != value:
            raise SystemExit(f"{path}: field '{key}' is {have!r}, this run's is {value!r}; "
                             "rerun without --reuse-pretrained or give an output of the same setting")
    return {k: v for k, v in old["results"].items() if k.startswith(pre_name + " / ")}


if __name__ == "__main__":
    main()
