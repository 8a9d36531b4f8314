"""Compare benchmark rows of two revisions side by side:
``python benchmarks/compare_revisions.py --base REV --only NAME [NAME ...] [--rounds 2] [--quick [NAME ...]]
[--base-tree DIR] [--threads 1] [--out benchmarks/reports/compare]`` (``--quick`` alone: every benchmark quick).

The *current* tree is the checkout holding this file; the *base* tree is a detached git worktree of ``REV``
(made in a temporary folder and removed afterwards, or reused with ``--base-tree DIR``, which must be checked
out at ``REV``). For each round and each benchmark name, ``benchmarks/run.py --only NAME [--quick] --out TMP``
runs once in the base tree and once in the current tree, alternating (base, current, base, current, ...) so
that machine drift hits both. Each run gets ``PYTHONPATH=<its tree>`` (checked before measuring: a child
prints ``r1sim_sumo.__file__``, which must lie in its own tree; the package is pip-installed editable from one
checkout, so without this both would import the same code). Ignored inputs the benchmarks read
(``--share``, default ``data/generated data/tokens``) are symlinked from the current tree into the base tree
when missing there.

Threads: ``--threads N`` (default 1) sets ``OMP_NUM_THREADS``/``MKL_NUM_THREADS`` and caps every
``torch.set_num_threads`` call at ``N`` in the children (a ``sitecustomize`` on their ``PYTHONPATH``, inherited
by subprocesses that keep ``PYTHONPATH``), so rows labelled "2 threads" run on ``N`` threads in both trees.
``--threads 0`` leaves the benchmarks' own settings.

Rows are paired by position (their labels, the string and constant integer fields, must agree). For every
timing/throughput field the output gives the per-round values, the base and current medians, the ratio
current/base and the noise: the larger relative spread ``(max - min) / median`` over rounds of one tree.
Direction comes from the field name: higher is better for throughputs (``*_per_s``, ``*per_wall_s``,
``speedup*``, ``*GFLOP_s``, ``frac_*``, ``*_over_*``, ``vs_*``), lower is better for times and memory
(``*_ms`` [ms], ``*_s`` / ``seconds*`` [s], ``*_us*`` [us], ``*rss*`` / ``*_MB`` / ``*_mib`` [MiB],
``slowdown*`` [x]); other numbers (counts, shares, rates) are listed in the JSON but not judged. A field is
"slower" when the current tree is worse by more than the noise (relative change, e.g. 0.12 = 12 %), "faster"
when better by more than the noise, else "within noise"; a row is "within noise or faster" unless a field is
slower. Writes ``<out>/compare.json``, ``<out>/compare.md`` and each run's report under ``<out>/raw/``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CURRENT = Path(__file__).resolve().parents[1]

SITECUSTOMIZE = '''"""Written by benchmarks/compare_revisions.py: caps torch.set_num_threads at $R1SIM_MAX_TORCH_THREADS."""
import importlib.abc
import importlib.machinery
import os
import sys

_MAX = int(os.environ.get("R1SIM_MAX_TORCH_THREADS", "0") or 0)


class _CapTorchThreads(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name != "torch":
            return None
        sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None:
            return spec
        load = spec.loader.exec_module

        def exec_module(module):
            load(module)
            real = module.set_num_threads
            module.set_num_threads = lambda n: real(min(int(n), _MAX))
            real(_MAX)

        spec.loader.exec_module = exec_module
        return spec


if _MAX > 0:
    sys.meta_path.insert(0, _CapTorchThreads())
'''

HIGHER = re.compile(r"per_s$|per_wall_s|speedup|gflop_s|^frac_|_over_|^vs_|_vs_in_model")
LOWER = re.compile(r"slowdown|_ms$|_ms_|^ms_|_s$|^s_per|seconds|_us_|_us$|rss|_mb$|_mib")


def direction(field: str) -> int:
    """+1 higher is better, -1 lower is better, 0 not a timing/throughput/memory field."""
    f = field.lower()
    if f.startswith("slowdown"):
        return -1
    if HIGHER.search(f):
        return 1
    if LOWER.search(f):
        return -1
    return 0


def git(*args: str, cwd: Path = CURRENT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def child_env(tree: Path, site_dir: Path | None, threads: int) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree)] + ([str(site_dir)] if site_dir else [])))
    if threads > 0:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads), R1SIM_MAX_TORCH_THREADS=str(threads))
    return env


def check_tree(tree: Path, env: dict, threads: int) -> str:
    """Fail unless a child started like the benchmarks imports ``r1sim_sumo`` from ``tree`` (and caps threads)."""
    code = ("import r1sim_sumo, torch; torch.set_num_threads(2); "
            "print(r1sim_sumo.__file__); print(torch.get_num_threads())")
    out = subprocess.run([sys.executable, "-c", code], cwd=tree, env=env, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"compare_revisions: python in {tree} failed:\n{out.stderr[-2000:]}")
    path, n = out.stdout.split()[-2:]
    if not Path(path).resolve().is_relative_to(tree.resolve()):
        raise SystemExit(f"compare_revisions: a child in {tree} imports r1sim_sumo from {path}, not from its own tree")
    if threads > 0 and int(n) != threads:
        raise SystemExit(f"compare_revisions: torch.set_num_threads(2) gave {n} threads, expected the cap {threads}")
    return path


def make_base_tree(rev: str, base_tree: str | None, share: list[str]) -> tuple[Path, bool]:
    """The base worktree (created when ``base_tree`` is None) and whether this run created it."""
    want = git("rev-parse", f"{rev}^{{commit}}")
    if base_tree:
        tree = Path(base_tree).resolve()
        have = git("rev-parse", "HEAD", cwd=tree)
        if have != want:
            raise SystemExit(f"compare_revisions: --base-tree {tree} is at {have[:9]}, not at --base {rev} ({want[:9]}); "
                             f"check out {rev} there or drop --base-tree")
        created = False
    else:
        tree = Path(tempfile.mkdtemp(prefix="compare_base_")) / "tree"
        git("worktree", "add", "--detach", str(tree), want)
        created = True
    for rel in share:
        src, dst = CURRENT / rel, tree / rel
        if src.exists() and not dst.exists():
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.symlink_to(src.resolve())
            print(f"[compare] shared {rel}: {dst} -> {src.resolve()}", flush=True)
    return tree, created


def run_once(tree: Path, env: dict, name: str, quick: bool, raw: Path, tag: str) -> dict:
    """One ``benchmarks/run.py --only name`` in ``tree``; returns that benchmark's result and the wall time [s]."""
    with tempfile.TemporaryDirectory(prefix="compare_run_") as tmp:
        cmd = [sys.executable, "benchmarks/run.py", "--only", name, "--out", tmp] + (["--quick"] if quick else [])
        t0 = time.perf_counter()
        out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        report_file = Path(tmp) / "report.json"
        report = json.loads(report_file.read_text()) if report_file.exists() else {}
    (raw / f"{tag}.json").write_text(json.dumps(report, indent=1))
    res = report.get("benchmarks", {}).get(name) or {"error": f"no report (rc {out.returncode}):\n{out.stderr[-3000:]}"}
    print(f"[compare] {tag}: {wall:.0f} s{' ERROR' if 'error' in res else ''}", flush=True)
    return {"result": res, "wall_s": wall}


