"""Two costs of a GRPO iteration on large scenes, each against what it replaced (session 23), side by side in one run.

1. Rollout neighbour search: the shipped policy rolled out (the engine GRPO samples with) with the k-d tree
   neighbour search of ``model.layers.knn`` on large CPU searches (default) vs the brute-force distance matrix
   (``KD_MIN_PAIRS`` raised so that it is never used). The scenes are ``model.synthetic.synthetic_batch`` ones with
   many agents and map tokens, as the urban scenes of the default recipe (130 agents, ~6,000 map tokens).
2. Reward collision flags:

   ``r1sim_sumo.train.rewards.token_collisions`` checks every 10 Hz state of every rollout token for box overlaps. It
first keeps the pairs whose centres are closer than the sum of the boxes' half-diagonals and runs the exact
separating-axis test only on those; the reference row is the plain all-pairs test (``geometry.boxes_overlap``
broadcast over ``[G, B, T, A, A]``, what the function did before session 23). The scene imitates one GRPO iteration
of the default recipe on a large urban scene: G rollouts x B scenes x A agents x 16 tokens (80 states), agents on a
grid of streets 400 m x 400 m (every 40 m), cars and trucks, driving 0-15 m/s along their street; a few pairs
overlap. Both methods must give identical flags (``flags_equal``).

Run: ``python benchmarks/run.py --only grpo_costs [--quick]``.
"""

from __future__ import annotations

import time

import torch


def _scene(G: int, B: int, A: int, F: int = 16, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    N = 5 * F + 1
    street = torch.randint(0, 11, (B, A), generator=g).float() * 40.0  # which street [m]
    along = torch.rand(B, A, generator=g) * 400.0  # position along it [m]
    vertical = torch.rand(B, A, generator=g) < 0.5
    sign = torch.where(torch.rand(B, A, generator=g) < 0.5, 1.0, -1.0)
    speed = torch.rand(G, B, A, 1, generator=g) * 15.0  # [m/s]
    t = torch.arange(N).float() * 0.1
    s = along[None, ..., None] + sign[None, ..., None] * speed * t  # [G, B, A, N]
    lane = street[None, ..., None] + sign[None, ..., None] * 1.6 + torch.randn(G, B, A, N, generator=g) * 0.3
    x = torch.where(vertical[None, ..., None], lane, s)
    y = torch.where(vertical[None, ..., None], s, lane)
    base = torch.where(vertical, torch.pi / 2, 0.0) + torch.where(sign < 0, torch.pi, 0.0)
    yaw = base[None, ..., None].expand(G, B, A, N) + torch.randn(G, B, A, N, generator=g) * 0.05
    xy = torch.stack([x, y], -1) + 1000.0  # world coordinates away from the origin
    valid = torch.ones(G, B, A, N, dtype=torch.bool)
    truck = torch.rand(B, A, generator=g) < 0.15
    size = torch.stack([torch.where(truck, 12.0, 4.8), torch.where(truck, 2.5, 1.9)], -1)
    return xy, yaw, valid, size


def _all_pairs(xy, yaw, valid, size):
    from r1sim_sumo.geometry import boxes_overlap

    G, B, A, N, _ = xy.shape
    F = (N - 1) // 5
    x, y = xy[..., 1:, 0].movedim(2, -1), xy[..., 1:, 1].movedim(2, -1)
    a, v = yaw[..., 1:].movedim(2, -1), valid[..., 1:].movedim(2, -1)
    L, W = size[None, :, None, :, 0], size[None, :, None, :, 1]
    ov = boxes_overlap(x.unsqueeze(-1), y.unsqueeze(-1), a.unsqueeze(-1), L.unsqueeze(-1), W.unsqueeze(-1),
                       x.unsqueeze(-2), y.unsqueeze(-2), a.unsqueeze(-2), L.unsqueeze(-2), W.unsqueeze(-2))
    ok = v.unsqueeze(-1) & v.unsqueeze(-2) & ~torch.eye(A, dtype=torch.bool)
    return (ov & ok).any(-1).reshape(G, B, F, 5, A).any(3).movedim(2, -1)


def _time(fn, reps: int) -> tuple[float, torch.Tensor]:
    out = fn()  # warm-up
    t0 = time.perf_counter()
    for _ in range(reps):
        out = fn()
    return (time.perf_counter() - t0) / reps, out


def _rollout_rows(quick: bool) -> list[dict]:
    import r1sim_sumo
    from r1sim_sumo.model import layers
    from r1sim_sumo.model.synthetic import synthetic_batch
    from r1sim_sumo.rollout.engine import rollout
    from r1sim_sumo.rollout.samplers import parse_sampler

    pol = r1sim_sumo.load_policy()
    G, A, M, steps = (4, 60, 2000, 4) if quick else (32, 130, 6000, 16)
    traj = [torch.as_tensor(pol.vocab.traj[i]) for i in range(3)]
    batch = synthetic_batch(traj, num_scenes=2, num_agents=A, num_map_tokens=M, extent_m=1000.0, seed=0)
    sampler, default = parse_sampler("entropy:16,80"), layers.KD_MIN_PAIRS
    times = {}
    with torch.no_grad():  # warm-up (allocations, the map encoder), not timed
        rollout(pol.model, pol.vocab, batch, 2, sampler, generator=torch.Generator().manual_seed(0), num_steps=2)
    try:
        for name, threshold in (("distance matrix", 1 << 62), ("k-d tree", default)):
            layers.KD_MIN_PAIRS = threshold
            with torch.no_grad():
                t0 = time.perf_counter()
                rollout(pol.model, pol.vocab, batch, G, sampler, generator=torch.Generator().manual_seed(0), num_steps=steps)
                times[name] = time.perf_counter() - t0
    finally:
        layers.KD_MIN_PAIRS = default
    return [{"case": f"rollout {G} x 2 scenes x {A} agents, {M} map tokens, {steps} steps", "before": "distance matrix",
             "before_s": times["distance matrix"], "after": "k-d tree", "after_s": times["k-d tree"],
             "speedup": times["distance matrix"] / times["k-d tree"]}]


def run(quick: bool = False) -> dict:
    from r1sim_sumo.train.rewards import token_collisions

    cases = [(4, 2, 60)] if quick else [(32, 2, 60), (32, 2, 130)]
    reps = 1 if quick else 2
    rows = _rollout_rows(quick)
    for G, B, A in cases:
        args = _scene(G, B, A)
        t_all, ref = _time(lambda a=args: _all_pairs(*a), reps)
        t_new, got = _time(lambda a=args: token_collisions(*a), reps)
        rows.append({"case": f"reward collision flags {G} x {B} scenes x {A} agents, 16 tokens", "before": "all-pairs SAT",
                     "before_s": t_all, "after": "prefilter + SAT", "after_s": t_new, "speedup": t_all / t_new,
                     "flags_equal": bool(torch.equal(ref, got)), "colliding_token_fraction": float(ref.float().mean())})
    return {"title": "GRPO iteration costs on large scenes: rollout neighbour search, reward collision flags", "rows": rows,
            "notes": [f"torch threads: {torch.get_num_threads()}; collision flags: seconds per call, mean of {reps} after a "
                      "warm-up, 16 tokens x 5 states per rollout; rollouts: one call each, shipped r1sim-nano, "
                      "entropy:16,80 sampler (GRPO's)."]}


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick=True), indent=2))
