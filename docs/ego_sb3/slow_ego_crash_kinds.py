"""What kind of collision learned traffic has with the slow lane-keeping ego of ``slow_ego_crashes.py``: for each crashed
episode, the other vehicle's position in the ego's frame one step (1/policy_frequency s) before the crash, its lane
relative to the ego's, its speed and heading, so a rear-end (same lane, behind, closing) is told from a cut-in or a
side-swipe (an adjacent lane, moving across).

    python docs/ego_sb3/slow_ego_crash_kinds.py CHECKPOINT [--episodes 40] [--seed 2000]

Same env and action as slow_ego_crashes.py (r1sim/highway-v0, 20 learned vehicles, 40 s, ego SLOWER every step;
top-5 or --sampler).
highway-env frame: x along the road [m], y to the right [m], heading radians; speeds [m/s].
"""
import argparse
from collections import Counter

import gymnasium as gym
import numpy as np
import torch

import r1sim_sumo.envs  # noqa: F401
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.sim.highway_vehicle import COORDINATOR_ATTR, LearnedVehicle, set_default_policy

SLOWER = 4
SLOW_MPS, FREE_GAP_M = 8.0, 60.0  # a learned vehicle under 8 m/s with no vehicle within 60 m ahead in its lane


def snapshot(env):
    road = env.unwrapped.road
    ego = env.unwrapped.vehicle
    return ego, [(v, np.array(v.position, float), float(v.speed), float(v.heading), v.lane_index) for v in road.vehicles if v is not ego]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--episodes", type=int, default=40)
    ap.add_argument("--sampler", default="topk:5", help="the learned traffic's token sampler (the env's default: topk:5)")
    ap.add_argument("--seed", type=int, default=2000)
    ap.add_argument("--safety", default="krauss", choices=["krauss", "none"], help="the learned traffic's safety layer")
    ap.add_argument("--learned-fraction", type=float, default=1.0, help="share of learned background vehicles (0: all IDM)")
    ap.add_argument("--verbose", action="store_true", help="print each free-road slow vehicle's recent speeds and gaps")
    a = ap.parse_args()
    torch.set_num_threads(1)
    set_default_policy(load_policy(a.checkpoint), sampler=a.sampler)
    env = gym.make("r1sim/highway-v0", config={"learned_fraction": a.learned_fraction, "vehicles_count": 20, "duration": 40.0,
                                                "safety": a.safety})
    kinds = Counter()
    kinds_speed = []
    free_slow_eps = free_slow_vehicles = crashed_eps = both = pairs = off = 0
    learned_v = []
    for ep in range(a.episodes):
        env.reset(seed=a.seed + ep)
        done, prev, speeds, free_slow = False, None, {}, set()
        while not done:
            ego, others = snapshot(env)
            allv = others + [(ego, np.array(ego.position, float), float(ego.speed), float(ego.heading), ego.lane_index)]
            learned_v.extend(o[2] for o in others if isinstance(o[0], LearnedVehicle) or a.learned_fraction == 0)
            for o in others:
                ahead = [(q[1][0] - o[1][0], q[2]) for q in allv if q[0] is not o[0] and q[4][2] == o[4][2] and q[1][0] > o[1][0]]
                lead = min(ahead) if ahead else (float("inf"), float("nan"))
                speeds.setdefault(id(o[0]), []).append((o[2], lead[0], lead[1]))
                if o[2] < SLOW_MPS and lead[0] > FREE_GAP_M and id(o[0]) not in free_slow:
                    free_slow.add(id(o[0]))
                    if a.verbose:
                        h = speeds[id(o[0])]
                        print(f"seed {a.seed + ep} t {env.unwrapped.time:.1f} s: free-road slow vehicle {type(o[0]).__name__} at x {o[1][0]:.0f} m, "
                              f"lane {o[4][2]}, heading {o[3]:+.3f}; speed/gap/leader speed over the last 8 s: "
                              f"{'  '.join(f'{x:.0f}/{g:.0f}/{w:.0f}' for x, g, w in h[-16::2])}")
            prev = (np.array(ego.position, float), float(ego.speed), ego.lane_index, others)
            _, _, term, trunc, info = env.step(SLOWER)
            done = term or trunc
        coord = getattr(env.unwrapped.road, COORDINATOR_ATTR, None)
        if coord is not None:
            pairs += coord.stats.crashes - bool(info["crashed"])  # pairs without the ego (its own crash is one pair)
            off += coord.stats.handed_to_idm + coord.stats.removed
        free_slow_eps += bool(free_slow)
        free_slow_vehicles += len(free_slow)
        crashed_eps += bool(info["crashed"])
        both += bool(info["crashed"]) and bool(free_slow)
        if not info["crashed"]:
            continue
        ego = env.unwrapped.vehicle
        ego_xy, ego_v, ego_lane, others = prev
        hit = [o for o in others if getattr(o[0], "crashed", False)]
        if not hit:
            kinds["no partner found"] += 1
            print(f"seed {a.seed + ep}: crashed, no crashed partner found")
            continue
        v, xy, spd, hdg, lane = min(hit, key=lambda o: np.linalg.norm(o[1] - ego_xy))
        dx, dy = xy - ego_xy
        dlane = lane[2] - ego_lane[2]
        if dlane == 0 and dx < 0:
            kind = "rear-end into the ego (same lane, from behind)"
        elif dlane == 0:
            kind = "ego into the vehicle ahead (same lane)"
        elif dx < 0:
            kind = "adjacent lane, from behind (cut-in / side-swipe)"
        else:
            kind = "adjacent lane, ahead (cut-in / side-swipe)"
        kinds[kind] += 1
        print(f"seed {a.seed + ep}: {kind}: dx {dx:+.1f} m dy {dy:+.1f} m, lanes {ego_lane[2]} -> other {lane[2]}, "
              f"speeds ego {ego_v:.1f} other {spd:.1f} m/s, other heading {hdg:+.3f} rad, t {env.unwrapped.time:.1f} s; "
              f"the other's speed / gap to its leader [m] / leader's speed over the last 8 s: "
              f"{'  '.join(f'{x:.0f}/{g:.0f}/{w:.0f}' for x, g, w in speeds[id(v)][-16::2])}")
        kinds_speed.append(spd)
    print(f"{a.checkpoint} ({a.sampler}): {sum(kinds.values())} crashes in {a.episodes} episodes")
    for k, n in kinds.most_common():
        print(f"  {n:3d}  {k}")
    print(f"  episodes with a learned vehicle under {SLOW_MPS:g} m/s and nothing within {FREE_GAP_M:g} m ahead in its lane: "
          f"{free_slow_eps} of {a.episodes} ({free_slow_vehicles} vehicles); of the {crashed_eps} crashed episodes, {both} had one")
    print(f"  background traffic: mean speed {np.mean(learned_v):.1f} m/s (10th percentile {np.percentile(learned_v, 10):.1f}) "
          f"over every 0.5 s; {pairs} crashes among the background (pairs without the ego); {off} left the road")
    if kinds_speed:
        print(f"  the other vehicle's speed one step before: median {np.median(kinds_speed):.1f} m/s, "
              f"{sum(x < 10 for x in kinds_speed)} of {len(kinds_speed)} under 10 m/s")


if __name__ == "__main__":
    main()
