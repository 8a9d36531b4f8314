"""``python -m r1sim_sumo.reliability {report,soak}``."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m r1sim_sumo.reliability", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    rp = sub.add_parser("report", help="run hostile inputs + fault injection, write report.md/report.json")
    rp.add_argument("--out", default="docs/reliability", help="output folder (default docs/reliability)")
    rp.add_argument("--faults", nargs="*", default=["nan", "sumo", "pretrain", "finetune"],
                    choices=["nan", "sumo", "pretrain", "finetune"], help="fault injections to run (default all)")
    rp.add_argument("--soak-dir", default=None, help="folder holding soak.json (default OUT/soak)")
    sp = sub.add_parser("soak", help="long SUMO run with the learned controller: RSS, vehicle balance, stuck vehicles")
    add_soak_arguments(sp)
    args = p.parse_args(argv)
    if args.cmd == "report":
        from r1sim_sumo.reliability.report import build_report

        r = build_report(args.out, tuple(args.faults), args.soak_dir)
        bad = [c["name"] for c in r["cases"] if not c["passed"]] + [k for k, f in r["faults"].items() if not f.get("passed")]
        print(f"[reliability] wrote {args.out}/report.md; {len(r['cases'])} hostile inputs, {len(r['faults'])} fault injections; "
              f"failed: {bad or 'none'}")
        return 1 if bad else 0
    return run_soak_cli(args)


def add_soak_arguments(sp) -> None:
    sp.add_argument("--sim-seconds", type=float, default=3600.0, help="simulated seconds (default 3600)")
    sp.add_argument("--out", default="docs/reliability/soak", help="output folder for soak.csv / soak_rss.png / soak.json")
    sp.add_argument("--network", default="motorway_merge", help="bundled network (default motorway_merge)")
    sp.add_argument("--checkpoint", default=None, help="policy checkpoint (default: the shipped one)")
    sp.add_argument("--sample-every", type=float, default=10.0, help="simulated seconds between CSV rows (default 10)")
    sp.add_argument("--stuck-after", type=float, default=60.0, help="seconds standing still without a reason = stuck")
    sp.add_argument("--seed", type=int, default=0)
    sp.add_argument("--progress", action="store_true", help="print every sample row")
    sp.add_argument("--max-running", type=int, default=150,
                    help="SUMO --max-num-vehicles: at most this many vehicles in the network (default 150; 0 = no cap)")


def run_soak_cli(args) -> int:
    from r1sim_sumo.reliability.soak import run_soak

    s = run_soak(args.sim_seconds, args.out, network=args.network, checkpoint=args.checkpoint, sample_every_s=args.sample_every,
                 stuck_after_s=args.stuck_after, seed=args.seed, progress=args.progress,
                 max_running=args.max_running or None)
    print(f"[soak] {s.sim_seconds:.0f} sim-s in {s.wall_s:.0f} s; RSS {s.rss_start_mb:.0f} -> {s.rss_end_mb:.0f} MB "
          f"(slope {s.rss_slope_mb_per_sim_h:+.1f} MB/sim-h; live RSS {s.rss_live_start_mb:.0f} -> {s.rss_live_end_mb:.0f} MB, "
          f"{s.rss_leak_mb_per_sim_h:+.1f} MB/sim-h at a fixed population: "
          f"flat {s.memory_flat}); departed {s.departed} = arrived {s.arrived} + removed {s.removed} "
          f"+ running {s.running}: {s.balanced_every_sample}; stuck {len(s.stuck_vehicles)}; passed: {s.passed}")
    return 0 if s.passed else 1


if __name__ == "__main__":
    sys.exit(main())
