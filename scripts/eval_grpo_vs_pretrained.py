#!/usr/bin/env python3
"""GRPO checkpoint vs the pretrained one on held-out SUMO test scenes (8 scenes, 16 rollouts, entropy:16,80, 5 seeds).

Needs the default dataset (``r1sim dataset build --out data/generated/default``).
Run: ``python scripts/eval_grpo_vs_pretrained.py`` (also writes ``eval_grpo_vs_pretrained.json``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.evaluate import evaluate_policy, summarize_runs
from r1sim_sumo.scenario import ScenarioDataset

SAMPLER = "entropy:16,80"
KEYS = ["realism/rmm", "realism/collision_rate", "realism/offroad_rate"]


def main() -> None:
    torch.set_num_threads(2)
    ds = ScenarioDataset("data/generated/default/test")
    idx = np.random.default_rng(1).choice(len(ds), 80, replace=False)
    scenes = [s for s in (ds[int(i)] for i in idx) if s.metadata.get("source") == "sumo"][:8]
    out = {}
    for name, ck in [("r1sim-nano (pretrained)", None), ("r1sim-grpo", "r1sim-grpo")]:
        pol = r1sim_sumo.load_policy(ck)
        runs = [evaluate_policy(pol, scenes, SAMPLER, 16, seed, batch_scenes=2, progress=False) for seed in range(5)]
        s = summarize_runs(runs)
        out[f"{name} / {SAMPLER}"] = s
        print(name, SAMPLER, {k.split("/")[1]: f"{s[k]:.4f} +- {s[k + '/std']:.4f}" for k in KEYS}, flush=True)
    Path("eval_grpo_vs_pretrained.json").write_text(
        json.dumps({"scenes": [str(s.metadata) for s in scenes], "results": out}, indent=1, default=str))


if __name__ == "__main__":
    main()