def _label(runs: list[dict], i: int) -> dict:
    """Identifying fields of row ``i``: strings/bools, and integers constant across every run of both trees."""
    rows = [r["rows"][i] for r in runs]
    keys = dict.fromkeys(k for r in rows for k in r)
    return {k: rows[0].get(k) for k in keys
            if all(not isinstance(r.get(k), float) for r in rows) and len({json.dumps(r.get(k)) for r in rows}) == 1}


def _spread(vals: list[float]) -> float:
    m = statistics.median(vals)
    return (max(vals) - min(vals)) / abs(m) if m else 0.0


def compare_rows(base_runs: list[dict], cur_runs: list[dict]) -> list[dict]:
    n = {len(r["rows"]) for r in base_runs + cur_runs}
    if len(n) != 1:
        raise ValueError(f"row counts differ between runs: {sorted(n)}")
    out = []
    for i in range(n.pop()):
        label = _label(base_runs + cur_runs, i)
        labels = {json.dumps({k: v for k, v in r["rows"][i].items() if isinstance(v, str)}) for r in base_runs + cur_runs}
        fields, worst = {}, "within noise"
        for k, v in base_runs[0]["rows"][i].items():
            if k in label or isinstance(v, (str, bool)) or not isinstance(v, (int, float)):
                continue
            b = [float(r["rows"][i][k]) for r in base_runs if isinstance(r["rows"][i].get(k), (int, float))]
            c = [float(r["rows"][i][k]) for r in cur_runs if isinstance(r["rows"][i].get(k), (int, float))]
            if not b or not c:
                continue
            d = direction(k)
            bm, cm = statistics.median(b), statistics.median(c)
            ratio = cm / bm if bm else float("nan")
            noise = max(_spread(b), _spread(c))
            f = {"base": b, "current": c, "base_median": bm, "current_median": cm, "ratio": ratio, "noise": noise,
                 "direction": {1: "higher is better", -1: "lower is better", 0: "not judged"}[d]}
            if d and bm and cm:
                worse = (ratio - 1.0) if d < 0 else (1.0 / ratio - 1.0)  # relative loss of the current tree
                f["worse_by"] = worse
                f["verdict"] = "slower" if worse > noise else "faster" if -worse > noise else "within noise"
                if f["verdict"] == "slower":
                    worst = "slower"
            fields[k] = f
        out.append({"label": label, "labels_agree": len(labels) == 1, "fields": fields,
                    "verdict": "SLOWER" if worst == "slower" else "within noise or faster"})
    return out


