"""``r1sim show SCENARIO [--index I] [--out file.png]``: draw one scenario of a shard or dataset as a PNG.

``SCENARIO`` is a shard file (``.npz``, see :func:`r1sim_sumo.scenario.read_shard`) or a dataset folder holding
``manifest.json`` (:class:`r1sim_sumo.scenario.ScenarioDataset`); ``--index`` picks the scenario (shard-local
or dataset-global, negative counts from the end).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "draw one scenario (shard .npz or dataset folder) as a PNG"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", metavar="SCENARIO_FILE_OR_DATASET", help="shard .npz or dataset folder with manifest.json")
    p.add_argument("--index", type=int, default=0, help="scenario index in the shard/dataset (default 0)")
    p.add_argument("--out", default=None, help="output PNG (default: <name>_<index>.png in the current folder)")
    p.add_argument("--full-map", action="store_true", help="show the whole map instead of zooming to the agents")


def load_one(source: str | Path, index: int):
    """Scenario ``index`` of a shard file or a dataset folder (raises ScenarioError / IndexError)."""
    from r1sim_sumo.scenario import ScenarioDataset, ScenarioError, read_shard, shard_size

    src = Path(source)
    if src.is_dir():
        ds = ScenarioDataset(src)
        n = len(ds)
        if not -n <= index < n:
            raise IndexError(f"{src}: --index {index} outside the dataset's {n} scenarios")
        return ds[index]
    if not src.exists():
        raise ScenarioError(f"{src}: no such shard file or dataset folder")
    n = shard_size(src)
    if not -n <= index < n:
        raise IndexError(f"{src}: --index {index} outside the shard's {n} scenarios")
    return read_shard(src, indices=[index % n])[0]


def run(args: argparse.Namespace) -> int:
    from r1sim_sumo.scenario import ScenarioError
    from r1sim_sumo.viz import save_scenario_png

    try:
        sc = load_one(args.scenario, args.index)
    except (ScenarioError, IndexError) as exc:
        print(f"r1sim show: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path(f"{Path(args.scenario).stem}_{args.index}.png")
    save_scenario_png(sc, out, zoom_to_agents=not args.full_map)
    print(f"wrote {out} ({sc.metadata.get('source', '?')}, {sc.agents.num_agents} agents, {sc.num_steps} steps)")
    return 0
