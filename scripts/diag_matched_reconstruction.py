#!/usr/bin/env python3
"""Offroad and position error of the rolling-matched *reference* (GT tokens rebuilt) on held-out SUMO test scenes, per
network: how far the vocabulary alone moves the logged futures.

Run: ``python scripts/diag_matched_reconstruction.py runs/vocab/vocab.safetensors`` (needs the default dataset).
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from r1sim_sumo.evaluate import matched_reference_sim
from r1sim_sumo.metrics.realism import compute_features
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.motion_vocab import MotionVocab


def scene_figures(sc, vocab) -> tuple[float, float, float]:
    """(offroad share of the agents valid now, mean and max position error [m]) of the matched reference."""
    ci = sc.current_index
    sim = matched_reference_sim(sc, vocab)
    f = compute_features(sc, sim.x_m, sim.y_m, sim.yaw_rad, sim.valid)
    T = sim.x_m.shape[-1]
    a = sc.agents
    both = sim.valid[0] & a.valid[:, ci + 1:ci + 1 + T]
    err = np.hypot(sim.x_m[0] - a.x_m[:, ci + 1:ci + 1 + T], sim.y_m[0] - a.y_m[:, ci + 1:ci + 1 + T])[both]
    live = a.valid[:, ci]
    return float(f.offroad.any(-1)[0, live].mean()), float(err.mean()), float(err.max())


def main(vocab_path: str) -> None:
    torch.set_num_threads(1)
    vocab = MotionVocab.load(vocab_path)
    ds = ScenarioDataset("data/generated/default/test")
    res: dict[str, list[tuple[float, float, float]]] = {}
    for i in np.random.default_rng(0).choice(len(ds), 80, replace=False):
        sc = ds[int(i)]
        if sc.metadata.get("source") == "sumo":
            res.setdefault(sc.metadata["network"], []).append(scene_figures(sc, vocab))
    for net, rows in res.items():
        r = np.array(rows)
        print(net, len(r), "offroad", r[:, 0].mean().round(3), "err mean", r[:, 1].mean().round(3), "max", r[:, 2].max().round(2))


if __name__ == "__main__":
    main(sys.argv[1])
