"""Benchmark suite: ``python benchmarks/run.py [--only NAME ...] [--quick] [--out benchmarks/reports]``.

Every ``benchmarks/bench_<name>.py`` exposes ``run(quick: bool) -> dict`` returning
``{"title": str, "rows": [dict, ...], "notes": [str, ...]}``. Rows compare things measured side by side in
this same run (ratios), because the machines are shared and noisy. The suite writes
``<out>/report.json`` and ``<out>/report.md`` with a description of the machine. To compare two revisions side by
side (alternating runs, each tree importing its own package): ``python benchmarks/compare_revisions.py --base REV
--only NAME ...``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent


def machine_description() -> dict:
    info = {
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cpu_count": os.cpu_count(),
        "processor": platform.processor(),
    }
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu_model"] = line.split(":", 1)[1].strip()
                break
        mem = Path("/proc/meminfo").read_text().splitlines()[0].split()[1]
        info["mem_gib"] = round(int(mem) / 2**20, 1)
    except OSError:
        pass
    try:
        import torch

        info["torch"] = torch.__version__
        info["torch_threads"] = torch.get_num_threads()
    except ImportError:
        pass
    return info


def discover() -> dict[str, Path]:
    return {p.stem[len("bench_"):]: p for p in sorted(HERE.glob("bench_*.py"))}


def to_markdown(report: dict) -> str:
    lines = ["# r1sim-sumo benchmark report", "", f"Generated {report['generated']} in {report['wall_s']:.1f} s.", "", "## Machine", ""]
    lines += [f"- {k}: {v}" for k, v in report["machine"].items()]
    for name, res in report["benchmarks"].items():
        lines += ["", f"## {res.get('title', name)}", ""]
        if "generated" in res:
            lines += [f"Measured {res['generated']}.", ""]
        if "error" in res:
            lines += ["```", res["error"], "```"]
            continue
        rows = res.get("rows", [])
        if rows:
            cols = list(dict.fromkeys(k for r in rows for k in r))
            lines.append("| " + " | ".join(cols) + " |")
            lines.append("|" + "---|" * len(cols))
            for r in rows:
                lines.append("| " + " | ".join(_fmt(r.get(c, "")) for c in cols) + " |")
        for n in res.get("notes", []):
            lines += ["", f"- {n}"]
    return "\n".join(lines) + "\n"


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", help="benchmark names to run (default: all)")
    ap.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    ap.add_argument("--out", default=str(HERE / "reports"), help="output folder for report.json / report.md")
    args = ap.parse_args(argv)
    benches = discover()
    names = args.only or list(benches)
    unknown = [n for n in names if n not in benches]
    if unknown:
        ap.error(f"unknown benchmark(s) {unknown}; available: {list(benches)}")
    t0 = time.time()
    report = {"generated": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": machine_description(), "benchmarks": {}}
    for n in names:
        print(f"[bench] {n} ...", flush=True)
        spec = importlib.util.spec_from_file_location(f"bench_{n}", benches[n])
        mod = importlib.util.module_from_spec(spec)
        try:
            spec.loader.exec_module(mod)
            report["benchmarks"][n] = mod.run(quick=args.quick)
        except Exception:
            report["benchmarks"][n] = {"title": n, "error": traceback.format_exc()}
            print(traceback.format_exc(), file=sys.stderr)
    report["wall_s"] = time.time() - t0
    for res in report["benchmarks"].values():
        res["generated"] = report["generated"]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.only and (out / "report.json").exists():  # a partial run updates its rows, the others stay (dated)
        old = json.loads((out / "report.json").read_text())
        for res in old.get("benchmarks", {}).values():
            res.setdefault("generated", old.get("generated", "?"))
        report["benchmarks"] = {**old.get("benchmarks", {}), **report["benchmarks"]}
    (out / "report.json").write_text(json.dumps(report, indent=2))
    (out / "report.md").write_text(to_markdown(report))
    print(f"[bench] wrote {out / 'report.json'} and {out / 'report.md'}")
    return 1 if any("error" in r for r in report["benchmarks"].values()) else 0


if __name__ == "__main__":
    sys.exit(main())
