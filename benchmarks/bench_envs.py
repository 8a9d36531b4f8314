"""Env steps per second: highway-env with learned background vehicles vs highway-env's IDM, side by side.

For 20/50/100 background vehicles, ``r1sim/highway-v0`` (every background vehicle a
:class:`~r1sim_sumo.sim.highway_vehicle.LearnedVehicle`: one batched policy call per 0.5 s and one batched
SAT collision check per simulation step) and highway-env's own ``highway-v0`` with IDM/MOBIL vehicles, both at
``simulation_frequency=10, policy_frequency=2`` (one env step = 0.5 s = 5 simulation steps), the ego
idling (action 1). The ego's ``crashed`` flag is cleared every step so both runs keep the full vehicle
count for the whole measurement. The policy is the trained default checkpoint when one exists, else an
untrained nano policy of the same size (same compute per step, random motion: more vehicles leave the road
and fall back to IDM, which makes the learned env slower than with a trained policy).

Run: ``python benchmarks/run.py --only envs [--quick]``.
"""

from __future__ import annotations

import time

import gymnasium as gym
import torch

import r1sim_sumo.envs  # noqa: F401  (registers r1sim/*)
from r1sim_sumo.sim.highway_vehicle import coordinator_of, default_or_untrained_policy, set_default_policy


def _steps_per_s(env_id: str, n_vehicles: int, n_steps: int, seed: int = 0) -> tuple[float, dict]:
    env = gym.make(env_id, config={"vehicles_count": n_vehicles, "simulation_frequency": 10, "policy_frequency": 2,
                                   "duration": 10_000})
    env.reset(seed=seed)
    env.unwrapped.vehicle.crashed = False
    env.step(1)  # warm-up (map tokenization, first plan)
    t0 = time.perf_counter()
    for _ in range(n_steps):
        env.unwrapped.vehicle.crashed = False
        env.step(1)
    dt = time.perf_counter() - t0
    coord = coordinator_of(env.unwrapped.road)
    extra = {}
    if coord is not None:
        n_learned = len(coord.learned_vehicles())
        extra = {"learned_at_end": n_learned, "handed_to_idm": coord.stats.handed_to_idm}
    env.close()
    return n_steps / dt, extra


def run(quick: bool = False) -> dict:
    torch.set_num_threads(1)  # the machine is shared: more threads only spin
    policy, trained = default_or_untrained_policy()
    set_default_policy(policy, sampler="topk:5", seed=0)
    n_steps = 4 if quick else 20
    rows = []
    for n in (20, 50) if quick else (20, 50, 100):
        idm, _ = _steps_per_s("highway-v0", n, n_steps)
        learned, extra = _steps_per_s("r1sim/highway-v0", n, n_steps)
        rows.append({"vehicles": n, "idm_steps_per_s": idm, "learned_steps_per_s": learned,
                     "learned_over_idm": learned / idm, **extra})
    notes = [
        "one env step = 0.5 s simulated (5 simulation steps at 10 Hz); ego idles, crash flag cleared each step",
        f"policy: {'trained default checkpoint' if trained else 'untrained nano (no checkpoint found)'}; "
        f"torch threads {torch.get_num_threads()}",
        "target: learned_over_idm >= 1 at 50 vehicles",
    ]
    return {"title": "Env steps/s: learned traffic vs highway-env IDM (r1sim/highway-v0 vs highway-v0)",
            "rows": rows, "notes": notes}


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick=True), indent=1))
