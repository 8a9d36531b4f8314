"""Steady-history augmentation: a vehicle that speeds up on the log is shown a steady-speed past (issue 19, session 16).

Why: in SUMO's data a vehicle below its desired speed is almost always already speeding up (Krauss accelerates at
once when the road clears), so "steady history, free road, desired speed far above" is a state the log never shows.
A policy trained on it copies its recent speed there: a lone car held at a steady 5-15 m/s on an empty 33 m/s
motorway lane drives at 20 m/s 10 s later, some cars stay near their start speed (SUMO: 33 m/s;
``scripts/diag_steady_start.py``), and in the drop-in a queue's discharge does not speed back up (the merge jams of
``docs/simulate``). Here, for a vehicle whose next token speeds up, the tokens and poses
*before* a step ``t0`` are rewritten to a straight, constant-speed approach ending at its real pose ``t0``: the past
says "steady", the label at ``t0`` (the real next token) says "speed up". Only the rewritten steps' labels are dropped;
other agents see the rewritten poses (a steady approach along the same heading).

Frames and units: world frame, metres, radians, tokens of 0.5 s (:data:`r1sim_sumo.tokens.constants.TOKEN_DT_S`).
"""

from __future__ import annotations

import numpy as np
import torch

from r1sim_sumo.tokens.constants import TOKEN_DT_S

SPEED_STEP_MPS = 0.1  # resolution of the straight-token table [m/s]
MAX_TABLE_SPEED_MPS = 60.0
MIN_SPEED_GAIN_MPS = 0.4  # the token at t0 is at least this much faster than the one before it (~0.8 m/s^2)
MIN_DESIRED_MARGIN_MPS = 2.0  # and the vehicle is at least this much below its desired speed (where known)
VEHICLE = 0


def straight_token_table(vocab_traj: np.ndarray) -> torch.Tensor:
    """``[n]`` int64: for speed ``i * SPEED_STEP_MPS`` [m/s], the vehicle token closest to driving straight at that
    constant speed (mean position error over the token's frames, start-pose frame). ``vocab_traj``: ``[V, F, 3]``."""
    tr = np.asarray(vocab_traj, np.float64)
    frames = tr.shape[1]
    t = np.arange(frames) * (TOKEN_DT_S / (frames - 1))  # [s] time of each frame
    v = np.arange(0.0, MAX_TABLE_SPEED_MPS + 1e-9, SPEED_STEP_MPS)
    ideal_x = v[:, None] * t[None, :]  # [n, F]
    err = np.hypot(tr[None, :, :, 0] - ideal_x[:, None, :], tr[None, :, :, 1]).mean(-1)  # [n, V]
    return torch.from_numpy(err.argmin(1).astype(np.int64))


