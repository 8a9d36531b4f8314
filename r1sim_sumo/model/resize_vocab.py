"""A trained policy carried over to a vocabulary that appends tokens (:mod:`r1sim_sumo.tokens.vocab_extend`).

Every weight is copied; the two that are indexed by token id grow:

* ``token_emb`` (learned part of a previous token's embedding, rows: vehicle ids, cyclist ids, pedestrian ids, then
  one start token per type): old rows keep their ids under the new type offsets, a new token's row is its nearest old
  token's (its shape part, ``token_mlp`` of the token's trajectory, is computed from the new trajectory anyway);
* the head's last linear layer (one logit per id): a new token starts with its nearest old token's weights and bias,
  and each old token and the new tokens copied from it share its probability: their biases are lowered by
  ``log(1 + copies)``. The extended model's distribution over *groups* (an old token and its copies) then equals the
  old model's over the old token, so training starts from the old model's behaviour and learns to tell them apart.
"""

from __future__ import annotations

import numpy as np
import torch

from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.policy import TrafficPolicy
from r1sim_sumo.tokens.motion_vocab import TYPES, VEHICLE
from r1sim_sumo.tokens.vocab_extend import nearest_old_token


def extend_policy_vocab(model: TrafficPolicy, old_vocab, new_vocab) -> TrafficPolicy:
    """A new :class:`TrafficPolicy` for ``new_vocab`` (old vehicle ids a prefix of the new ones, other types equal)
    holding ``model``'s weights as described in the module docstring."""
    old_sizes, new_sizes = tuple(old_vocab.sizes), tuple(new_vocab.sizes)
    if any(o != n for t, (o, n) in enumerate(zip(old_sizes, new_sizes, strict=True)) if t != VEHICLE):
        raise ValueError(f"only the vehicle vocabulary may grow: sizes {old_sizes} -> {new_sizes}")
    base = old_sizes[VEHICLE]
    if new_sizes[VEHICLE] < base or not np.array_equal(new_vocab.traj[VEHICLE][:base], old_vocab.traj[VEHICLE]):
        raise ValueError("the new vehicle vocabulary must start with the old one's tokens (same ids, same paths)")
    cfg = PolicyConfig(**{**model.config.to_dict(), "vocab_sizes": new_sizes})
    new = TrafficPolicy(cfg, [torch.from_numpy(new_vocab.traj[t]) for t in TYPES])
    src = model.state_dict()
    dst = new.state_dict()
    near = torch.from_numpy(nearest_old_token(new_vocab, base))  # [n_new] old vehicle id of each new token
    n_new = len(near)
    for k, v in src.items():
        if k in dst and dst[k].shape == v.shape:
            dst[k] = v.clone()
    # token_emb rows: [vehicle | cyclist | pedestrian | start tokens]
    emb_k = "token_emb.weight"
    old_emb = src[emb_k]
    rows = list(range(base)) + near.tolist() + list(range(base, old_emb.shape[0]))
    dst[emb_k] = old_emb[torch.tensor(rows)].clone()
    # head: the last Linear of the head Sequential
    head_w = [k for k in src if k.startswith("head.") and k.endswith(".weight") and src[k].shape[0] == model.config.vocab_max]
    if len(head_w) != 1:
        raise ValueError(f"cannot find the token head's output layer among {head_w}")
    wk, bk = head_w[0], head_w[0][:-len("weight")] + "bias"
    W, b = src[wk], src[bk]
    Vn = cfg.vocab_max
    nW = torch.zeros(Vn, W.shape[1], dtype=W.dtype)
    nb = torch.zeros(Vn, dtype=b.dtype)
    nW[: W.shape[0]], nb[: b.shape[0]] = W, b
    nW[base:base + n_new], nb[base:base + n_new] = W[near], b[near]
    copies = torch.bincount(near, minlength=base).to(b.dtype)  # [base] new tokens copied from each old one
    share = torch.log1p(copies)
    nb[:base] -= share
    nb[base:base + n_new] -= share[near]
    dst[wk], dst[bk] = nW, nb
    new.load_state_dict(dst, strict=True)
    return new


def group_log_prob_gap(old_model, new_model, batch, base: int, near: np.ndarray) -> float:
    """Largest |log p| difference, over the batch's vehicle rows, between the old model's token probabilities and the
    new model's summed over each old token's group (itself + its copies): 0 up to float error right after
    :func:`extend_policy_vocab`. For tests and sanity checks."""
    with torch.no_grad():
        lo = torch.log_softmax(old_model(batch).float(), -1)
        ln = torch.log_softmax(new_model(batch).float(), -1)
    veh = batch.agent_type == VEHICLE
    lo, ln = lo[veh][..., :base], ln[veh]
    p = ln.exp()
    grouped = p[..., :base].clone()
    grouped.index_add_(-1, torch.from_numpy(near), p[..., base:base + len(near)])
    gap = (grouped.clamp_min(1e-30).log() - lo).abs()
    return float(gap[torch.isfinite(lo)].max()) if gap.numel() else 0.0

