"""Export a policy checkpoint from a pretraining run's training state (``state/state.safetensors``: weights + AdamW).

For a run stopped between kept checkpoints (a lent GPU machine's time limit, a killed job): the weights of its last
``ckpt_every`` step become a loadable checkpoint folder, with the model config, vocabulary and training record of one
of the run's kept checkpoints and the state's step written in. The optimizer's step count tells which step that is.

    python scripts/checkpoint_from_state.py runs/gpu_ext2 --like runs/gpu_ext2/ckpt-000600 --out runs/gpu_ext2/final
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from r1sim_sumo.model.checkpoint import load_checkpoint, save_checkpoint
from r1sim_sumo.train.train_state import TrainStateError, load_state_weights


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="run folder holding state/state.safetensors")
    ap.add_argument("--like", required=True, help="a kept checkpoint of the same run (model config + vocabulary)")
    ap.add_argument("--out", required=True, help="checkpoint folder to write (must not exist)")
    a = ap.parse_args(argv)
    if Path(a.out).exists():
        sys.exit(f"{a.out}: exists; choose another --out (nothing is overwritten)")
    policy = load_checkpoint(a.like)
    state = Path(a.run) / "state"
    try:
        step = load_state_weights(state, policy.model)
    except TrainStateError as exc:
        sys.exit(str(exc))
    extra = dict(policy.info.get("training", {}))
    train = dict(extra.get("train", {}))
    like_step = train.get("steps")
    if like_step and train.get("agent_tokens_seen"):
        train["agent_tokens_seen"] = int(round(train["agent_tokens_seen"] * step / like_step))  # scaled: same batch size
    train.pop("cpu_hours", None)  # not known for the exported step
    train.update(steps=step, exported_from_state=str(state))
    extra["train"] = train
    save_checkpoint(a.out, policy.model, policy.vocab, extra=extra)
    print(f"{a.out}: step {step} weights from {state}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
