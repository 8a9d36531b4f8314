"""``r1sim tokens build``: the compact token dataset (tokenized train/val in a few LZMA files, <= 64 MiB for the
default recipe) that a training run on any machine starts from without regenerating SUMO data.

Example::

    r1sim tokens build --data data/generated/default --out data/tokens/default      # vocabulary of the shipped policy
    r1sim pretrain --config configs/pretrain.yaml --set tokens=data/tokens/default
"""

from __future__ import annotations

import argparse

HELP = "Build the compact token dataset (tokenized train/val splits, de-duplicated maps) from a dataset folder."


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="tokens_command", metavar="ACTION", required=True)
    b = sub.add_parser("build", help="tokenize a dataset folder into a compact token dataset")
    b.add_argument("--data", required=True, help="dataset folder of `r1sim dataset build` (with train/ and val/)")
    b.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    b.add_argument("--vocab", default=None,
                   help="vocabulary: a .safetensors file or a checkpoint (folder or bundled name) whose vocabulary to use "
                        "[default: the shipped r1sim-nano's]")
    b.add_argument("--splits", nargs="+", default=["train", "val"], help="splits to include [default: train val]")
    b.add_argument("--workers", type=int, default=2, help="tokenizing processes [default 2]")
    b.add_argument("--no-progress", action="store_true")


def _vocab(spec: str | None):
    from pathlib import Path

    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.tokens.motion_vocab import MotionVocab

    if spec and Path(spec).is_file():
        return MotionVocab.load(spec)
    return load_policy(spec).vocab


def run(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    from r1sim_sumo.tokens.compact import build_compact

    t0 = time.time()
    man = build_compact(args.data, _vocab(args.vocab), args.out, splits=tuple(args.splits), workers=args.workers,
                        progress=not args.no_progress)
    size = sum(f.stat().st_size for f in Path(args.out).iterdir()) / 2**20
    counts = ", ".join(f"{k} {v['num_scenes']} scenes / {v['num_maps']} maps" for k, v in man["splits"].items())
    print(f"wrote {args.out}: {counts}; {size:.1f} MiB in {time.time() - t0:.0f} s")
    return 0
