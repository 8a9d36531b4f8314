"""Widen a trained policy without changing what it predicts (Net2WiderNet for :class:`TrafficPolicy`).

A wider model trained from scratch throws away everything the narrow one learned (session 37: ~10 minutes of training
on a lent H200, 72M agent-tokens, gave a hidden-128 policy a held-out NLL of 1.30 against the nano's 0.99). Widening instead starts the wider model *at* the
narrow one's predictions:

* every hidden-sized axis (the residual stream ``D``, the feed-forward width ``mult * D``, the edge features
  ``[content D, relative D]``) is widened block by block: each block of ``D`` values is followed by its copy, so the
  wider model's residual stream is ``[x, x]`` where the narrow one's is ``x``;
* parameters that *produce* such an axis (rows of a linear map, embedding tables, biases, LayerNorm scales) are copied
  into both blocks; LayerNorm over ``[x, x]`` has the same mean and variance as over ``x``;
* parameters that *consume* it (columns of a linear map, the edge-space key / value maps ``w_k`` / ``w_v``) are halved
  over the two copies, as ``W/2 + eps`` and ``W/2 - eps``: on duplicated inputs the result is exactly ``W x`` whatever
  ``eps``, and ``eps`` (``noise`` x the tensor's standard deviation) makes the two copies' gradients differ, so that
  training can use the new units (without it they stay twins except for dropout);
* the heads are repeated: with ``factor * H`` heads of the same size, head ``h`` of the wider model's block ``j`` sees
  block ``j`` of the queries, i.e. the narrow model's head ``h``.

The logits are those of the narrow model up to float rounding (``tests/test_widen.py``). Command line::

    python -m r1sim_sumo.model.widen r1sim-nano runs/nano_x2 [--factor 2] [--noise 0.01]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from torch import Tensor, nn

from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.policy import TrafficPolicy


def _dup_blocks(t: Tensor, axis: int, block: int, factor: int) -> Tensor:
    """Each block of ``block`` entries along ``axis`` followed by ``factor - 1`` copies of itself."""
    n = t.shape[axis]
    v = t.movedim(axis, 0).reshape(n // block, 1, block, *t.shape[:axis], *t.shape[axis + 1 :])
    v = v.expand(-1, factor, *v.shape[2:]).reshape(n * factor, *t.shape[:axis], *t.shape[axis + 1 :])
    return v.movedim(0, axis).contiguous()


def _split_blocks(t: Tensor, axis: int, block: int, factor: int, noise: float, gen: torch.Generator) -> Tensor:
    """``t`` consumed by a duplicated axis: each block becomes ``factor`` parts ``t / factor + eps_j`` with
    ``sum_j eps_j = 0`` (``eps`` ~ ``noise * std(t)``), so the parts sum to ``t`` on equal inputs."""
    out = _dup_blocks(t, axis, block, factor) / factor
    if noise > 0 and t.numel() > 1:
        eps = torch.randn(out.shape, generator=gen, dtype=out.dtype) * (noise * float(t.std()))
        n = t.shape[axis]
        e = eps.movedim(axis, 0).reshape(n // block, factor, block, -1)
        e = e - e.mean(1, keepdim=True)  # the parts' noise sums to zero within each block
        out = out + e.reshape(out.movedim(axis, 0).shape).movedim(0, axis)
    return out


def widen_model(model: TrafficPolicy, token_traj, factor: int = 2, noise: float = 0.01, seed: int = 0) -> TrafficPolicy:
    """A :class:`TrafficPolicy` with ``factor`` x the hidden width and heads of ``model`` (same head size, layers,
    neighbourhoods and vocabulary: ``token_traj``, the per-type ``[V_t, 6, 3]`` trajectories it was built with) that
    gives ``model``'s logits (module text). ``noise``: relative size of the symmetry-breaking split of consumed
    weights (0: exact twins)."""
    if factor < 2:
        raise ValueError(f"factor {factor}: must be >= 2")
    c = model.config
    D = c.hidden_dim
    cfg = PolicyConfig.from_dict({**c.to_dict(), "hidden_dim": D * factor, "num_heads": c.num_heads * factor})
    wide = TrafficPolicy(cfg, token_traj)
    gen = torch.Generator().manual_seed(seed)
    modules = dict(wide.named_modules())
    new_state = {}
    old_state = model.state_dict()
    for name, new in wide.state_dict().items():
        old = old_state[name]
        if old.shape == new.shape:
            new_state[name] = old.clone()
            continue
        owner = modules[name.rsplit(".", 1)[0]] if "." in name else wide
        leaf = name.rsplit(".", 1)[-1]
        grown = [a for a in range(old.dim()) if new.shape[a] == factor * old.shape[a] and old.shape[a] != new.shape[a]]
        if any(new.shape[a] != old.shape[a] for a in range(old.dim()) if a not in grown):
            raise ValueError(f"{name}: {tuple(old.shape)} -> {tuple(new.shape)} is not a widening by {factor}")
        t = old.clone()
        if leaf in ("w_k", "w_v"):  # [H, dh, De] / [H, De, dh]: repeat the heads, split the consumed edge axis
            t = torch.cat([t] * factor, 0)
            t = _split_blocks(t, 2 if leaf == "w_k" else 1, D, factor, noise, gen)
        elif isinstance(owner, nn.Linear) and leaf == "weight":  # [out, in]
            if 0 in grown:
                t = _dup_blocks(t, 0, D, factor)
            if 1 in grown:
                t = _split_blocks(t, 1, D, factor, noise, gen)
        else:  # embedding tables [V, D], biases, LayerNorm scales: produced values, copied
            for a in grown:
                t = _dup_blocks(t, a, D, factor)
        if t.shape != new.shape:
            raise ValueError(f"{name}: widened to {tuple(t.shape)}, the wider model has {tuple(new.shape)}")
        new_state[name] = t
    wide.load_state_dict(new_state)
    return wide.train(model.training)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", help="checkpoint folder or shipped name (r1sim-nano)")
    ap.add_argument("out", help="folder to write the wider checkpoint to (must not exist)")
    ap.add_argument("--factor", type=int, default=2, help="width and heads multiplier (default 2)")
    ap.add_argument("--noise", type=float, default=0.01, help="symmetry-breaking split, relative to each tensor's std")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    from r1sim_sumo.model.checkpoint import load_policy, save_checkpoint

    if Path(a.out).exists():
        sys.exit(f"{a.out}: exists; choose another folder (nothing is overwritten)")
    policy = load_policy(a.checkpoint)
    traj = [torch.from_numpy(policy.vocab.traj[t]) for t in range(policy.config.num_agent_types)]
    wide = widen_model(policy.model, traj, a.factor, a.noise, a.seed)
    n_old = sum(p.numel() for p in policy.model.parameters())
    n_new = sum(p.numel() for p in wide.parameters())
    # the training record stays the narrow model's (what it saw is what the wider one starts from), plus how it grew
    record = {**policy.info.get("training", {}), "widened_from": {"checkpoint": str(a.checkpoint), "factor": a.factor,
                                                                   "noise": a.noise, "seed": a.seed}}
    save_checkpoint(a.out, wide, policy.vocab, extra=record)
    print(f"{a.out}: hidden {policy.config.hidden_dim} -> {wide.config.hidden_dim}, heads {policy.config.num_heads} -> "
          f"{wide.config.num_heads}, {n_old:,} -> {n_new:,} parameters")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
