"""The policy's memory between online decisions: per-agent features of their last decisions, kept by agent id.

An online host (:class:`~r1sim_sumo.sim.policy_driver.PolicyDriver`) decides every 0.5 s for the agents it sees now.
:class:`PolicyState` owns what the model remembers of them: per agent id its per-layer features of its last
``temporal_span - 1`` decisions (the rows of the model's rollout KV cache). An agent seen at the previous decision
(0.5 s ago, at the position it now reports 0.5 s back) costs one policy step and attends to up to 2.5 s of its own
past, as in batched rollouts; agents seen for the first time (or after a gap, or whose remembered position does not
match: a reused id) are warmed up from their two history tokens. Only this module lays remembered features into a
``RolloutCache``; simulator code never touches cache slots.

Frames: internal (metres, x east, y north, yaw radians CCW from +x, box centres).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from r1sim_sumo.tokens.constants import CURRENT_POSE

MEMORY_POSE_TOL_M = 0.5  # [m] a remembered agent must be where the history says it was 0.5 s ago


@dataclass
class Remembered:
    """Every agent kept from the last decision, stacked: ``rows`` maps an agent id to its row; per row its features
    of its last ``W - 1`` decisions (oldest first) and its actual position at the last one."""

    rows: dict[str, int]
    t_xn: torch.Tensor  # [L, n, W-1, D] per-layer normalised features
    t_pose: torch.Tensor  # [n, W-1, 4] packed poses
    t_valid: torch.Tensor  # [n, W-1] bool
    xy: np.ndarray  # [n, 2] actual position [m] at the last decision


class PolicyState:
    """Per-agent memory of ``model`` between decisions made exactly every 0.5 s of simulated time.

    :param model: a ``TrafficPolicy`` (``init_rollout`` / ``step``, ``config.temporal_span``).
    :param device: torch device of the model.
    """

    def __init__(self, model, device: str = "cpu"):
        self.model = model
        self.device = device
        self.memory: Remembered | None = None
        self.last_known = 0  # agents whose remembered features the last step reused

    def reset(self) -> None:
        """Forget every agent (e.g. a new episode)."""
        self.memory = None

    def rows(self, ids: list[str], back_xy: np.ndarray, back_ok: np.ndarray) -> np.ndarray:
        """``[A]`` row of each agent in the memory, -1 where it is not known: agents remembered from the last decision
        and now reported ``back_xy [A, 2]`` [m] 0.5 s ago (``back_ok [A]``: the history holds that state and every one
        since) within :data:`MEMORY_POSE_TOL_M` of where they were then."""
        m = self.memory
        if m is None or not len(ids):
            return np.full(len(ids), -1, np.int64)
        rows = np.fromiter((m.rows.get(v, -1) for v in ids), np.int64, len(ids))
        d = np.hypot(*(m.xy[np.maximum(rows, 0)] - np.asarray(back_xy, np.float64)).T)
        return np.where((rows >= 0) & np.asarray(back_ok, bool) & (d < MEMORY_POSE_TOL_M), rows, -1)

    def known(self, ids: list[str], back_xy: np.ndarray, back_ok: np.ndarray) -> np.ndarray:
        """``[A]`` bool: the agents :meth:`rows` finds in the memory."""
        return self.rows(ids, back_xy, back_ok) >= 0

    @torch.no_grad()
    def step(self, ids: list[str], now_xy: np.ndarray, back_xy: np.ndarray, back_ok: np.ndarray, batch,
             warm_up: Callable[[np.ndarray], object], map_ctx) -> torch.Tensor:
        """Logits ``[1, A, V]`` of the current decision of the agents of the one-scene ``batch`` (``ids [A]``, positions
        ``now_xy [A, 2]`` [m] now and ``back_xy`` 0.5 s ago), reusing remembered features; remembers the agents valid now.

        The current step runs as step ``W - 1`` of a rollout cache whose ``W - 1`` earlier slots hold, per agent, its
        remembered steps (oldest first) or, for a fresh agent, its two history steps computed now by
        ``init_rollout(warm_up(fresh))`` (``warm_up`` returns the batch of the fresh agents ``fresh [n]`` alone).
        Remembered rows are gathered and stored with one indexing op per tensor (no per-agent copies).
        """
        model, c, dev = self.model, self.model.config, self.device
        W = c.temporal_span
        rows = self.rows(ids, back_xy, back_ok)
        known = np.flatnonzero(rows >= 0)
        fresh = np.flatnonzero(rows < 0)
        self.last_known = len(known)
        cache = model.init_rollout(batch, num_rollouts=1, upto_step=0, map_ctx=map_ctx, last_step=W - 1)  # empty cache of all agents, slots up to this decision's step
        slot0 = W - 1  # step W-1 attends to slots W-1 .. 2W-2 (the W-1 past ones, then itself in slot 2W-2)
        past = slice(slot0, slot0 + W - 1)
        if len(fresh):  # warm-up: the fresh agents' 2 history steps become their 2 newest past slots
            warm = model.init_rollout(warm_up(fresh), num_rollouts=1, upto_step=CURRENT_POSE, map_ctx=map_ctx,
                                      last_step=CURRENT_POSE - 1)
            fi, newest = torch.from_numpy(fresh).to(dev), slice(slot0 + W - 3, slot0 + W - 1)
            cache.t_xn[:, 0, fi, newest] = warm.t_xn[:, 0, :, W - 1 : W + 1]
            cache.t_pose[0, fi, newest] = warm.t_pose[0, :, W - 1 : W + 1]
            cache.t_valid[0, fi, newest] = warm.t_valid[0, :, W - 1 : W + 1]
        if len(known):
            m = self.memory
            ki, mi = torch.from_numpy(known).to(dev), torch.from_numpy(rows[known]).to(dev)
            cache.t_xn[:, 0, ki, past] = m.t_xn[:, mi]
            cache.t_pose[0, ki, past] = m.t_pose[mi]
            cache.t_valid[0, ki, past] = m.t_valid[mi]
        cache.next_step = W - 1
        prev = torch.where(batch.agent_token_valid[:, :, CURRENT_POSE - 1], batch.agent_token[:, :, CURRENT_POSE - 1], -1)  # [1, A]
        valid = batch.pose_valid[:, :, CURRENT_POSE] & batch.agent_mask
        before = torch.where(batch.agent_token_valid[:, :, CURRENT_POSE - 2], batch.agent_token[:, :, CURRENT_POSE - 2], -1)
        logits = model.step(cache, W - 1, prev, batch.pose_xy[:, :, CURRENT_POSE], batch.pose_yaw[:, :, CURRENT_POSE], valid,
                            before_token=before)
        # remember the newest W-1 steps of every agent valid now (advanced indexing copies them out of the cache)
        vi = np.flatnonzero(valid[0].cpu().numpy())
        cur = slot0 + W - 1
        newest_w = slice(cur - (W - 2), cur + 1)
        vt = torch.from_numpy(vi).to(dev)
        self.memory = Remembered({ids[i]: j for j, i in enumerate(vi)}, cache.t_xn[:, 0, vt, newest_w],
                                 cache.t_pose[0, vt, newest_w], cache.t_valid[0, vt, newest_w],
                                 np.asarray(now_xy, np.float64)[vi].copy())
        return logits
