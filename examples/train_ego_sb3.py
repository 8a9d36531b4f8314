"""Train an ego with SB3 PPO against IDM traffic and against learned traffic, evaluate both in both.

    python examples/train_ego_sb3.py --short            # ~1 min smoke run (CI)
    python examples/train_ego_sb3.py --steps 20000 --episodes 20 --out runs/ego_sb3

Writes ``<out>/results.md`` (collision rate, mean speed [m/s], mean episode return per ego x traffic) and
``<out>/episode.gif`` (the learned-traffic ego in learned traffic; Pillow via matplotlib, no extra dependency).
Learned traffic = ``r1sim/highway-v0``; IDM traffic = the same env with ``learned_fraction=0``. Without a
trained checkpoint (``r1sim_sumo.load_policy()``) an untrained policy drives the traffic (stated in the table).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO

import r1sim_sumo.envs  # noqa: F401  (registers r1sim/*)
from r1sim_sumo.sim.highway_vehicle import default_or_untrained_policy, set_default_policy

TRAFFIC = {"idm": {"learned_fraction": 0.0}, "learned": {"learned_fraction": 1.0}}


def make_env(traffic: str, vehicles: int, duration_s: float, render: bool = False):
    cfg = {**TRAFFIC[traffic], "vehicles_count": vehicles, "duration": duration_s}
    return gym.make("r1sim/highway-v0", config=cfg, render_mode="rgb_array" if render else None)


def evaluate(model, env, episodes: int, seed: int) -> dict:
    crashes, speeds, returns = 0, [], []
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        done, ret = False, 0.0
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, r, term, trunc, info = env.step(action)
            ret += r
            speeds.append(info["speed"])
            done = term or trunc
        crashes += bool(info["crashed"])
        returns.append(ret)
    return {"collision_rate": crashes / episodes, "mean_speed_mps": float(np.mean(speeds)),
            "episode_return": float(np.mean(returns))}


def record_gif(model, env, path: Path, seed: int, max_frames: int) -> None:
    from matplotlib import animation
    from matplotlib.figure import Figure

    obs, _ = env.reset(seed=seed)
    frames = [env.render()]
    for _ in range(max_frames):
        obs, _, term, trunc, _ = env.step(model.predict(obs, deterministic=True)[0])
        frames.append(env.render())
        if term or trunc:
            break
    fig = Figure(figsize=(frames[0].shape[1] / 100, frames[0].shape[0] / 100), dpi=100)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.axis("off")
    im = ax.imshow(frames[0])
    anim = animation.FuncAnimation(fig, lambda i: [im.set_data(frames[i])], frames=len(frames))
    anim.save(str(path), writer=animation.PillowWriter(fps=2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--short", action="store_true", help="smoke run: tiny budget, ~1 minute")
    ap.add_argument("--steps", type=int, default=20_000, help="PPO timesteps per ego")
    ap.add_argument("--episodes", type=int, default=10, help="evaluation episodes per (ego, traffic)")
    ap.add_argument("--vehicles", type=int, default=20, help="background vehicles")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sampler", default="topk:5", help="the learned traffic's token sampler (the env's default: topk:5)")
    ap.add_argument("--out", type=Path, default=Path("runs/ego_sb3"))
    a = ap.parse_args()
    if a.short:
        a.steps, a.episodes, a.vehicles = 128, 1, 8
    duration = 5.0 if a.short else 40.0  # [s]
    torch.set_num_threads(1)
    policy, trained = default_or_untrained_policy()
    set_default_policy(policy, sampler=a.sampler)
    a.out.mkdir(parents=True, exist_ok=True)

    egos = {}
    for traffic in TRAFFIC:
        env = make_env(traffic, a.vehicles, duration)
        egos[traffic] = PPO("MlpPolicy", env, n_steps=64 if a.short else 512, batch_size=32 if a.short else 64,
                            seed=a.seed, device="cpu", verbose=0).learn(a.steps)
        env.close()
    lines = [f"# Ego PPO ({a.steps} steps) on r1sim/highway-v0, {a.vehicles} background vehicles",
             "", f"traffic policy: {'trained checkpoint' if trained else 'UNTRAINED (no checkpoint found)'}, "
             f"tokens {a.sampler}", "",
             "| ego trained against | evaluated in | collision rate | mean speed [m/s] | episode return |",
             "|---|---|---|---|---|"]
    for ego_name, model in egos.items():
        for traffic in TRAFFIC:
            env = make_env(traffic, a.vehicles, duration)
            r = evaluate(model, env, a.episodes, seed=1000 + a.seed)
            env.close()
            lines.append(f"| {ego_name} | {traffic} | {r['collision_rate']:.2f} | {r['mean_speed_mps']:.2f} | "
                         f"{r['episode_return']:.2f} |")
    (a.out / "results.md").write_text("\n".join(lines) + "\n")
    env = make_env("learned", a.vehicles, duration, render=True)
    record_gif(egos["learned"], env, a.out / "episode.gif", seed=2000 + a.seed, max_frames=10 if a.short else 80)
    env.close()
    print("\n".join(lines))
    print(f"wrote {a.out / 'results.md'} and {a.out / 'episode.gif'}")


if __name__ == "__main__":
    main()
