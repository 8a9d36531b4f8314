"""``python -m r1sim_sumo.reliability report --out docs/reliability/``: run every hostile-input case and the fault
injections, add the soak figures when a soak summary exists, write ``report.md`` and ``report.json``."""

from __future__ import annotations

import json
import platform
import tempfile
import time
from dataclasses import asdict
from pathlib import Path


def _md_cell(s: str, limit: int = 400) -> str:
    s = " ".join(str(s).split())
    s = s if len(s) <= limit else s[: limit - 3] + "..."
    return s.replace("|", "\\|")


def _short_paths(msg: str, tmp: str) -> str:
    return msg.replace(tmp + "/", "<tmp>/").replace(tmp, "<tmp>")


def build_report(out: str | Path, faults_to_run: tuple[str, ...] = ("nan", "sumo", "pretrain", "finetune"),
                 soak_dir: str | Path | None = None) -> dict:
    from r1sim_sumo.reliability import faults
    from r1sim_sumo.reliability.cases import cases, run_case

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    results: dict = {"cases": [], "faults": {}}
    with tempfile.TemporaryDirectory() as d:
        for c in cases():
            o = run_case(c, Path(d) / c.name)
            o.message = _short_paths(o.message, d)
            results["cases"].append(asdict(o))
        runners = {
            "nan": ("NaN / +inf / empty logit rows in every sampler", lambda: faults.nan_logits_guard()),
            "sumo": ("SUMO process SIGKILLed during `r1sim simulate --traci`", lambda: faults.sumo_crash_during_simulate(Path(d) / "sumo")),
            "pretrain": ("`r1sim pretrain` subprocess SIGKILLed twice at random moments, then --resume",
                         lambda: faults.kill_and_resume("pretrain", Path(d) / "pt", steps=16, kills=2, seed=0)),
            "finetune": ("`r1sim finetune` subprocess SIGKILLed twice at random moments, then --resume",
                         lambda: faults.kill_and_resume("finetune", Path(d) / "ft", steps=8, kills=2, seed=0)),
        }
        for key in faults_to_run:
            title, fn = runners[key]
            ts = time.perf_counter()
            try:
                res = fn()
            except Exception as exc:  # noqa: BLE001 - a failing injection is reported, not hidden
                res = {"passed": False, "error": f"{type(exc).__name__}: {exc}"}
            res = json.loads(_short_paths(json.dumps(res, default=str), d))
            res["title"], res["seconds"] = title, round(time.perf_counter() - ts, 1)
            results["faults"][key] = res
    soak_dir = Path(soak_dir) if soak_dir else out / "soak"
    if (soak_dir / "soak.json").exists():
        results["soak"] = json.loads((soak_dir / "soak.json").read_text())
        results["soak"]["dir"] = str(soak_dir)
    results["wall_s"] = round(time.perf_counter() - t0, 1)
    results["machine"] = f"{platform.processor() or platform.machine()}, python {platform.python_version()}"
    (out / "report.json").write_text(json.dumps(results, indent=1, default=str))
    (out / "report.md").write_text(render_markdown(results, out))
    return results