def steady_history(batch, targets: torch.Tensor | None, prob: float, gen: torch.Generator, straight: torch.Tensor,
                   at: int | None = None, min_run: int = 1):
    """Rewrite the past of speeding-up vehicles to a steady speed; returns ``(batch, targets)``.

    Each real vehicle with at least one eligible step is picked with probability ``prob``; its ``t0`` is drawn
    uniformly among its eligible steps: tokens ``0 .. t0`` and poses ``0 .. t0 + 1`` valid, token ``t0`` at least
    :data:`MIN_SPEED_GAIN_MPS` faster (mean speed over the token) than token ``t0 - 1``, whose speed ``v`` is at least
    :data:`MIN_DESIRED_MARGIN_MPS` below the desired speed where known. Poses ``s < t0`` move to
    ``pose[t0] - (t0 - s) * 0.5 s * v`` along the heading at ``t0`` (that heading too), tokens ``s < t0`` become the
    straight token at ``v`` (``straight``, :func:`straight_token_table`), and their labels become -1 (ignored).
    ``targets``: the noised-matching labels ``[B, A, T]`` or None (then the labels are the batch's tokens, copied
    before the rewrite). Draws nothing from ``gen`` when ``prob`` is 0.

    ``at``: only step ``at`` may be ``t0`` (closed-loop fine-tuning: ``at = CURRENT_POSE``, the first token the policy
    rolls out, so that the rollout starts from a steady past while the reference speeds up; poses from ``at`` on, the
    reference the reward compares with, are not touched).

    ``min_run``: ``t0`` must start a run of at least this many tokens that each speed up by
    :data:`MIN_SPEED_GAIN_MPS` (1 = any single speed-up). In SUMO's log a quarter to two fifths of a steady motorway
    vehicle's first speed-ups revert at the next token (``scripts/speed_up_runs.py``), so with 1 the augmentation
    also shows "steady, one step up, step back"; with 2 only speed-ups that last are shown after a steady past (run
    sr2_a, session 27: it did not change the policy's step back at its second decision,
    ``scripts/probe_token_distribution.py --decision 2``)."""
    if prob <= 0:
        return batch, targets
    tok, tv = batch.agent_token, batch.agent_token_valid.bool()
    B, A, T = tok.shape
    xy, yaw, pv = batch.pose_xy, batch.pose_yaw, batch.pose_valid.bool()
    speed = torch.linalg.vector_norm(xy[:, :, 1:T + 1] - xy[:, :, :T], dim=-1) / TOKEN_DT_S  # [B, A, T] mean over token
    ok = tv & pv[:, :, :T] & pv[:, :, 1:T + 1]
    prefix_ok = ok.int().cumprod(-1).bool()  # tokens 0..t all valid
    gain = torch.zeros_like(speed, dtype=torch.bool)
    gain[:, :, 1:] = speed[:, :, 1:] - speed[:, :, :-1] >= MIN_SPEED_GAIN_MPS
    v_prev = torch.zeros_like(speed)
    v_prev[:, :, 1:] = speed[:, :, :-1]
    desired = batch.agent_desired_speed.unsqueeze(-1)  # [B, A, 1] NaN = unknown
    below = torch.isnan(desired) | (v_prev <= desired - MIN_DESIRED_MARGIN_MPS)
    vehicle = batch.agent_mask.bool() & (batch.agent_type == VEHICLE)
    run = gain.clone()
    for k in range(1, int(min_run)):  # the next k tokens speed up too (and are valid)
        run[:, :, : T - k] &= gain[:, :, k:] & ok[:, :, k:]
        run[:, :, T - k:] = False
    elig = prefix_ok & run & below & vehicle.unsqueeze(-1)
    elig[:, :, 0] = False
    if at is not None:
        if not 1 <= at < T:
            raise ValueError(f"steady_history: at={at} must be a token step in 1..{T - 1}")
        only = torch.zeros(T, dtype=torch.bool)
        only[at] = True
        elig = elig & only
    pick = (torch.rand(B, A, generator=gen) < prob) & elig.any(-1)  # [B, A]
    score = torch.rand(B, A, T, generator=gen).masked_fill(~elig, -1.0)
    t0 = score.argmax(-1)  # [B, A]
    if not bool(pick.any()):
        return batch, targets
    labels = (batch.agent_token if targets is None else targets).clone()
    tok, xy, yaw = tok.clone(), xy.clone(), yaw.clone()
    b, a = pick.nonzero(as_tuple=True)
    t = t0[b, a]
    v = v_prev[b, a, t]  # [n] steady speed [m/s]
    h = yaw[b, a, t]
    start = xy[b, a, t]  # [n, 2] the real pose at t0
    direction = torch.stack([torch.cos(h), torch.sin(h)], -1)
    sid = straight[(v / SPEED_STEP_MPS).round().long().clamp(0, len(straight) - 1)]
    for s in range(T - 1):  # steps before t0 (s < t <= T - 1)
        m = s < t
        if not bool(m.any()):
            continue
        bb, aa = b[m], a[m]
        back = ((t[m] - s).to(xy.dtype) * TOKEN_DT_S * v[m]).unsqueeze(-1)
        xy[bb, aa, s] = start[m] - back * direction[m]
        yaw[bb, aa, s] = h[m]
        tok[bb, aa, s] = sid[m]
        labels[bb, aa, s] = -1
    return batch._replace(agent_token=tok, pose_xy=xy, pose_yaw=yaw), labels
