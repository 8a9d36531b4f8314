"""Rebuild the bundled SUMO networks (``<name>/<name>.net.xml``) from their plain-XML sources.

Each network folder ``networks/<name>/`` holds a netconvert configuration ``<name>.netccfg`` that names its
plain-XML inputs (``.nod.xml``, ``.edg.xml`` and, where used, ``.con.xml`` / ``.tll.xml``) and the options
(no coordinate offset, no turnarounds, ...). This script runs the ``netconvert`` shipped with eclipse-sumo on
each configuration.

Idempotent: a network is built into a temporary file first and its ``.net.xml`` is replaced only when the
content changed (the leading "generated on <date>" comment is ignored), so rebuilding unchanged sources leaves
the files untouched.

    python networks/build.py                 # rebuild every network whose sources changed
    python networks/build.py --only roundabout
    python networks/build.py --check         # exit 1 if a committed .net.xml is out of date
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

NETWORKS_DIR = Path(__file__).resolve().parent

try:
    from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
except ImportError:  # run from a checkout without the package installed
    sys.path.insert(0, str(NETWORKS_DIR.parent))
    from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary

_HEADER_COMMENT = re.compile(r"<!--.*?-->", re.DOTALL)


@dataclass(frozen=True)
class NetworkSources:
    """The netconvert configuration of one bundled network and the .net.xml it produces."""

    name: str
    folder: Path
    netccfg: Path
    net_xml: Path


def discover(networks_dir: Path = NETWORKS_DIR) -> list[NetworkSources]:
    """Every folder ``<networks_dir>/<name>/`` (and ``<networks_dir>/training/<name>/``, the training-only networks)
    holding ``<name>.netccfg``, sorted by name."""
    found = []
    training = networks_dir / "training"
    folders = [p for p in networks_dir.iterdir() if p.is_dir()]
    folders += [p for p in training.iterdir() if p.is_dir()] if training.is_dir() else []
    for folder in sorted(folders, key=lambda p: p.name):
        cfg = folder / f"{folder.name}.netccfg"
        if cfg.is_file():
            found.append(NetworkSources(folder.name, folder, cfg, folder / f"{folder.name}.net.xml"))
    return found


def net_body(text: str) -> str:
    """The .net.xml text without its first comment (netconvert's date + configuration header)."""
    return _HEADER_COMMENT.sub("", text, count=1)


def run_netconvert(src: NetworkSources, output: Path) -> None:
    """Run netconvert on ``src.netccfg`` writing ``output``; raises RuntimeError with netconvert's messages."""
    env = dict(os.environ, SUMO_HOME=str(ensure_sumo_home()))
    cmd = [sumo_binary("netconvert"), "-c", src.netccfg.name, "--output-file", str(output)]
    proc = subprocess.run(cmd, cwd=src.folder, env=env, capture_output=True, text=True)
    messages = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0 or not output.is_file():
        raise RuntimeError(f"netconvert failed for {src.netccfg} (exit {proc.returncode}):\n{messages}")
    warnings = [ln for ln in messages.splitlines() if ln.startswith("Warning")]
    for ln in warnings:
        print(f"  [{src.name}] {ln}", file=sys.stderr)


def build_one(src: NetworkSources, check: bool) -> bool:
    """Build ``src`` into a temporary file; return True when the committed .net.xml is (now) up to date.

    With ``check`` the committed file is never written; otherwise it is replaced when its body differs.
    """
    with tempfile.TemporaryDirectory(prefix=f"r1sim_net_{src.name}_") as tmp:
        fresh = Path(tmp) / src.net_xml.name
        run_netconvert(src, fresh)
        same = src.net_xml.is_file() and net_body(src.net_xml.read_text()) == net_body(fresh.read_text())
        if same:
            print(f"{src.name}: up to date")
            return True
        if check:
            print(
                f"{src.name}: OUT OF DATE ({src.net_xml} differs from a rebuild; run python networks/build.py)"
            )
            return False
        shutil.copyfile(fresh, src.net_xml)
        print(f"{src.name}: rebuilt {src.net_xml}")
        return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--only", action="append", metavar="NAME", help="build only this network (repeatable)"
    )
    parser.add_argument("--check", action="store_true", help="do not write; exit 1 if any .net.xml is stale")
    args = parser.parse_args(argv)

    sources = discover()
    if args.only:
        known = {s.name for s in sources}
        unknown = sorted(set(args.only) - known)
        if unknown:
            parser.error(f"unknown network(s) {unknown}; choose from {sorted(known)}")
        sources = [s for s in sources if s.name in args.only]
    ok = [build_one(s, args.check) for s in sources]
    return 0 if all(ok) else 1


if __name__ == "__main__":
    sys.exit(main())
