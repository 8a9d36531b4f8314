"""Where a drop-in decision's time goes, and whether two revisions drive identically.

One SUMO run on a scene of :mod:`bench_sumo_controller` (``N`` cars kept on motorway_merge or on the city grid, the shipped policy,
hand-offs off): after a 2 s warm-up, 15 simulated s are timed; prints ms per policy decision, simulated s per wall s,
agents per decision, a hash of every vehicle's final x position (equal hashes = the same plans were driven) and, with
``--profile``, the cProfile table of the timed part (by own time).

    python benchmarks/profile_sumo_decision.py --vehicles 100 --drive position [--scene merge|grid] [--threads 1] [--profile] [--torch-profile]
    PYTHONPATH=/path/to/other/checkout python benchmarks/profile_sumo_decision.py ...   # the same for another revision

Session 7 used it to check that the PolicyState / history-matching speed-up drives bit-identically (same hash) and to
find what is left of a decision (``model.step``, the warm-up steps of agents new to the context, matching, sampling).
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import pstats
import resource
import sys
import tempfile
import time
from pathlib import Path

# isort: off
import r1sim_sumo  # first: it sets the OpenMP wait policy before torch loads, as `r1sim simulate`
import torch
# isort: on

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_sumo_controller as scene  # noqa: E402

WARMUP_STEPS, TIMED_STEPS = 20, 150  # 0.1 s each
CONTROLLER_PARTS = ("time_read_s", "time_checks_s", "time_policy_s", "time_move_s")  # SumoStats wall-time fields


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=100)
    ap.add_argument("--drive", choices=["commands", "position"], default="position")
    ap.add_argument("--scene", choices=["merge", "grid"], default="merge",
                    help="merge: ~N cars on motorway_merge; grid: ~N cars on random trips over the 9 x 9 city grid")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--guidance", type=float, default=0.0, help="desired-speed guidance weight (SumoController guidance)")
    ap.add_argument("--profile", action="store_true", help="print the cProfile table of the timed part")
    ap.add_argument("--sort", default="tottime", help="cProfile order: tottime (own time) or cumulative")
    ap.add_argument("--rows", type=int, default=30, help="rows of the cProfile table")
    ap.add_argument("--torch-profile", action="store_true", help="print torch.profiler's table of the timed part's "
                    "tensor ops (self CPU time): where a decision's model time goes at the chosen thread count")
    ap.add_argument("--callers", default=None, help="with --profile: also print who calls the functions matching this "
                    "regular expression (e.g. 'topk|amax')")
    ap.add_argument("--callees", default=None, help="with --profile: also print what the functions matching this regular "
                    "expression call (e.g. '_apply_rules|_move')")
    a = ap.parse_args(argv)
    from r1sim_sumo.sim.sumo_controller import SumoController

    torch.set_num_threads(a.threads)
    policy = r1sim_sumo.load_policy()
    prof = cProfile.Profile()
    tprof = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU], record_shapes=True) if a.torch_profile else None
    with tempfile.TemporaryDirectory() as d:
        conn, refill = scene.start_scene(a.scene, a.vehicles, Path(d))
        ctrl = SumoController(conn, policy, offroad_margin_m=1e9, seed=0, standstill_handoff_s=None, drive=a.drive,
                              guidance=a.guidance)
        for k in range(WARMUP_STEPS + TIMED_STEPS):
            if k == WARMUP_STEPS:
                calls0, policy0, t0 = ctrl.stats.policy_calls, ctrl.stats.time_policy_s, time.perf_counter()
                parts0 = {f: getattr(ctrl.stats, f) for f in CONTROLLER_PARTS}
                sumo_s = refill_s = 0.0
                faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
                if a.profile:
                    prof.enable()
                if tprof is not None:
                    tprof.__enter__()
            ta = time.perf_counter()
            conn.simulationStep()
            tb = time.perf_counter()
            refill.refill()  # keep about N cars on the road
            tc = time.perf_counter()
            ctrl.step()
            if k >= WARMUP_STEPS:
                sumo_s += tb - ta
                refill_s += tc - tb
        prof.disable()
        wall = time.perf_counter() - t0
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0
        if tprof is not None:
            tprof.__exit__(None, None, None)
        final = str([(v, round(conn.vehicle.getPosition(v)[0], 4)) for v in sorted(conn.vehicle.getIDList())])
        s = ctrl.stats
        conn.close()
    print(f"{r1sim_sumo.__file__}: {a.vehicles} vehicles ({a.scene}), {a.drive} drive, {a.threads} thread(s), guidance {a.guidance:g}: "
          f"{(s.time_policy_s - policy0) * 1e3 / max(s.policy_calls - calls0, 1):.1f} ms per decision, "
          f"{TIMED_STEPS * 0.1 / wall:.1f} sim-s per wall-s, {s.policy_agents / max(s.policy_calls, 1):.0f} agents per "
          f"decision, {faults} minor page faults, end state {hashlib.md5(final.encode()).hexdigest()}")
    parts = {"sumo_step": sumo_s, "bench_refill": refill_s} | {
        f.removeprefix("time_").removesuffix("_s"): getattr(s, f) - parts0[f] for f in CONTROLLER_PARTS}
    print("per 0.1 s step [ms]: " + ", ".join(f"{n} {v * 1e3 / TIMED_STEPS:.2f}" for n, v in parts.items())
          + f" (wall {wall * 1e3 / TIMED_STEPS:.2f}; the controller's parts: read = population sync, state read and "
          "ring buffers; checks = counts and rules; move = speed commands or placements)")
    if tprof is not None:
        print(tprof.key_averages().table(sort_by="self_cpu_time_total", row_limit=a.rows))
        print(tprof.key_averages(group_by_input_shape=True).table(sort_by="self_cpu_time_total", row_limit=a.rows))
    if a.profile:
        pstats.Stats(prof).sort_stats(a.sort).print_stats(a.rows)
        if a.callers:
            pstats.Stats(prof).sort_stats(a.sort).print_callers(a.callers)
        if a.callees:
            pstats.Stats(prof).sort_stats("cumulative").print_callees(a.callees)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
