"""A lone vehicle on a free straight lane from a steady start speed with a desired speed well above: its speed every
0.5 s (does it speed up, and from which start speeds not?), on several lanes of two bundled networks (is it the map?).

    python scripts/diag_free_road_start_speeds.py [--checkpoint CKPT] [--desired 33.3] [--sampler median:0.1]

Session 49: the nano creeps up at 0.2-0.4 m/s^2 from a steady 18-23 m/s and speeds up at 1.5-3 m/s^2 from 24 m/s, on
every lane (``r1sim_sumo.evaluate_free_road``'s lone-vehicle drive, history at a constant speed).
"""

from __future__ import annotations

import argparse

import numpy as np

LANES = (("motorway_merge", "main_in_1"), ("motorway_merge", "main_out_1"), ("lane_drop", "approach_1"),
         ("lane_drop", "downstream_0"))
START_SPEEDS_MPS = (15.0, 18.0, 20.0, 22.0, 24.0, 26.0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--desired", type=float, default=33.3, help="[m/s] desired speed handed to the policy")
    ap.add_argument("--sampler", default="median:0.1", help="token sampler (default: the drop-in's)")
    ap.add_argument("--decisions", type=int, default=16, help="0.5 s decisions driven (default 16 = 8 s)")
    a = ap.parse_args(argv)

    import torch

    from r1sim_sumo.evaluate_free_road import drive_alone, lane_axis
    from r1sim_sumo.model.checkpoint import load_policy

    torch.set_num_threads(1)
    policy = load_policy(a.checkpoint) if a.checkpoint else load_policy()
    print(f"{a.checkpoint or 'r1sim-nano'}, {a.sampler}, desired {a.desired:g} m/s: speed [m/s] every 0.5 s from a steady start")
    for net, lane in LANES:
        road, p0, u, yaw0, _limit = lane_axis(net, lane)
        for v0 in START_SPEEDS_MPS:
            xy, _yaw = drive_alone(policy, v0, seed=0, decisions=a.decisions, axis=(road, p0, u, yaw0, a.desired),
                                   sampler=a.sampler)
            sp = np.linalg.norm(np.diff(xy, axis=0), axis=1) / 0.1  # [m/s] at 10 Hz
            after = sp[10::5]  # from the last history step on, every 0.5 s
            rate = (after[-1] - after[0]) / (0.5 * (len(after) - 1))
            print(f"{net}/{lane} from {v0:4.1f}: {' '.join(f'{x:.1f}' for x in after)}  (mean {rate:+.2f} m/s^2)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
