"""Long free-lane probes of a policy (issue 19, session 9): speed [m/s] every 4 s of a lone vehicle (3 seeds) and of the
front and last of a 5-vehicle platoon (1.5 s headways), all started at ``v0`` on the bundled motorway lane of
:mod:`r1sim_sumo.evaluate_free_road`, desired speed = the lane limit (33.3 m/s).

    python scripts/diag_platoon_long.py CHECKPOINT 2 40      # from 2 m/s, 40 decisions (20 s)
"""

import sys

import numpy as np
import torch

from r1sim_sumo.evaluate_free_road import drive_alone, drive_platoon, lane_axis
from r1sim_sumo.model.checkpoint import load_policy


def every_4s(v: np.ndarray) -> list[float]:
    return [round(float(v[i:i + 10].mean()), 1) for i in range(10, len(v), 40)]


def main(ckpt: str, v0: float, decisions: int) -> None:
    torch.set_num_threads(1)
    pol, axis = load_policy(ckpt), lane_axis()
    for seed in range(3):
        xy, _ = drive_alone(pol, v0, seed, decisions, axis)
        print(f"alone, seed {seed}:", every_4s(np.linalg.norm(np.diff(xy, axis=0), axis=1) / 0.1))
    xy = drive_platoon(pol, v0, 5, seed=0, decisions=decisions, axis=axis)
    v = np.linalg.norm(np.diff(xy, axis=1), axis=2) / 0.1  # [5, T]
    print("platoon front:", every_4s(v[0]))
    print("platoon last: ", every_4s(v[-1]))


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), int(sys.argv[3]))
