"""Full-demand-horizon runs of the drop-in controller next to SUMO-native control on the same demand.

For every scenario (the 5 bundled networks over their whole 900 s demand, plus sample scenarios shipped inside
the eclipse-sumo wheel that this project did not write), ``r1sim simulate`` runs twice with the same seed:
``--native`` (SUMO's own car-following / lane-change models drive everything) and with the policy driving every
vehicle it can take over (``--control all``). Each run writes its summary JSON; this script collects them into
``<out>/report.md`` + ``report.json``: collisions per 1000 vehicle-km (SUMO reports and SAT box overlaps, each
pair-event once), the share of vehicles that completed their route among those that left the simulation
(arrived / (arrived + removed with a reason)), teleports, hand-backs, mean speed and speed (sim s per wall s).

Run::

    python examples/full_horizon_runs.py --out docs/simulate            # 4 modes x 8 scenarios: hours on 2 CPU cores
    python examples/full_horizon_runs.py --scenarios motorway_merge --end 120 --out /tmp/fh   # quick look
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from pathlib import Path

BUNDLED = ["motorway_merge", "lane_drop", "urban_intersection", "roundabout", "urban_grid"]
SUMO_SAMPLES = {"sumo-game-ramp": "tools/game/ramp.sumocfg", "sumo-game-cross": "tools/game/cross.sumocfg",
                "sumo-game-grid6": "tools/game/grid6.sumocfg"}


def scenario_sumocfg(name: str) -> Path:
    """The ``.sumocfg`` of a scenario name: a bundled network or an eclipse-sumo sample (:data:`SUMO_SAMPLES`). Call it
    before ``libsumo`` is imported in the process: importing it sets ``SUMO_HOME`` to its own data folder."""
    if name in SUMO_SAMPLES:
        from r1sim_sumo._sumo_env import ensure_sumo_home

        return Path(ensure_sumo_home()) / SUMO_SAMPLES[name]
    from r1sim_sumo.resources import network_files

    return Path(network_files(name)["sumocfg"])


def _horizon(sumocfg: Path) -> float:
    """The ``<end value=...>`` of a .sumocfg [s] (900 s when it has none)."""
    import xml.etree.ElementTree as ET

    end = ET.parse(sumocfg).getroot().find("./time/end")
    return float(end.get("value")) if end is not None else 900.0


MODES = ("native", "commands", "position", "position-raw")  # position-raw: position drive without the safety layer


def run_one(name: str, sumocfg: Path, mode: str, end_s: float, out: Path, checkpoint: str | None, seed: int,
            sampler: str | None = None, lane_changes: str = "policy+overtaking", guidance: float = 0.0,
            merge_cooperation: str = "on", safety: str = "krauss", brake_floor: str = "off",
            lane_change_gate: str = "sumo", replan_every_s: float = 0.5, junction_floor: float = 0.0,
            free_road_quantile: float | None = None, free_road_headway: float | None = None,
            speed_carry: str | None = None, junction_turns: str = "sumo", junction_crossings: str | None = None) -> dict:
    js = out / f"{name}_{mode}.json"
    cmd = [sys.executable, "-m", "r1sim_sumo.cli", "simulate", "--sumocfg", str(sumocfg), "--end", f"{end_s:g}",
           "--seed", str(seed), "--json", str(js), "--no-progress"]
    cmd += ["--plot", str(out / f"{name}_{mode}.time_space.png")]
    if mode == "native":
        cmd.append("--native")
    else:
        raw = mode == "position-raw"
        cmd += ["--drive", "commands" if mode == "commands" else "position", "--safety", "none" if raw else safety,
                "--standstill-handoff", "0" if raw else "5"]
        if checkpoint:
            cmd += ["--checkpoint", checkpoint]
        if sampler is not None:  # None: the drive's own default (r1sim simulate --sampler)
            cmd += ["--sampler", sampler]
        cmd += ["--lane-changes", lane_changes, "--guidance", f"{guidance:g}",
                "--merge-cooperation", merge_cooperation, "--brake-floor", brake_floor, "--lane-change-gate", lane_change_gate,
                "--replan-every", f"{replan_every_s:g}", "--junction-floor", f"{junction_floor:g}",
                "--junction-turns", junction_turns]
        if junction_crossings is not None:  # None: the drive's own (r1sim simulate --junction-crossings)
            cmd += ["--junction-crossings", junction_crossings]
        if speed_carry is not None:  # None: the drive's own (r1sim simulate --speed-carry)
            cmd += ["--speed-carry", speed_carry]
        if free_road_quantile is not None and mode != "commands":  # the position drives' free-road decoding
            cmd += ["--free-road-quantile", f"{free_road_quantile:g}"]
            if free_road_headway is not None:
                cmd += ["--free-road-headway", f"{free_road_headway:g}"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode == 3 and js.exists():  # SUMO died mid-run: keep the partial summary (it says so) and go on
        print(f"{name} {mode}: SUMO stopped early, partial summary kept:\n{r.stderr[-1000:]}", file=sys.stderr)
    elif r.returncode != 0:
        raise RuntimeError(f"{name} {mode} failed (exit {r.returncode}):\n{r.stderr[-3000:]}")
    s = json.loads(js.read_text())
    s["mode"] = mode
    js.write_text(json.dumps(s, indent=2, default=str))
    return s


def completed_share(s: dict) -> float | None:
    left = s["arrived"] + s["removed"]
    return s["arrived"] / left if left else None


def row(name: str, s: dict) -> dict:
    return {
        "scenario": name, "mode": s["mode"], "safety_slowdowns": s.get("safety_slowdowns", 0),
        "policy_vkm_share": s.get("policy_vkm_share"), "retakes": s.get("retakes", 0), "simulated_s": round(s["sim_seconds"]), "departed": s["departed"],
        "arrived": s["arrived"], "removed": s["removed"], "controlled": s["controlled_total"],
        "completed_route_share": completed_share(s), "collisions_per_1000_vkm": s["collisions_per_1000_vkm"],
        "collisions_sumo": s["collisions_sumo"], "collisions_boxes": s.get("collisions_sat"),
        "collisions_either": s["collisions_any"], "teleports": s["teleports"],
        "handbacks": sum(s["handbacks"].values()) if isinstance(s["handbacks"], dict) else s["handbacks"],
        "mean_speed_mps": s["mean_speed_mps"], "free_road_speed_share": s.get("free_road_speed_share"), "vkm": s["vkm_all"],
        "waiting_to_insert": s.get("waiting_to_insert"), "waiting_to_insert_max": s.get("waiting_to_insert_max"),
        "standing_share": s.get("standing_share"), "longest_standstill_s": s.get("longest_standstill_s"),
        "stood_over_60s": s.get("stood_over_60s"), "queue_growth_s": s.get("longest_queue_growth_s"),
        "queue_head": s.get("longest_queue_head"), "queues_over_60s": s.get("queues_grown_over_60s"),
        "speed_capped_share": s.get("speed_capped_share"),
        "lane_change_refused": s.get("lane_change_refused"), "warnings": s.get("warnings"), "sim_s_per_wall_s": s["sim_s_per_wall_s"],
        "balanced": s["balanced"], "sumo_crashed": s.get("sumo_crashed"),
    }


def markdown(rows: list[dict]) -> str:
    """One table row per (scenario, mode); arrivals and mean speed also as a share of the native run's."""
    cols = ["scenario", "mode", "simulated_s", "departed", "waiting_to_insert", "arrived", "arrived_vs_native",
            "removed", "mean_speed_mps", "speed_vs_native", "free_road_speed_share", "collisions_sumo", "collisions_boxes",
            "collisions_per_1000_vkm", "stood_over_60s", "longest_standstill_s", "queue_growth_s",
            "queues_over_60s", "speed_capped_share",
            "lane_change_refused", "handbacks", "policy_vkm_share", "teleports", "sim_s_per_wall_s"]
    native = {r["scenario"]: r for r in rows if r["mode"] == "native"}

    def fmt(v):
        if v is None:
            return "n/a"
        return f"{v:.3f}" if isinstance(v, float) else str(v)

    def cell(r, c):
        n = native.get(r["scenario"])
        if c == "arrived_vs_native":
            return fmt(r["arrived"] / n["arrived"]) if n and n["arrived"] else "n/a"
        if c == "speed_vs_native":
            return fmt(r["mean_speed_mps"] / n["mean_speed_mps"]) if n and n["mean_speed_mps"] else "n/a"
        return fmt(r.get(c))

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(cell(r, c) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def write_report(out: Path, rows: list[dict], header: str) -> None:
    (out / "report.json").write_text(json.dumps(rows, indent=1))
    text = ["# Full-horizon runs: policy vs SUMO-native on the same demand", "", header, "", markdown(rows), "",
            "completed_route_share = arrived / (arrived + removed with a reason) among vehicles that left the simulation;",
            "collisions per 1000 vehicle-km count each colliding pair-event once (SUMO report or SAT box overlap; a pair",
            "touching again within 3 s is the same event); sumo-game-* are sample scenarios shipped in the eclipse-sumo",
            "wheel (tools/game), not written by this project. collisions_sumo / collisions_boxes: events reported by",
            "SUMO / box overlaps of any two vehicles (native runs counted the same way). waiting_to_insert: vehicles whose",
            "departure time has come but that SUMO could not insert at the end (blocked insertions). stood_over_60s:",
            "vehicles that stood still for more than 60 s in one go. queue_growth_s: the longest a queue of standing",
            "vehicles (lanes joined along their connections, or the vehicles waiting to insert) grew without clearing;",
            "queues_over_60s: queues that grew for more than 60 s (`r1sim_sumo/sim/queue_growth.py`).",
            "free_road_speed_share: speed / desired speed (lane limit x speedFactor, capped by the type's maxSpeed) of the",
            "vehicles with no leader, signal, turn or yield within 100 m, sampled every 0.5 s: every vehicle in native runs,",
            "the policy's in policy runs (`r1sim_sumo/sim/free_road_speed.py`); n/a in rows run before it existed. Time-space",
            "pictures: `<scenario>_time_space.png` (native first, then the policy modes, along the route native drove most).", ""]
    crashed = [f"{r['scenario']} {r['mode']} ({r['sumo_crashed']})" for r in rows if r.get("sumo_crashed")]
    if crashed:
        text += ["Runs that ended early (SUMO stopped; the row covers the part that ran): " + "; ".join(crashed) + ".", ""]
    text += [f"![{n}]({n}_time_space.png)" for n in dict.fromkeys(r["scenario"] for r in rows)
             if (out / f"{n}_time_space.png").exists()]
    (out / "report.md").write_text("\n".join(text) + "\n")


def report_from_existing(out: Path, names: list[str], header: str) -> list[dict]:
    """Collect the summaries already written in ``out`` (e.g. after an interrupted run) into the report."""
    rows = [row(n, json.loads((out / f"{n}_{m}.json").read_text())) for n in names for m in MODES
            if (out / f"{n}_{m}.json").exists()]
    write_report(out, rows, header)
    return rows


def side_by_side(out: Path, name: str, modes) -> Path | None:
    """``<out>/<name>_time_space.png``: the time-space pictures of every mode of one scenario next to each other,
    all along the route the native run's vehicles drove most."""
    from r1sim_sumo.sim.time_space import plot_side_by_side, reproject, samples_path

    series = [json.loads(f.read_text()) for m in modes if (f := samples_path(out / f"{name}_{m}.time_space.png")).exists()]
    if not series:
        return None
    route = series[0]["route"]
    png = out / f"{name}_time_space.png"
    plot_side_by_side([reproject(s, route) for s in series], png)
    return png


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=BUNDLED + list(SUMO_SAMPLES),
                    help="bundled network names and/or eclipse-sumo samples (sumo-game-ramp, sumo-game-cross, sumo-game-grid6)")
    ap.add_argument("--checkpoint", default=None, help="policy checkpoint (default: the shipped one)")
    ap.add_argument("--end", type=float, default=None, help="simulated seconds (default: each scenario's own horizon)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sampler", default=None, help="the policy's token sampler (r1sim simulate --sampler; "
                    "default: each drive's own, commands quantile:0.7,0.1, position median:0.1)")
    ap.add_argument("--lane-changes", default="policy+overtaking", choices=["policy", "policy+overtaking"],
                    help="commands drive's lane changes (r1sim simulate --lane-changes)")
    ap.add_argument("--guidance", type=float, default=0.0, help="desired-speed guidance weight (r1sim simulate --guidance)")
    ap.add_argument("--merge-cooperation", default="on", choices=["on", "off"],
                    help="commands drive's yields to merging vehicles (r1sim simulate --merge-cooperation)")
    ap.add_argument("--brake-floor", default="off", choices=["off", "open-road"],
                    help="position drive's braking floor on the open road (r1sim simulate --brake-floor)")
    ap.add_argument("--lane-change-gate", default="sumo", choices=["sumo", "off"],
                    help="position drive's lane-change gate (r1sim simulate --lane-change-gate)")
    ap.add_argument("--junction-turns", default="sumo", choices=["sumo", "policy"],
                    help="position drive: who drives a vehicle through a junction where its plan leaves its route or its "
                         "route turns off the major road "
                         "(r1sim simulate --junction-turns)")
    ap.add_argument("--junction-crossings", default=None, choices=["sumo", "policy"],
                    help="who drives a vehicle (position) or its speed (commands) through a junction where it may have "
                         "to stop (r1sim simulate --junction-crossings; default: each drive's own, sumo for both)")
    ap.add_argument("--replan-every", type=float, default=0.5,
                    help="time between the policy's decisions [s] (r1sim simulate --replan-every)")
    ap.add_argument("--free-road-quantile", type=float, default=None,
                    help="position drives: decode a vehicle with a free road ahead at this travel quantile (r1sim "
                         "simulate --free-road-quantile; default off)")
    ap.add_argument("--free-road-headway", type=float, default=None,
                    help="with --free-road-quantile: a leader this headway [s] ahead or more, not slower, leaves the "
                         "road free (r1sim simulate --free-road-headway; default: any leader within 100 m does not)")
    ap.add_argument("--speed-carry", default=None, choices=["off", "gains", "free", "both"],
                    help="policy drives: read each token's speed change against the last 0.5 s driven (r1sim "
                         "simulate --speed-carry; default: each drive's own, gains)")
    ap.add_argument("--junction-floor", type=float, default=0.0,
                    help="commands drive's least speed command inside a junction [m/s] (r1sim simulate --junction-floor; 0: off, the default)")
    ap.add_argument("--safety", default="krauss", choices=["krauss", "none"],
                    help="safety layer of the commands and position modes (r1sim simulate --safety; position-raw is "
                         "always none): none runs the commands drive on SUMO's own checks alone")
    ap.add_argument("--out", default="docs/simulate")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES,
                    help="native (SUMO drives), commands (--drive commands), position (--drive position with the "
                         "safety layer), position-raw (--drive position --safety none)")
    ap.add_argument("--reuse", nargs="*", default=[], choices=MODES,
                    help="modes whose summaries already in --out are reused instead of re-run (e.g. native)")
    a = ap.parse_args(argv)
    if a.replan_every != 0.5 and any(m.startswith("position") for m in a.modes):
        ap.error(f"--replan-every {a.replan_every:g} is for the commands drive only (r1sim simulate refuses it with "
                 "--drive position); run the position modes separately with the default 0.5")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in a.scenarios:
        cfg = scenario_sumocfg(name)
        end_s = a.end or _horizon(cfg)
        for mode in a.modes:
            js = out / f"{name}_{mode}.json"
            if mode in a.reuse and js.exists():
                s = {"mode": mode, **json.loads(js.read_text())}
            else:
                s = run_one(name, cfg, mode, end_s, out, a.checkpoint, a.seed, a.sampler, a.lane_changes, a.guidance,
                                a.merge_cooperation, a.safety, a.brake_floor, a.lane_change_gate, a.replan_every,
                                a.junction_floor, a.free_road_quantile, a.free_road_headway, a.speed_carry,
                                a.junction_turns, a.junction_crossings)
            rows.append(row(name, s))
            r = rows[-1]
            print(f"{name:22s} {mode:7s} {end_s:5.0f} s  completed {r['completed_route_share']}  "
                  f"coll/1000vkm {r['collisions_per_1000_vkm']:.2f}  {r['sim_s_per_wall_s']:.1f} sim-s/s", flush=True)
        side_by_side(out, name, a.modes)
    given = " ".join(shlex.quote(x) for x in (sys.argv[1:] if argv is None else argv))  # exactly what was run
    from r1sim_sumo.sim.sumo_controller import DROP_IN_SAMPLERS

    carry_default = "each drive's own (gains; off without the safety layer)"
    sampler_default = "each drive's own (" + ", ".join(f"{d} {DROP_IN_SAMPLERS[d]}" for d in ("commands", "position")) + ")"
    header = (f"Command: `python examples/full_horizon_runs.py {given}`"
              + f"; checkpoint: {a.checkpoint or 'shipped r1sim-nano'}; seed {a.seed}; sampler {a.sampler or sampler_default}; lane changes {a.lane_changes}; guidance {a.guidance:g}; merge cooperation {a.merge_cooperation}; brake floor {a.brake_floor}; lane-change gate {a.lane_change_gate}; junction turns {a.junction_turns}, junction crossings {a.junction_crossings or 'each drive default'}; decisions every {a.replan_every:g} s; junction floor {a.junction_floor:g} m/s (commands); free-road quantile {a.free_road_quantile if a.free_road_quantile is not None else 'off'}{'' if a.free_road_headway is None else f' with leaders from {a.free_road_headway:g} s'} (position); speed carry {a.speed_carry or carry_default}; safety layer {a.safety} (position-raw: none); `--control all`.")
    write_report(out, rows, header)
    print(f"report written to {out / 'report.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
