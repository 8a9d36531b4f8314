"""How often the ego that both SB3 egos of ``examples/train_ego_sb3.py`` converged to (hold the lowest target speed,
20 m/s, in its lane: the meta-action SLOWER at every step) collides with learned traffic, over many episodes. Mostly it
runs into a slower learned vehicle ahead in its lane (``slow_ego_crash_kinds.py``, session 57), not the other way.

    python docs/ego_sb3/slow_ego_crashes.py CHECKPOINT [--episodes 100] [--seed 1000]

Same env as the example (r1sim/highway-v0, 20 learned background vehicles, 40 s, top-5 or --sampler); prints crashes / episodes and
the Wilson 95% interval. The example's 20 evaluation episodes are seeds 1000-1019.
"""
import argparse
import math

import gymnasium as gym
import torch

import r1sim_sumo.envs  # noqa: F401
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.sim.highway_vehicle import set_default_policy

SLOWER = 4  # highway-env DiscreteMetaAction: LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--sampler", default="topk:5", help="the learned traffic's token sampler (the env's default: topk:5)")
    ap.add_argument("--seed", type=int, default=1000)
    a = ap.parse_args()
    torch.set_num_threads(1)
    set_default_policy(load_policy(a.checkpoint), sampler=a.sampler)
    env = gym.make("r1sim/highway-v0", config={"learned_fraction": 1.0, "vehicles_count": 20, "duration": 40.0})
    crashes = 0
    for ep in range(a.episodes):
        env.reset(seed=a.seed + ep)
        done = False
        while not done:
            _, _, term, trunc, info = env.step(SLOWER)
            done = term or trunc
        crashes += bool(info["crashed"])
    n, p, z = a.episodes, crashes / a.episodes, 1.96
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    print(f"{a.checkpoint} ({a.sampler}): {crashes} / {n} episodes crashed ({p:.2f}, 95% interval {c - h:.2f}-{c + h:.2f}); "
          f"seeds {a.seed}-{a.seed + n - 1}")


if __name__ == "__main__":
    main()
