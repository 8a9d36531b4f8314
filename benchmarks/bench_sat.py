"""SAT box-overlap throughput: ``geometry.boxes_overlap`` batched (numpy, torch) vs highway-env per pair.

Same random oriented boxes for every method (centres uniform in an 8 m square, so about half the pairs
overlap; yaw uniform; length 3-6 m, width 1.5-2.5 m). highway-env's
``highway_env.utils.are_polygons_intersecting`` is called once per pair on the closed corner polygons, as
highway-env does in its own collision loop. Rows report pair checks per second and the ratio to
highway-env measured in this same run, plus how many pairs the two implementations agree on.

Run: ``python benchmarks/run.py --only sat [--quick]``.
"""

from __future__ import annotations

import time

import numpy as np

from r1sim_sumo.geometry import box_corners, boxes_overlap


def _random_boxes(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    b = {}
    for s in ("1", "2"):
        b["x" + s] = rng.uniform(0.0, 8.0, n)
        b["y" + s] = rng.uniform(0.0, 8.0, n)
        b["yaw" + s] = rng.uniform(-np.pi, np.pi, n)
        b["l" + s] = rng.uniform(3.0, 6.0, n)
        b["w" + s] = rng.uniform(1.5, 2.5, n)
    return b


def _args(b: dict, conv=lambda a: a) -> list:
    return [conv(b[k]) for k in ("x1", "y1", "yaw1", "l1", "w1", "x2", "y2", "yaw2", "l2", "w2")]


def _rate(fn, n_pairs: int, min_time_s: float) -> tuple[float, object]:
    """Pair checks per second of ``fn()`` (repeated until ``min_time_s`` has elapsed) and its last result."""
    out = fn()  # warm-up
    reps, t0 = 0, time.perf_counter()
    while True:
        out = fn()
        reps += 1
        dt = time.perf_counter() - t0
        if dt >= min_time_s:
            return reps * n_pairs / dt, out


def run(quick: bool = False) -> dict:
    n = 20_000 if quick else 1_000_000
    n_hw = 500 if quick else 20_000
    min_t = 0.1 if quick else 1.0
    b = _random_boxes(n)
    rows = []
    np_rate, np_flags = _rate(lambda: boxes_overlap(*_args(b)), n, min_t)
    results = {"numpy (batched)": (np_rate, np_flags)}
    try:
        import torch

        args_t = _args(b, lambda a: torch.from_numpy(a).float())
        t_rate, t_flags = _rate(lambda: boxes_overlap(*args_t), n, min_t)
        results["torch float32 (batched)"] = (t_rate, t_flags.numpy())
        threads = torch.get_num_threads()
    except ImportError:
        threads = None
    try:
        from highway_env.utils import are_polygons_intersecting
    except ImportError:
        are_polygons_intersecting = None
    notes = [f"{n} random box pairs for the batched methods, {n_hw} for highway-env (per-pair Python calls)."]
    if threads is not None:
        notes.append(f"torch threads: {threads}")
    hw_rate = None
    if are_polygons_intersecting is not None:
        c1 = box_corners(b["x1"][:n_hw], b["y1"][:n_hw], b["yaw1"][:n_hw], b["l1"][:n_hw], b["w1"][:n_hw])  # [n, 4, 2]
        c2 = box_corners(b["x2"][:n_hw], b["y2"][:n_hw], b["yaw2"][:n_hw], b["l2"][:n_hw], b["w2"][:n_hw])
        p1 = np.concatenate([c1, c1[:, :1]], 1)  # closed polygons [n, 5, 2], as highway-env builds them
        p2 = np.concatenate([c2, c2[:, :1]], 1)
        zero = np.zeros(2)

        def hw_all():
            return np.array([are_polygons_intersecting(p1[k], p2[k], zero, zero)[0] for k in range(n_hw)])

        hw_rate, hw_flags = _rate(hw_all, n_hw, min_t)
        results["highway-env are_polygons_intersecting (per pair)"] = (hw_rate, hw_flags)
    else:
        notes.append("highway-env not installed: no reference rows")
    for name, (rate, flags) in results.items():
        row = {"method": name, "pair_checks_per_s": float(rate)}
        if hw_rate is not None:
            row["speedup_vs_highway_env"] = float(rate / hw_rate)
            f = np.asarray(flags)[:n_hw].astype(bool)
            row["agree_with_highway_env"] = f"{int((f == hw_flags).sum())}/{n_hw}"
        row["overlap_fraction"] = float(np.asarray(flags).astype(bool).mean())
        rows.append(row)
    return {"title": "SAT box overlap: batched geometry.boxes_overlap vs highway-env per pair", "rows": rows, "notes": notes}


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick=True), indent=2))
