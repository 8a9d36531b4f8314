#!/usr/bin/env python3
"""Carry a trained checkpoint over to its vocabulary extended with high-speed curve and lane-change vehicle tokens
(:mod:`r1sim_sumo.tokens.vocab_extend`, :mod:`r1sim_sumo.model.resize_vocab`), and check that the extended model's
distribution over each old token's group equals the old model's on a few real scenes.

    python scripts/extend_vocab_checkpoint.py r1sim-nano --out runs/vocab_ext/init --check data/generated/default/val

Then tokenize with its vocabulary (``r1sim tokens build --vocab runs/vocab_ext/init ...``) and train from it
(``init_checkpoint: runs/vocab_ext/init``).
"""

from __future__ import annotations

import argparse
import json

import torch

import r1sim_sumo
from r1sim_sumo.model.checkpoint import save_checkpoint
from r1sim_sumo.model.resize_vocab import extend_policy_vocab, group_log_prob_gap
from r1sim_sumo.tokens.motion_vocab import VEHICLE
from r1sim_sumo.tokens.vocab_extend import extend_vehicle_vocab, nearest_old_token


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", help="checkpoint folder or bundled name")
    ap.add_argument("--out", required=True)
    ap.add_argument("--check", default=None, help="scenario split to compare old and new distributions on (4 scenes)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    pol = r1sim_sumo.load_policy(a.checkpoint)
    vocab = extend_vehicle_vocab(pol.vocab)
    model = extend_policy_vocab(pol.model, pol.vocab, vocab).eval()
    ext = vocab.meta["extension"]
    # checkpoint.json "training": a zero-step "train" segment whose init_checkpoint is the source, which
    # `r1sim_sumo.train.ship` follows back to the shipped policy
    train = {"steps": 0, "cpu_hours": 0.0, "init_checkpoint": a.checkpoint, "extension": ext,
             "method": "vocabulary extension (scripts/extend_vocab_checkpoint.py)"}
    info = {"train": train}
    if a.check:
        from r1sim_sumo.scenario import ScenarioDataset
        from r1sim_sumo.tokens.batch import collate, tokenize_scenario

        ds = ScenarioDataset(a.check)
        base = pol.vocab.size(VEHICLE)
        near = nearest_old_token(vocab, base)
        items_old = [tokenize_scenario(ds[i], pol.vocab) for i in range(4)]
        gap = group_log_prob_gap(pol.model.eval(), model, collate(items_old), base, near)
        train["group_log_prob_gap"] = gap
        print(f"largest |log p(old token) - log p(its group)| on 4 scenes: {gap:.2e}")
    save_checkpoint(a.out, model, vocab, extra=info)
    print(json.dumps(ext, indent=1))
    print(f"extended checkpoint written to {a.out}: vehicle vocabulary {ext['base_vehicle_size']} -> {vocab.size(VEHICLE)}")


if __name__ == "__main__":
    main()
