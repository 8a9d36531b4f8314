"""SUMO reference generation: throughput (vehicle states/s) and peak memory, 1 vs 2 worker processes on the
same jobs, and the recording overhead (plain SUMO stepping vs stepping + reading every vehicle and the TL
states, vs the whole job including windowing and validation).

Run alone: ``python benchmarks/run.py --only generation [--quick]``.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from r1sim_sumo._memory import peak_rss_mb


def _jobs(quick: bool):
    from r1sim_sumo.data.sumo_reference import SumoGenConfig
    from r1sim_sumo.resources import list_networks

    nets = [n for n in ("motorway_merge", "urban_intersection", "lane_drop", "urban_grid") if n in list_networks()]
    dur, warm, n_jobs = (30.0, 10.0, 2) if quick else (180.0, 60.0, 4)
    return [SumoGenConfig(network=nets[i % len(nets)], seed=i, duration_s=dur, warmup_s=warm) for i in range(n_jobs)]


def _pool_row(jobs, workers: int) -> dict:
    from r1sim_sumo.data.dataset import execute_jobs

    with tempfile.TemporaryDirectory(prefix="bench_gen_") as tmp:
        t0 = time.perf_counter()
        res = execute_jobs(jobs, Path(tmp), workers=workers, progress=False)
        wall = time.perf_counter() - t0
        shard_mb = sum(f.stat().st_size for f in Path(tmp).rglob("*.npz")) / 2**20
    vs = sum(r.vehicle_states for r in res)
    wins = sum(r.num_scenarios for r in res)
    return {
        "case": f"{workers} worker{'s' if workers > 1 else ''}", "jobs": len(jobs), "wall_s": wall,
        "vehicle_states": vs, "vehicle_states_per_s": vs / wall, "windows": wins, "windows_per_s": wins / wall,
        "peak_rss_mb_per_worker": max(r.worker_peak_rss_mb for r in res), "shards_mb": shard_mb,
    }


def _overhead_rows(config) -> list[dict]:
    """Same job three ways in this process: plain stepping, stepping + recording, the whole job.

    An untimed short run first loads libsumo and the map code so imports are not counted.
    """
    import dataclasses

    from r1sim_sumo.data.sumo_reference import RunStats, iter_sumo_scenarios

    for _ in iter_sumo_scenarios(dataclasses.replace(config, duration_s=9.1, warmup_s=0.0)):
        pass
    rows = []
    for case, record, windows in (("plain SUMO stepping", False, False), ("stepping + recording", True, False),
                                  ("whole job (+ windows, validation)", True, True)):
        st = RunStats()
        t0 = time.perf_counter()
        it = iter_sumo_scenarios(config, stats=st, record=record)
        n = 0
        for sc in it:  # the simulation runs entirely before the first window is yielded
            sc.validate()
            n += 1
            if not windows:
                it.close()
                break
        wall = time.perf_counter() - t0
        rows.append({"case": case, "steps": st.steps, "vehicle_states": st.vehicle_states,
                     "vehicle_states_per_s": st.vehicle_states / wall, "loop_s": st.step_s + st.record_s,
                     "wall_s": wall, "windows": n, "steps_per_s": st.steps / wall,
                     "peak_rss_mb": peak_rss_mb()})
    base = rows[0]["loop_s"]
    for r in rows:
        r["loop_ratio_vs_plain"] = r["loop_s"] / base
    return rows


def run(quick: bool) -> dict:
    jobs = _jobs(quick)
    one = _pool_row(jobs, 1)
    two = _pool_row(jobs, 2)
    for r in (one, two):
        r["speedup_vs_1_worker"] = one["wall_s"] / r["wall_s"]
    over = _overhead_rows(jobs[0])
    return {
        "title": "SUMO reference generation (throughput, memory, recording overhead)",
        "rows": [one, two, *over],
        "notes": [
            f"jobs: {[(j.network, j.seed, j.duration_s) for j in jobs]}; warm-up {jobs[0].warmup_s} s; 0.1 s steps",
            "worker rows: each job in its own spawned process (libsumo = one simulation per process); wall includes "
            "process start, recording, windowing, validation and compressed shard writing",
            "peak_rss_mb_per_worker = max peak RSS (VmHWM) of the worker processes; overhead rows run in this process",
            "loop_ratio_vs_plain = (simulationStep + state/TL reads) time over plain simulationStep time",
            "the machine is shared: compare rows of this run only",
        ],
    }
