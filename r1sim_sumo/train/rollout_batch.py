"""Scene batches rebuilt from rollouts, shared by the GRPO learner (:mod:`r1sim_sumo.train.grpo`) and closed-loop
SFT (:mod:`r1sim_sumo.train.sft`): the teacher-forced recomputation runs on a batch whose future is the rollouts'.
"""

from __future__ import annotations

import torch

from r1sim_sumo.tokens.constants import CURRENT_POSE


def rebuild_batch(batch, token: torch.Tensor, pose_xy: torch.Tensor, pose_yaw: torch.Tensor, valid: torch.Tensor):
    """A batch of ``G * B`` scenes (row ``g * B + b``) whose future is the rollouts' instead of the reference.

    :param batch: the ``B`` scenes the rollouts started from (history tokens/poses and the map are kept).
    :param token: ``[G, B, A, F]`` rolled-out tokens (-1 invalid); ``pose_xy [G, B, A, F+1, 2]``,
        ``pose_yaw [G, B, A, F+1]``, ``valid [G, B, A, F+1]``: boundary poses 2 .. 2+F.
    Tokens/poses after ``2 + F`` (when ``F < 16``) are marked invalid.
    """
    G, B, A, F = token.shape
    S, n = G * B, CURRENT_POSE + F
    rb = type(batch)(*(t.repeat(G, *([1] * (t.dim() - 1))) for t in batch))
    tok, tv = rb.agent_token.clone(), rb.agent_token_valid.clone()
    xy, yaw, pv = rb.pose_xy.clone(), rb.pose_yaw.clone(), rb.pose_valid.clone()
    t = token.reshape(S, A, F)
    tok[:, :, CURRENT_POSE:n] = t
    tok[:, :, n:] = -1
    tv[:, :, CURRENT_POSE:n] = t >= 0
    tv[:, :, n:] = False
    xy[:, :, CURRENT_POSE : n + 1] = pose_xy.reshape(S, A, F + 1, 2)
    yaw[:, :, CURRENT_POSE : n + 1] = pose_yaw.reshape(S, A, F + 1)
    pv[:, :, CURRENT_POSE : n + 1] = valid.reshape(S, A, F + 1).bool()
    pv[:, :, n + 1 :] = False
    return rb._replace(agent_token=tok, agent_token_valid=tv, pose_xy=xy, pose_yaw=yaw, pose_valid=pv)


def index_batch(batch, idx: torch.Tensor):
    """Scenes ``idx`` of a batch (every field indexed on its first dim)."""
    return type(batch)(*(t[idx] for t in batch))
