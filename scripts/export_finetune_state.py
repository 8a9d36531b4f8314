#!/usr/bin/env python3
"""Export the weights of a fine-tuning run's training state (``r1sim finetune``: SFT or GRPO) as a checkpoint folder.

    python scripts/export_finetune_state.py runs/grpo_i --out runs/grpo_i/ckpt-000060

A run keeps ``state/`` (weights + optimizer, written every ``ckpt_every`` iterations) but exports a checkpoint folder only
at its end or every ``keep_every`` iterations; this turns the state at its current iteration into a folder that
``load_policy``, the evaluation scripts and ``r1sim_sumo.train.ship`` read. The model is built from the run's
``init_checkpoint`` (recorded in the state), so the weights load with ``strict=True``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="the run folder (holds state/)")
    ap.add_argument("--out", required=True, help="checkpoint folder to write (refused if it exists)")
    args = ap.parse_args(argv)
    from r1sim_sumo import load_policy
    from r1sim_sumo.model.checkpoint import save_checkpoint
    from r1sim_sumo.train.train_state import load_train_state

    state = Path(args.run) / "state"
    meta = state / "state.json"
    if not meta.exists():
        raise SystemExit(f"{meta}: no training state; give the folder of a run started by `r1sim finetune`")
    info = json.loads(meta.read_text())["info"]
    init = info.get("config", {}).get("init_checkpoint")
    if not init:
        raise SystemExit(f"{meta}: field info.config.init_checkpoint is missing; this is not a fine-tuning run's state")
    out = Path(args.out)
    if out.exists():
        raise SystemExit(f"{out}: exists; choose another --out (nothing was overwritten)")
    policy = load_policy(init)
    model = policy.model.float()
    it = int(load_train_state(state, model, None)["iter"])
    save_checkpoint(out, model, policy.vocab, extra={"finetune": {"method": info["config"].get("method"), "iters": it,
                                                                  "config": info["config"], "exported_from": str(state)}})
    print(f"[export] iteration {it} of {args.run} -> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
