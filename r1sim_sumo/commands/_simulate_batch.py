"""Batch mode of ``r1sim simulate``: one SUMO run per (sumocfg, seed) on a worker pool, one summary row each.

Entered when several ``--sumocfg`` / ``--network`` values, a ``--batch FILE_OR_GLOB`` or ``--seeds`` are
given. Each run is a task of :mod:`r1sim_sumo.workers` (libsumo holds one simulation per process, so the
``process`` and ``ray`` backends run one simulation per worker). A loaded checkpoint is sent to each worker
once (``shared``); ``--untrained`` policies are built in the worker from the run's seed, as in a single run.
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

GLOB_CHARS = set("*?[")


@dataclass
class SimRun:
    """One batch run: the .sumocfg, the seed and the options every run shares (see ``r1sim simulate``)."""

    sumocfg: str
    seed: int
    end: float
    control: str
    sampler: str
    traci: bool
    native: bool
    untrained: bool
    fcd_output: str | None
    drive: str = "commands"
    safety: str = "krauss"
    standstill_handoff: float = 5.0

    def describe(self) -> str:
        return f"{self.sumocfg} seed {self.seed}"


def batch_requested(args: argparse.Namespace) -> bool:
    """True for several configs, a ``--batch`` file/glob or ``--seeds``."""
    many = len(args.sumocfg or []) > 1 or len(args.network or []) > 1
    return bool(many or args.batch or args.seeds)


def _batch_configs(spec: str) -> list[str]:
    """A glob of .sumocfg files, one .sumocfg, or a text file listing .sumocfg paths (relative to it)."""
    from r1sim_sumo.commands.simulate import SimulateError

    if GLOB_CHARS & set(spec):
        found = sorted(glob.glob(spec, recursive=True))
        if not found:
            raise SimulateError(f"--batch {spec}: the pattern matches no file")
        return found
    p = Path(spec)
    if not p.is_file():
        raise SimulateError(f"--batch {spec}: no such file (give a glob of .sumocfg files or a text file listing them)")
    if p.suffix == ".sumocfg":
        return [str(p)]
    lines = [ln.split("#", 1)[0].strip() for ln in p.read_text().splitlines()]
    out = [str(Path(ln) if Path(ln).is_absolute() else p.parent / ln) for ln in lines if ln]
    if not out:
        raise SimulateError(f"--batch {spec}: the file lists no .sumocfg (one path per line expected)")
    return out


def batch_runs(args: argparse.Namespace) -> list[SimRun]:
    """Every (config, seed) run of the batch, configs checked up front (errors name the file and field)."""
    from r1sim_sumo.commands.simulate import SimulateError, resolve_sumocfg

    if args.gui:
        raise SimulateError("--gui: batch mode runs many simulations without windows; drop --gui or run one config")
    if args.batch:
        cfgs = [resolve_sumocfg(c, None) for c in _batch_configs(args.batch)]
    elif args.sumocfg:
        cfgs = [resolve_sumocfg(c, None) for c in args.sumocfg]
    else:
        cfgs = [resolve_sumocfg(None, n) for n in (args.network or [None])]
    seeds = list(dict.fromkeys(args.seeds or [args.seed]))
    runs = []
    for cfg in cfgs:
        for seed in seeds:
            fcd = None
            if args.fcd_output:
                f = Path(args.fcd_output)
                fcd = str(f.with_name(f"{f.stem}__{cfg.stem}__seed{seed}{f.suffix or '.xml'}"))
            runs.append(SimRun(str(cfg), int(seed), float(args.end), args.control, args.sampler, bool(args.traci),
                               bool(args.native), bool(args.untrained), fcd, getattr(args, "drive", "commands"),
                               getattr(args, "safety", "krauss"), getattr(args, "standstill_handoff", 5.0)))
    labels = [(r.sumocfg, r.seed) for r in runs]
    if len(set(labels)) != len(labels):
        raise SimulateError("batch: the same (sumocfg, seed) is listed twice; each run must be unique")
    return runs


def simulate_task(run: SimRun, policy=None) -> dict:
    """Pool task: one simulation; ``policy`` is the shared checkpoint (``None``: native or untrained)."""
    from r1sim_sumo.commands.simulate import SumoCrashed, simulate, untrained_policy

    if run.untrained and not run.native:
        policy = untrained_policy(run.seed)
    if run.native:
        policy = None
    ns = argparse.Namespace(gui=False, **{k: v for k, v in asdict(run).items() if k not in ("sumocfg", "native", "untrained")})
    try:
        return simulate(Path(run.sumocfg), ns, policy, progress=False)
    except SumoCrashed as exc:  # a partial summary is still a result: the row says where SUMO stopped
        return exc.summary


ROW_FIELDS = [("sumocfg", "{}"), ("seed", "{}"), ("mode", "{}"), ("drive", "{}"), ("departed", "{}"),
              ("waiting_to_insert", "{}"), ("arrived", "{}"),
              ("collisions_any", "{}"), ("teleports", "{}"), ("mean_speed_mps", "{:.2f}"), ("sim_s_per_wall_s", "{:.1f}")]


def format_rows(summaries: list[dict]) -> str:
    """A fixed-width table: one row per run (``crashed`` marks runs where SUMO stopped early)."""
    head = [k for k, _ in ROW_FIELDS] + ["status"]
    rows = []
    for s in summaries:
        cells = [fmt.format(Path(s[k]).stem if k == "sumocfg" else s.get(k, "")) for k, fmt in ROW_FIELDS]
        rows.append(cells + ["crashed" if s.get("sumo_crashed") else "ok"])
    w = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    line = lambda cells: "  ".join(c.ljust(w[i]) for i, c in enumerate(cells))  # noqa: E731
    return "\n".join([line(head), line(["-" * x for x in w]), *(line(r) for r in rows)])


def run_batch(args: argparse.Namespace) -> int:
    """``r1sim simulate`` batch mode: run, print one row per run and the pool's retry report."""
    from r1sim_sumo.commands.simulate import SimulateError, load_checkpoint
    from r1sim_sumo.workers import TaskFailedError, pool_from_args

    try:
        runs = batch_runs(args)
        policy = None if (args.native or args.untrained) else load_checkpoint(args.checkpoint)
        with pool_from_args(args) as pool:
            summaries = pool.map(simulate_task, runs, shared=policy)
            stats = pool.stats
    except (SimulateError, TaskFailedError, ValueError, ImportError) as exc:
        print(f"r1sim simulate: error: {exc}", file=sys.stderr)
        return 2
    print(format_rows(summaries))
    print(f"[simulate] {len(runs)} run(s); {stats.summary()}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"runs": summaries, "pool": stats.to_dict()}, indent=2, default=str))
        print(f"summaries written to {args.json}")
    return 3 if any(s.get("sumo_crashed") for s in summaries) else 0