def render_markdown(r: dict, out: Path) -> str:
    cases = r["cases"]
    n_ok = sum(c["passed"] for c in cases)
    L = ["# Reliability report", "",
         "Produced by `python -m r1sim_sumo.reliability report --out docs/reliability/` "
         f"({r['wall_s']} s on {r['machine']}). Hostile inputs come from one table "
         "(`r1sim_sumo/reliability/cases.py`), also run by `tests/test_hostile_inputs.py`.", "",
         f"## Hostile inputs: {n_ok} / {len(cases)} handled as specified", "",
         "Outcome `refused`: the owner module raised the error shown (it names the file and the field); "
         "`cleaned up`: the documented clean-up ran and was checked. Temporary folders are shown as `<tmp>`.", "",
         "| case | category | input | outcome | message |", "|---|---|---|---|---|"]
    for c in cases:
        L.append(f"| {c['name']} | {c['category']} | {_md_cell(c['description'])} | "
                 f"{c['outcome'] if c['passed'] else '**FAILED**'} | {_md_cell(c['message'])} |")
    L += ["", "## Fault injection", ""]
    for key, f in r["faults"].items():
        L.append(f"### {f['title']}: {'passed' if f.get('passed') else '**FAILED**'} ({f['seconds']} s)")
        L.append("")
        if "error" in f:
            L.append(f"error: `{_md_cell(f['error'])}`")
        elif key == "nan":
            L += ["| sampler | tokens (rows: NaN, all -inf, +inf, all NaN, normal) | finite logp/entropy | warned |", "|---|---|---|---|"]
            L += [f"| {s} | {v['tokens']} | {v['finite_logp_entropy']} | {v['warned']} |" for s, v in f["samplers"].items()]
        elif key == "sumo":
            L += [f"- exit code {f['returncode']}, traceback printed: {f['traceback']}",
                  f"- error line: `{_md_cell(f['error_line'])}`",
                  f"- partial summary: {f['partial_sim_s']:.1f} simulated s, {f['departed']} departed, balanced: {f['balanced']}"]
        else:
            kills = "; ".join(f"killed={k['killed']} after {k['after_s']} s, state {k['state']}" for k in f["kills"])
            L += [f"- {f['steps']} {'steps' if key == 'pretrain' else 'iterations'}; uninterrupted run {f['reference_run_s']} s",
                  f"- kills: {kills}",
                  f"- final weights identical to the uninterrupted run: {f['identical_weights']}; log rows identical: "
                  f"{f['identical_log']}; state folder never corrupt: {f['state_never_corrupt']}"]
        L.append("")
    L += ["## Soak", ""]
    s = r.get("soak")
    if s:
        png = Path(s["dir"]) / "soak_rss.png"
        rel = png.relative_to(out) if png.is_relative_to(out) else png
        L += [f"`scripts/soak.py --sim-seconds {s['sim_seconds']:g}` on `{s['network']}` with {s['checkpoint']}: "
              f"{'passed' if s['passed'] else '**FAILED**'}", "",
              "| figure | value |", "|---|---|",
              f"| simulated / wall time | {s['sim_seconds']:.0f} s / {s['wall_s']:.0f} s ({s['sim_s_per_wall_s']} sim-s per s) |",
              f"| RSS start / end / max | {s['rss_start_mb']:.0f} / {s['rss_end_mb']:.0f} / {s['rss_max_mb']:.0f} MB |",
              f"| RSS slope, second half | {s['rss_slope_mb_per_sim_h']:+.1f} MB per simulated hour |",
              *([f"| live RSS (after malloc_trim) start / end | {s['rss_live_start_mb']:.0f} / {s['rss_live_end_mb']:.0f} MB |",
                 f"| live RSS vs time at a fixed population (leak) | {s['rss_leak_mb_per_sim_h']:+.1f} MB per simulated hour "
                 f"(limit 10; memory flat: {s.get('memory_flat')}) |",
                 f"| vehicles capped at (SUMO --max-num-vehicles) | {s.get('max_running')} |",
                 f"| live Python objects (sys.getallocatedblocks) start / end | {s['py_blocks_start']} / {s['py_blocks_end']} |"]
                if "rss_live_start_mb" in s else []),
              f"| departed / arrived / removed / running | {s['departed']} / {s['arrived']} / {s['removed']} / {s['running']} |",
              f"| balanced at every sample; = SUMO's departed | {s['balanced_every_sample']}; {s['matches_sumo_departed']} |",
              f"| stuck controlled vehicles | {len(s['stuck_vehicles'])} {s['stuck_vehicles'][:10]} |",
              f"| policy errors; collision onsets (any) | {s['policy_errors']}; {s['collisions_any']} |",
              f"| hand-backs | {s['handbacks']} |", "", f"![RSS over time]({rel})", ""]
    else:
        L += ["No soak summary found (run `python scripts/soak.py --sim-seconds 3600 --out docs/reliability/soak`, "
              "then this report again).", ""]
    return "\n".join(L) + "\n"
