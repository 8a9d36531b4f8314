"""The ``r1sim`` command. Each subcommand lives in ``r1sim_sumo/commands/<name>.py`` exposing
``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``; they are imported lazily so
``r1sim --help`` is fast and a missing optional dependency only affects its own subcommand."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import r1sim_sumo.commands as _commands
from r1sim_sumo._version import __version__

ORDER = ["generate", "dataset", "show", "vocab", "tokens", "pretrain", "finetune", "evaluate", "simulate", "bench"]


def _available() -> list[str]:
    names = [m.name for m in pkgutil.iter_modules(_commands.__path__) if not m.name.startswith("_")]
    return sorted(names, key=lambda n: (ORDER.index(n) if n in ORDER else len(ORDER), n))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="r1sim", description="Learned tokenized traffic for SUMO and highway-env (R1Sim).")
    p.add_argument("--version", action="version", version=f"r1sim-sumo {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name in _available():
        mod = importlib.import_module(f"r1sim_sumo.commands.{name}")
        sp = sub.add_parser(name.replace("_", "-"), help=mod.HELP, description=mod.HELP)
        mod.add_arguments(sp)
        sp.set_defaults(_run=mod.run)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 0
    return int(args._run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
