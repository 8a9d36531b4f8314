"""How the learned background traffic of each highway-env env behaves around a passive ego, against IDM traffic.

    python docs/ego_sb3/traffic_health.py [CHECKPOINT] [--envs highway-v0 merge-v0 ...] [--episodes 10] [--seed 3000]
        [--speed-carry off|gains|both] [--skip-idm]

For each env of ``r1sim/<env>`` (highway-env's own roads, config defaults) and each traffic (learned: every background
vehicle driven by the policy, top-5 tokens and the Krauss safety layer, the env defaults; IDM: ``learned_fraction=0``),
``--episodes`` episodes with the ego taking highway-env's IDLE meta-action (keep lane and speed; racetrack-v0: zero steering) at every step. Per env
and traffic: episodes in which the ego crashed, pairs of background vehicles that collided (learned runs: the
coordinator's count, without the ego's pair), learned vehicles that left the road (handed to IDM), and the background's
mean and 10th-percentile speed [m/s] sampled every ego step. Prints a markdown table.
"""
import argparse
import time

import gymnasium as gym
import numpy as np
import torch

import r1sim_sumo.envs  # noqa: F401
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.sim.highway_vehicle import COORDINATOR_ATTR, set_default_policy

IDLE = 1  # highway-env DiscreteMetaAction: LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER
ENVS = ("highway-v0", "merge-v0", "roundabout-v0", "intersection-v0", "racetrack-v0")


def run(env_name: str, learned: bool, episodes: int, seed: int, speed_carry: str = "off") -> dict:
    env = gym.make(f"r1sim/{env_name}", config={"learned_fraction": 1.0 if learned else 0.0, "speed_carry": speed_carry})
    crashed = pairs = off = steps = 0
    speeds = []
    space = env.action_space  # racetrack-v0 steers continuously: zero steering (and throttle where there is one)
    action = IDLE if isinstance(space, gym.spaces.Discrete) else np.zeros(space.shape, space.dtype)
    for ep in range(episodes):
        env.reset(seed=seed + ep)
        done, info = False, {}
        while not done:
            _, _, term, trunc, info = env.step(action)
            done = term or trunc
            steps += 1
            ego = env.unwrapped.vehicle
            speeds.extend(float(v.speed) for v in env.unwrapped.road.vehicles if v is not ego)
        crashed += bool(info.get("crashed"))
        coord = getattr(env.unwrapped.road, COORDINATOR_ATTR, None)
        if learned and coord is not None:
            pairs += coord.stats.crashes - bool(info.get("crashed"))
            off += coord.stats.handed_to_idm + coord.stats.removed
    env.close()
    return {"crashed": crashed, "pairs": pairs, "off": off, "steps": steps,
            "mean": float(np.mean(speeds)) if speeds else float("nan"),
            "p10": float(np.percentile(speeds, 10)) if speeds else float("nan")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", nargs="?", default="r1sim-nano")
    ap.add_argument("--envs", nargs="+", default=list(ENVS), choices=ENVS)
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--seed", type=int, default=3000)
    ap.add_argument("--speed-carry", default="off", choices=["off", "gains", "both"],
                    help="the env's speed_carry for the learned traffic (default off, the env's)")
    ap.add_argument("--skip-idm", action="store_true", help="only the learned rows")
    a = ap.parse_args()
    torch.set_num_threads(1)
    set_default_policy(load_policy(a.checkpoint), sampler="topk:5")
    print(f"{a.checkpoint}, top-5, {a.episodes} episodes per row, seeds {a.seed}-{a.seed + a.episodes - 1}, ego IDLE, speed carry {a.speed_carry}\n")
    print("| env | traffic | ego crashed (episodes) | background pairs collided | learned vehicles left the road "
          "| background speed mean / 10th pct [m/s] | ego steps | wall [s] |")
    print("|---|---|---|---|---|---|---|---|")
    for name in a.envs:
        for learned in (True,) if a.skip_idm else (False, True):
            t0 = time.perf_counter()
            r = run(name, learned, a.episodes, a.seed, a.speed_carry)
            print(f"| {name} | {'learned' if learned else 'IDM'} | {r['crashed']} / {a.episodes} | "
                  f"{r['pairs'] if learned else 'n/a'} | {r['off'] if learned else 'n/a'} | {r['mean']:.1f} / {r['p10']:.1f} | "
                  f"{r['steps']} | {time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
