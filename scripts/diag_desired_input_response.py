"""Does the policy's next move depend on the desired-speed input? A lone vehicle on a free straight lane
(motorway_merge ``main_in_1``) from a steady start speed, given several desired speeds (and none: NaN, the input's
"unknown"): its mean acceleration over the first 1 s (two decisions) over ``--seeds`` draws of ``--sampler``.

    python scripts/diag_desired_input_response.py [--checkpoint CKPT] [--sampler topk:5] [--seeds 12]

Session 49: the nano's answer hardly depends on the input between 18 and 26 m/s (see docs/training "session 49").
"""

from __future__ import annotations

import argparse

import numpy as np

START_SPEEDS_MPS = (10.0, 15.0, 18.0, 22.0, 26.0, 30.0)
DESIRED_MPS = (float("nan"), 15.0, 20.0, 27.0, 33.3, 40.0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--sampler", default="topk:5")
    ap.add_argument("--seeds", type=int, default=12)
    a = ap.parse_args(argv)

    import torch

    from r1sim_sumo.evaluate_free_road import drive_alone, lane_axis
    from r1sim_sumo.model.checkpoint import load_policy

    torch.set_num_threads(1)
    policy = load_policy(a.checkpoint) if a.checkpoint else load_policy()
    road, p0, u, yaw0, _limit = lane_axis()
    print(f"{a.checkpoint or 'r1sim-nano'}, {a.sampler}, {a.seeds} seeds: mean acceleration [m/s^2] over the first 1 s")
    print("| start speed [m/s] | " + " | ".join("desired unknown" if np.isnan(d) else f"desired {d:g}" for d in DESIRED_MPS) + " |")
    print("|---" * (len(DESIRED_MPS) + 1) + "|")
    for v0 in START_SPEEDS_MPS:
        cells = []
        for d in DESIRED_MPS:
            acc = []
            for seed in range(a.seeds):
                xy, _ = drive_alone(policy, v0, seed=seed, decisions=2, axis=(road, p0, u, yaw0, d), sampler=a.sampler)
                sp = np.linalg.norm(np.diff(xy, axis=0), axis=1) / 0.1
                acc.append((sp[-5:].mean() - v0) / 1.0)
            cells.append(f"{np.mean(acc):+.2f}")
        print(f"| {v0:g} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
