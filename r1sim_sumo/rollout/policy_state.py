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
class AgentMemory:
    """One agent's features of its last ``W - 1`` decisions (oldest first) and its position at the last one."""

    t_xn: torch.Tensor  # [L, W-1, D] per-layer normalised features
    t_pose: torch.Tensor  # [W-1, 4] packed poses
    t_valid: torch.Tensor  # [W-1] bool
    xy: np.ndarray  # [2] actual position [m] at the last decision


class PolicyState:
    """Per-agent memory of ``model`` between decisions made exactly every 0.5 s of simulated time.

    :param model: a ``TrafficPolicy`` (``init_rollout`` / ``step``, ``config.temporal_span``).
    :param device: torch device of the model.
    """

    def __init__(self, model, device: str = "cpu"):
        self.model = model
        self.device = device
        self.memory: dict[str, AgentMemory] = {}
        self.last_known = 0  # agents whose remembered features the last step reused

    def reset(self) -> None:
        """Forget every agent (e.g. a new episode)."""
        self.memory.clear()

    def known(self, ids: list[str], back_xy: np.ndarray, back_ok: np.ndarray) -> np.ndarray:
        """``[A]`` bool: agents remembered from the last decision and now reported ``back_xy [A, 2]`` [m] 0.5 s ago
        (``back_ok [A]``: the history holds that state and every one since) within :data:`MEMORY_POSE_TOL_M`."""
        out = np.zeros(len(ids), bool)
        for i, vid in enumerate(ids):
            m = self.memory.get(vid)
            if m is not None and back_ok[i]:
                out[i] = np.hypot(*(m.xy - back_xy[i])) < MEMORY_POSE_TOL_M
        return out

    @torch.no_grad()
    def step(self, ids: list[str], now_xy: np.ndarray, back_xy: np.ndarray, back_ok: np.ndarray, batch,
             warm_up: Callable[[np.ndarray], object], map_ctx) -> torch.Tensor:
        """Logits ``[1, A, V]`` of the current decision of the agents of the one-scene ``batch`` (``ids [A]``, positions
        ``now_xy [A, 2]`` [m] now and ``back_xy`` 0.5 s ago), reusing remembered features; remembers the agents valid now.

        The current step runs as step ``W - 1`` of a rollout cache whose ``W - 1`` earlier slots hold, per agent, its
        remembered steps (oldest first) or, for a fresh agent, its two history steps computed now by
        ``init_rollout(warm_up(fresh))`` (``warm_up`` returns the batch of the fresh agents ``fresh [n]`` alone).
        """
        model, c, dev = self.model, self.model.config, self.device
        W, L, D = c.temporal_span, c.agent_layers, c.hidden_dim
        A = len(ids)
        known = self.known(ids, back_xy, back_ok)
        self.last_known = int(known.sum())
        t_xn = torch.zeros(L, 1, A, W - 1, D, device=dev)
        t_pose = torch.zeros(1, A, W - 1, 4, device=dev)
        t_valid = torch.zeros(1, A, W - 1, dtype=torch.bool, device=dev)
        fresh = np.flatnonzero(~known)
        if len(fresh):  # warm-up: the fresh agents' 2 history steps become their 2 newest past slots
            warm = model.init_rollout(warm_up(fresh), num_rollouts=1, upto_step=CURRENT_POSE, map_ctx=map_ctx)
            fi = torch.from_numpy(fresh).to(dev)
            t_xn[:, :, fi, W - 3:] = warm.t_xn[:, :, :, W - 1 : W + 1]
            t_pose[:, fi, W - 3:] = warm.t_pose[:, :, W - 1 : W + 1]
            t_valid[:, fi, W - 3:] = warm.t_valid[:, :, W - 1 : W + 1]
        cache = model.init_rollout(batch, num_rollouts=1, upto_step=0, map_ctx=map_ctx)  # empty cache of all agents
        slot0 = W - 1  # step W-1 uses slots W-1 .. 2W-2; the current step sits in slot 2W-2
        prev = torch.where(batch.agent_token_valid[:, :, CURRENT_POSE - 1], batch.agent_token[:, :, CURRENT_POSE - 1], -1)  # [1, A]
        for i in np.flatnonzero(known):
            m = self.memory[ids[i]]
            t_xn[:, 0, i], t_pose[0, i], t_valid[0, i] = m.t_xn, m.t_pose, m.t_valid
        n_slots = cache.t_xn.shape[3]
        full_xn = torch.zeros(L, 1, A, n_slots, D, device=dev)
        full_pose = torch.zeros(1, A, n_slots, 4, device=dev)
        full_valid = torch.zeros(1, A, n_slots, dtype=torch.bool, device=dev)
        full_xn[..., slot0 : slot0 + W - 1, :] = t_xn
        full_pose[:, :, slot0 : slot0 + W - 1] = t_pose
        full_valid[:, :, slot0 : slot0 + W - 1] = t_valid
        cache.t_xn, cache.t_pose, cache.t_valid, cache.next_step = full_xn, full_pose, full_valid, W - 1
        valid = batch.pose_valid[:, :, CURRENT_POSE] & batch.agent_mask
        logits = model.step(cache, W - 1, prev, batch.pose_xy[:, :, CURRENT_POSE], batch.pose_yaw[:, :, CURRENT_POSE], valid)
        # remember the newest W-1 steps of every agent valid now
        cur = slot0 + W - 1
        keep_xn = cache.t_xn[:, 0, :, cur - (W - 2) : cur + 1]  # [L, A, W-1, D]
        keep_pose = cache.t_pose[0, :, cur - (W - 2) : cur + 1]
        keep_valid = cache.t_valid[0, :, cur - (W - 2) : cur + 1]
        now_valid = valid[0].cpu().numpy()
        self.memory = {ids[i]: AgentMemory(keep_xn[:, i].clone(), keep_pose[i].clone(), keep_valid[i].clone(), now_xy[i].copy())
                       for i in range(A) if now_valid[i]}
        return logits