def to_markdown(res: dict) -> str:
    lines = ["# Benchmark comparison: base vs current", "",
             f"- base: `{res['base']}` = {res['base_commit'][:9]} ({res['base_tree']})",
             f"- current: {res['current_commit'][:9]}{' + uncommitted changes' if res['current_dirty'] else ''} ({res['current_tree']})",
             f"- command: `{res['command']}`",
             f"- {res['rounds']} rounds, alternating base/current per benchmark; quick (run.py --quick) for: {', '.join(res['quick']) or 'none'}; torch threads capped at "
             f"{res['threads'] or 'benchmark default'}; wall {res['wall_s']:.0f} s; {res['generated']}",
             "- ratio = current / base of the medians over rounds; noise = larger (max - min) / median over the rounds of "
             "one tree; worse = relative loss of current (direction from the field name).", ""]
    for name, b in res["benchmarks"].items():
        lines += [f"## {name}", ""]
        if "error" in b:
            lines += ["```", b["error"][-3000:], "```", ""]
            continue
        lines += ["| row | field | base | current | ratio | worse | noise | verdict |", "|---|---|---|---|---|---|---|---|"]
        for r in b["rows"]:
            lab = ", ".join(f"{k}={v}" for k, v in r["label"].items()) or "-"
            for k, f in r["fields"].items():
                if "verdict" not in f:
                    continue
                lines.append(f"| {lab} | {k} | {f['base_median']:.4g} | {f['current_median']:.4g} | {f['ratio']:.3f} | "
                             f"{100 * f['worse_by']:+.1f}% | {100 * f['noise']:.1f}% | {f['verdict']} |")
        lines += ["", "Row verdicts:", ""]
        lines += [f"- {', '.join(f'{k}={v}' for k, v in r['label'].items()) or '-'}: **{r['verdict']}**"
                  + ("" if r["labels_agree"] else " (row labels differ between runs!)") for r in b["rows"]]
        if b["notes_base"] != b["notes_current"]:
            lines += ["", "Notes differ (first round):", ""] + [f"- base: {n}" for n in b["notes_base"]] + \
                     [f"- current: {n}" for n in b["notes_current"]]
        lines += ["", "Run wall times [s]: base " + ", ".join(f"{t:.0f}" for t in b["wall_s_base"])
                  + "; current " + ", ".join(f"{t:.0f}" for t in b["wall_s_current"]), ""]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True, help="git revision to compare against (e.g. a commit before a refactor)")
    ap.add_argument("--base-tree", help="reuse this worktree, checked out at --base, instead of making one")
    ap.add_argument("--only", nargs="+", required=True, help="benchmark names (benchmarks/bench_<name>.py)")
    ap.add_argument("--rounds", type=int, default=2, help="runs per tree and benchmark (>= 2 for a noise estimate)")
    ap.add_argument("--quick", nargs="*", metavar="NAME",
                    help="pass --quick to run.py: alone for every benchmark, with names for those only")
    ap.add_argument("--threads", type=int, default=1, help="cap on torch threads in the children; 0 = no cap")
    ap.add_argument("--share", nargs="*", default=["data/generated", "data/tokens"],
                    help="ignored paths symlinked from the current tree into the base tree when missing there")
    ap.add_argument("--out", default=str(CURRENT / "benchmarks" / "reports" / "compare"))
    args = ap.parse_args(argv)
    if args.rounds < 1:
        ap.error("--rounds must be >= 1")
    quick = set(args.only) if args.quick == [] else set(args.quick or [])
    if quick - set(args.only):
        ap.error(f"--quick names {sorted(quick - set(args.only))} are not in --only")
    t0 = time.time()
    base_tree, created = make_base_tree(args.base, args.base_tree, args.share)
    out = Path(args.out)
    (out / "raw").mkdir(parents=True, exist_ok=True)
    site = Path(tempfile.mkdtemp(prefix="compare_site_")) if args.threads > 0 else None
    try:
        if site:
            (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
        trees = {"base": base_tree, "current": CURRENT}
        envs = {k: child_env(t, site, args.threads) for k, t in trees.items()}
        for k, t in trees.items():
            print(f"[compare] {k}: {t} imports {check_tree(t, envs[k], args.threads)}", flush=True)
        runs = {n: {"base": [], "current": []} for n in args.only}
        for rnd in range(args.rounds):
            for n in args.only:
                for k in ("base", "current"):
                    runs[n][k].append(run_once(trees[k], envs[k], n, n in quick, out / "raw", f"{n}_{k}_r{rnd}"))
        res = {"generated": time.strftime("%Y-%m-%d %H:%M:%S"), "command": " ".join(["python", *sys.argv]),
               "base": args.base, "base_commit": git("rev-parse", "HEAD", cwd=base_tree), "base_tree": str(base_tree),
               "current_commit": git("rev-parse", "HEAD"), "current_dirty": bool(git("status", "--porcelain", "--untracked-files=no", "--", ".", ":!benchmarks/reports")),
               "current_tree": str(CURRENT), "rounds": args.rounds, "quick": sorted(quick), "threads": args.threads,
               "load_average_end": os.getloadavg(), "benchmarks": {}}
        for n, r in runs.items():
            b, c = [x["result"] for x in r["base"]], [x["result"] for x in r["current"]]
            entry = {"wall_s_base": [x["wall_s"] for x in r["base"]], "wall_s_current": [x["wall_s"] for x in r["current"]],
                     "notes_base": b[0].get("notes", []), "notes_current": c[0].get("notes", [])}
            errs = [x["error"] for x in b + c if "error" in x]
            try:
                entry.update({"error": errs[0]} if errs else {"rows": compare_rows(b, c)})
            except ValueError as exc:
                entry["error"] = str(exc)
            res["benchmarks"][n] = entry
        res["wall_s"] = time.time() - t0
        (out / "compare.json").write_text(json.dumps(res, indent=1))
        (out / "compare.md").write_text(to_markdown(res))
        print(f"[compare] wrote {out / 'compare.json'} and {out / 'compare.md'}")
        return 1 if any("error" in b or any(r["verdict"] == "SLOWER" for r in b["rows"]) for b in res["benchmarks"].values()) else 0
    finally:
        if site:
            shutil.rmtree(site, ignore_errors=True)
        if created:
            git("worktree", "remove", "--force", str(base_tree))


if __name__ == "__main__":
    sys.exit(main())
