"""Average the weights of several checkpoints of one run (iterate averaging, as SWA / Polyak averaging).

GRPO's iterates on this CPU recipe (2 scenes x 32 rollouts per iteration) move a lot from one iteration to the
next: the same closed-loop evaluation of checkpoints 10 iterations apart differs by +-15% (session 53,
docs/training/README.md). The mean of several iterates of one run is one checkpoint with less of that noise.

Every checkpoint must have the same model config and vocabulary (fingerprint); the vocabulary tensors are copied,
each model tensor is the arithmetic mean (float64 accumulation, saved in the first checkpoint's dtype). The result is
an ordinary checkpoint (:func:`~r1sim_sumo.model.checkpoint.save_checkpoint`) whose ``training`` records the inputs
(paths and weight hashes) and the first input's training info.

    python -m r1sim_sumo.train.average_checkpoints OUT CKPT [CKPT ...]
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import torch

from r1sim_sumo.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint


def average_checkpoints(checkpoints: list[str | Path], out: str | Path) -> Path:
    """Write the weight average of ``checkpoints`` (directories) to ``out``; returns ``out``.

    Raises :class:`CheckpointError` naming the checkpoint that does not fit (another model config or vocabulary),
    and ``ValueError`` for fewer than two inputs or an ``out`` that is one of them."""
    paths = [Path(c) for c in checkpoints]
    if len(paths) < 2:
        raise ValueError(f"average_checkpoints: give at least two checkpoints, got {len(paths)}")
    out = Path(out)
    if any(out.resolve() == p.resolve() for p in paths):
        raise ValueError(f"average_checkpoints: the output {out} is one of the inputs; choose a new directory")
    first = load_checkpoint(paths[0])
    fp, cfg = first.info.get("vocab_fingerprint"), first.config.to_dict()
    state = {k: v.detach().to(torch.float64).clone() if v.is_floating_point() else v.clone()
             for k, v in first.model.state_dict().items()}
    inputs = [{"path": str(paths[0]), "weights_sha256": first.info.get("weights", {}).get("sha256")}]
    for p in paths[1:]:
        pol = load_checkpoint(p)
        if pol.info.get("vocab_fingerprint") != fp:
            raise CheckpointError(f"{p}: vocabulary {pol.info.get('vocab_fingerprint')} differs from {paths[0]}'s {fp}; "
                                  "average checkpoints of one run only")
        if pol.config.to_dict() != cfg:
            raise CheckpointError(f"{p}: model_config differs from {paths[0]}'s; average checkpoints of one run only")
        for k, v in pol.model.state_dict().items():
            if v.is_floating_point():
                state[k] += v.detach().to(torch.float64)
            elif not torch.equal(state[k], v):
                raise CheckpointError(f"{p}: non-float tensor '{k}' differs from {paths[0]}'s; cannot average it")
        inputs.append({"path": str(p), "weights_sha256": pol.info.get("weights", {}).get("sha256")})
    ref = first.model.state_dict()
    mean = {k: (v / len(paths)).to(ref[k].dtype) if v.is_floating_point() else v for k, v in state.items()}
    model = copy.deepcopy(first.model)
    model.load_state_dict(mean, strict=True)
    training = dict(first.info.get("training", {}))
    training["average_of"] = inputs
    return save_checkpoint(out, model, first.vocab, extra=training)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m r1sim_sumo.train.average_checkpoints", description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="new checkpoint directory")
    ap.add_argument("checkpoints", nargs="+", help="checkpoint directories of one run (two or more)")
    a = ap.parse_args(argv)
    try:
        d = average_checkpoints(a.checkpoints, a.out)
    except (CheckpointError, ValueError) as exc:
        print(f"average_checkpoints: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {d} (mean of {len(a.checkpoints)} checkpoints)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
