"""``r1sim generate {sumo,highway,csv,highd}``: write a scenario dataset folder (shards + manifest.json).

Examples::

    r1sim generate sumo --networks all --seeds 0-3 --duration 600 --out data/generated/sumo --workers 2
    r1sim generate sumo --networks all --seeds 0-63 --out data/generated/big --backend ray --workers 64
    r1sim generate highway --envs highway-v0,merge-v0 --seeds 0-1 --out data/generated/hw
    r1sim generate csv --tracks tracks.csv --map map.csv --out data/generated/csv
    r1sim generate highd --dir /data/highD --recording 1 --out data/generated/highd01

An existing non-empty ``--out`` folder is refused (datasets are never overwritten).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HELP = "generate reference scenarios from SUMO, highway-env or logged data (CSV, highD)"


def parse_seeds(text: str) -> list[int]:
    """``"0-3"`` -> [0, 1, 2, 3]; ``"0,2,5-6"`` -> [0, 2, 5, 6]."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            part = part.strip()
            if not part:
                continue
            if "-" in part:
                lo, hi = part.split("-", 1)
                a, b = int(lo), int(hi)
                if b < a or a < 0:
                    raise ValueError
                seeds += list(range(a, b + 1))
            elif int(part) >= 0:
                seeds.append(int(part))
            else:
                raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"--seeds '{text}': expected e.g. '0-3' or '0,2,5-7'") from None
    if not seeds:
        raise argparse.ArgumentTypeError(f"--seeds '{text}': no seed given")
    return sorted(dict.fromkeys(seeds))


def parse_names(text: str, available: list[str], what: str) -> list[str]:
    if text.strip() == "all":
        return list(available)
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in available and not Path(n).is_dir()]
    if unknown:
        raise SystemExit(f"r1sim generate: unknown {what} {unknown}; choose from {available} (or 'all')")
    return names


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="output dataset folder (must not exist or be empty)")
    p.add_argument("--stride", type=int, default=20, help="steps (0.1 s) between window starts (default 20 = 2 s)")
    p.add_argument("--shard-size", type=int, default=256, help="scenarios per shard (default 256)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from r1sim_sumo.workers import add_pool_arguments

    sub = parser.add_subparsers(dest="source", metavar="SOURCE", required=True)

    p = sub.add_parser("sumo", help="run SUMO on bundled networks, record 91-step windows")
    p.add_argument("--networks", default="all", help="'all' or comma-separated bundled names / network folders")
    p.add_argument("--seeds", type=parse_seeds, default=[0], help="e.g. 0-3 or 0,2,5 (default 0)")
    p.add_argument("--duration", type=float, default=600.0, help="recorded seconds per run (default 600)")
    p.add_argument("--warmup", type=float, default=120.0, help="seconds simulated before recording (default 120)")
    p.add_argument("--demand-scale", type=float, default=1.0, help="multiplies the networks' default demand")
    p.add_argument("--save-states", action="store_true", help="save a SUMO state at each window's current step")
    add_pool_arguments(p, default_workers=2, what="SUMO runs (one simulation each)")
    _common(p)

    p = sub.add_parser("highway", help="record highway-env IDM/MOBIL traffic")
    p.add_argument("--envs", default="highway-v0,merge-v0,roundabout-v0,intersection-v0", help="comma-separated env ids or 'all'")
    p.add_argument("--seeds", type=parse_seeds, default=[0], help="e.g. 0-1")
    p.add_argument("--episodes", type=int, default=1, help="episodes per (env, seed)")
    p.add_argument("--episode-s", type=float, default=40.0, help="episode length [s] (default 40)")
    p.add_argument("--vehicles", type=int, default=None, help="override the env's vehicles_count")
    add_pool_arguments(p, default_workers=2, what="highway-env runs")
    _common(p)

    p = sub.add_parser("csv", help="convert a generic tracks CSV + map CSV")
    p.add_argument("--tracks", required=True, help="tracks CSV file")
    p.add_argument("--map", required=True, help="map polylines CSV file")
    _common(p)

    p = sub.add_parser("highd", help="convert one highD recording")
    p.add_argument("--dir", required=True, help="highD data folder (holding XX_tracks.csv ...)")
    p.add_argument("--recording", type=int, required=True, help="recording id, e.g. 1")
    p.add_argument("--max-windows", type=int, default=None, help="keep at most this many windows")
    _common(p)


def run(args: argparse.Namespace) -> int:
    from r1sim_sumo.data.dataset import GenerationError, check_fresh_out_dir

    t0 = time.perf_counter()
    try:
        check_fresh_out_dir(args.out)
        out = _SOURCES[args.source](args)
    except (GenerationError, ValueError, FileNotFoundError) as exc:
        print(f"r1sim generate {args.source}: error: {exc}", file=sys.stderr)
        return 1
    from r1sim_sumo.scenario import ScenarioDataset

    n = len(ScenarioDataset(out))
    print(f"wrote {n} scenarios to {out} in {time.perf_counter() - t0:.1f} s")
    return 0


def _sumo(args) -> Path:
    from r1sim_sumo.data.dataset import generate_sumo_dataset
    from r1sim_sumo.data.sumo_reference import SumoGenConfig
    from r1sim_sumo.resources import list_networks

    nets = parse_names(args.networks, list_networks(), "network(s)")
    configs = [SumoGenConfig(network=n, seed=s, duration_s=args.duration, warmup_s=args.warmup, stride_steps=args.stride,
                             demand_scale=args.demand_scale, save_states=args.save_states)
               for n in nets for s in args.seeds]
    return generate_sumo_dataset(configs, args.out, workers=args.workers, shard_size=args.shard_size,
                                 progress=not args.no_progress, backend=args.backend or "process",
                                 ray_address=args.ray_address, max_retries=args.max_retries)


def _highway(args) -> Path:
    from r1sim_sumo.data.dataset import HIGHWAY_ENVS, HighwayGenJob, run_generation_jobs

    envs = parse_names(args.envs, list(HIGHWAY_ENVS), "env(s)")
    jobs = [HighwayGenJob(env_name=e, seed=s, n_episodes=args.episodes, episode_s=args.episode_s,
                          stride_steps=args.stride, vehicles_count=args.vehicles) for e in envs for s in args.seeds]
    return run_generation_jobs(jobs, args.out, workers=args.workers, shard_size=args.shard_size,
                               progress=not args.no_progress, backend=args.backend or "process",
                               ray_address=args.ray_address, max_retries=args.max_retries)


def _write(scenarios, args, extra: dict) -> Path:
    from r1sim_sumo.scenario import write_dataset

    scenarios = list(scenarios)
    if not scenarios:
        raise ValueError("the input produced no scenario windows (too short? every window needs 9.1 s of tracks)")
    return write_dataset(args.out, scenarios, shard_size=args.shard_size, extra_manifest=extra)


def _csv(args) -> Path:
    from r1sim_sumo.data.logged import load_generic_csv

    scenarios = load_generic_csv(args.tracks, args.map, stride_steps=args.stride)
    return _write(scenarios, args, {"source": "csv", "tracks": str(args.tracks), "map": str(args.map)})


def _highd(args) -> Path:
    from r1sim_sumo.data.logged import load_highd

    scenarios = load_highd(args.dir, args.recording, stride_steps=args.stride, max_windows=args.max_windows)
    return _write(scenarios, args, {"source": "highd", "recording": args.recording})


_SOURCES = {"sumo": _sumo, "highway": _highway, "csv": _csv, "highd": _highd}
