"""``r1sim vocab``: build the motion-token vocabulary (k-disk) from a scenario dataset and report its error.

Example::

    r1sim vocab --data data/generated/sumo_train --out vocab.safetensors --size 2048 512 512 --tolerance 0.05
"""

from __future__ import annotations

import argparse

HELP = "Build the motion-token vocabulary (k-disk clustering of 0.5 s segments) from a scenario dataset."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True, help="scenario dataset folder (manifest.json + shards)")
    p.add_argument("--out", required=True, help="output vocabulary file (.safetensors; a .json sidecar is written beside it)")
    p.add_argument("--size", type=int, nargs="+", default=[2048, 512, 512],
                   help="max tokens: one value for all types or three (vehicle cyclist pedestrian) [default 2048 512 512]")
    p.add_argument("--tolerance", type=float, nargs="+", default=[0.05],
                   help="k-disk radius on mean corner distance [m]: one value or three [default 0.05]")
    p.add_argument("--max-segments", type=int, default=200_000, help="segments per type fed to clustering [default 200000]")
    p.add_argument("--heldout", type=float, default=0.1, help="trailing fraction of scenarios held out for the report [default 0.1]")
    p.add_argument("--synthetic-fill", type=float, default=0.1,
                   help="fraction of each data-built sub-vocabulary filled with synthetic segments no data token covers [default 0.1]")
    p.add_argument("--seed", type=int, default=0)


def _triple(values: list, name: str) -> tuple:
    if len(values) == 1:
        return (values[0],) * 3
    if len(values) == 3:
        return tuple(values)
    raise SystemExit(f"r1sim vocab: --{name} takes one value or three (vehicle cyclist pedestrian), got {values}")


def run(args: argparse.Namespace) -> int:
    from r1sim_sumo.scenario import ScenarioDataset
    from r1sim_sumo.tokens.motion_vocab import VocabBuildConfig
    from r1sim_sumo.tokens.vocab_build import build_vocab_from_dataset, format_report

    cfg = VocabBuildConfig(size=_triple(args.size, "size"), tolerance_m=_triple(args.tolerance, "tolerance"),
                           max_segments=args.max_segments, heldout_fraction=args.heldout,
                           synthetic_fill=args.synthetic_fill, seed=args.seed)
    data = ScenarioDataset(args.data)
    vocab, report = build_vocab_from_dataset(data, cfg, progress=True)
    path = vocab.save(args.out)
    print(f"vocabulary {path} (fingerprint {vocab.fingerprint()}): sizes {vocab.sizes} "
          f"sources {vocab.meta['source']} coverage {vocab.meta['coverage']}")
    print("reconstruction error of rolling-matched held-out tracks (future window):")
    print(format_report(report))
    return 0
