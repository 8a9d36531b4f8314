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

from safetensors.torch import load_file

from r1sim_sumo.model.checkpoint import load_checkpoint, save_checkpoint


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="run folder holding state/state.safetensors")
    ap.add_argument("--like", required=True, help="a kept checkpoint of the same run (model config + vocabulary)")
    ap.add_argument("--out", required=True, help="checkpoint folder to write (must not exist)")
    a = ap.parse_args(argv)
    state_file = Path(a.run) / "state" / "state.safetensors"
    if not state_file.exists():
        sys.exit(f"{state_file}: missing; the run folder needs its training state (state/state.safetensors)")
    if Path(a.out).exists():
        sys.exit(f"{a.out}: exists; choose another --out (nothing is overwritten)")
    state = load_file(str(state_file))
    weights = {k[len("model."):]: v for k, v in state.items() if k.startswith("model.")}
    steps = {float(v.reshape(-1)[0]) for k, v in state.items() if k.startswith("opt.") and k.endswith(".step")}
    if len(steps) != 1:
        sys.exit(f"{state_file}: optimizer step counts differ ({sorted(steps)[:4]}...); not one training step's state")
    step = int(steps.pop())
    policy = load_checkpoint(a.like)
    policy.model.load_state_dict(weights, strict=True)
    extra = dict(policy.info.get("training", {}))
    train = dict(extra.get("train", {}))
    like_step = train.get("steps")
    if like_step and train.get("agent_tokens_seen"):
        train["agent_tokens_seen"] = int(round(train["agent_tokens_seen"] * step / like_step))  # scaled: same batch size
    train.pop("cpu_hours", None)  # not known for the exported step
    train.update(steps=step, exported_from_state=str(state_file))
    extra["train"] = train
    save_checkpoint(a.out, policy.model, policy.vocab, extra=extra)
    print(f"{a.out}: step {step} weights from {state_file}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
