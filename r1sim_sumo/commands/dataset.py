"""``r1sim dataset build``: the default training data (SUMO networks x seeds + highway-env), split by seed.

Examples::

    r1sim dataset build --out data/generated/small --size small          # < 1 min, for tests
    r1sim dataset build --out data/generated/default --workers 2         # >= 20,000 training windows
    r1sim dataset build --out DIR --config configs/dataset.yaml          # recipe overrides from YAML

Writes ``DIR/train``, ``DIR/val``, ``DIR/test`` (dataset folders) and ``DIR/splits.json``; see
:mod:`r1sim_sumo.data.dataset` for the recipe.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

HELP = "build the default train/val/test scenario dataset (SUMO + highway-env)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    p = sub.add_parser("build", help="generate train/ val/ test/ + splits.json")
    p.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    p.add_argument("--size", choices=("small", "default"), default="default", help="recipe preset (default: default)")
    p.add_argument("--config", default=None, help="YAML file of recipe overrides (keys of DatasetRecipe)")
    p.add_argument("--workers", type=int, default=2, help="parallel simulator processes (default 2)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from r1sim_sumo.data.dataset import DatasetRecipe, GenerationError, build_dataset, check_fresh_out_dir

    try:
        check_fresh_out_dir(args.out)
        recipe = DatasetRecipe.preset(args.size)
        if args.config:
            recipe = DatasetRecipe.from_yaml(args.config, base=recipe)
        jobs = recipe.jobs()
        name = f"'{args.size}' + {args.config}" if args.config else f"'{args.size}'"
        print(f"dataset recipe {name}: " + ", ".join(f"{s} {len(j)} jobs" for s, j in jobs.items())
              + f"; <= {recipe.expected_sumo_windows('train')} SUMO training windows", flush=True)
        t0 = time.perf_counter()
        out = build_dataset(args.out, recipe, workers=args.workers, progress=not args.no_progress)
    except (GenerationError, ValueError, FileNotFoundError) as exc:
        print(f"r1sim dataset build: error: {exc}", file=sys.stderr)
        return 1
    splits = json.loads((out / "splits.json").read_text())["splits"]
    counts = ", ".join(f"{s}={v['num_scenarios']}" for s, v in splits.items())
    print(f"wrote {out} ({counts} windows) in {time.perf_counter() - t0:.1f} s")
    return 0
