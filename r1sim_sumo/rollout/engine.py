"""Batched closed-loop rollouts: G rollouts x B scenes x A agents, one batched policy step per 0.5 s token.

Flow per token step ``k`` (2..17, i.e. the 16 future tokens = 8 s), one
:func:`r1sim_sumo.rollout.kernel.token_step` for all rollouts x scenes: cached ``policy.step`` on the newest
pose only -> sampler (top-K / entropy-guided / greedy) -> chosen token -> next boundary pose by placing the
token's end pose at the current (rolled-out) pose. Agents the caller marks as log-replay (``replay_mask``)
follow their matched ground-truth tokens and poses instead, and are valid exactly where the reference is.
Simulated agents are those valid at the current pose (index 2 = state 10); they stay valid for the whole
horizon. 10 Hz states between boundary poses are decoded from the tokens' paths (``decoding``; by default each
path is retimed at one constant acceleration from the mean of the previous and current token speeds).

Records per agent per step: token, the sampler's log-probability of it (GRPO's "old" log-prob), the model
distribution's entropy [nats] and the ``K_t`` used.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from r1sim_sumo.rollout.kernel import LoopState, Replay, StepRecorder, token_step
from r1sim_sumo.rollout.samplers import Sampler
from r1sim_sumo.tokens.batch import SceneBatch
from r1sim_sumo.tokens.constants import CURRENT_POSE, N_TOK
from r1sim_sumo.tokens.matching import reconstruct_states

N_FUTURE_TOK = N_TOK - CURRENT_POSE  # 16 tokens = 8 s


@dataclass
class RolloutResult:
    """Rollouts of ``B`` scenes; leading dims ``[G, B, A]``; future token steps ``F = 16``.

    token, logp, logp_full, entropy, k: ``[G, B, A, F]`` (int64 / float32 / float32 / float32 / int64); ``logp`` is the
    sampler's log-probability (truncated, tempered distribution actually sampled from), ``logp_full`` the model's
    full-softmax log-probability of the same token (0 for agents not driven by the policy);
    pose_xy ``[G, B, A, F+1, 2]`` and pose_yaw ``[G, B, A, F+1]``: boundary poses from "now" (pose 2) to 8 s;
    xy_10hz ``[G, B, A, 5F+1, 2]``, yaw_10hz ``[G, B, A, 5F+1]``: 10 Hz states from state 10 (index 0) to 90;
    valid ``[G, B, A, F+1]`` at boundary poses; sim_mask ``[B, A]`` agents driven by the policy.
    """

    token: torch.Tensor
    logp: torch.Tensor
    logp_full: torch.Tensor
    entropy: torch.Tensor
    k: torch.Tensor
    pose_xy: torch.Tensor
    pose_yaw: torch.Tensor
    xy_10hz: torch.Tensor
    yaw_10hz: torch.Tensor
    valid: torch.Tensor
    sim_mask: torch.Tensor

    def valid_10hz(self) -> torch.Tensor:
        """Validity of the 10 Hz states ``[G, B, A, 5F+1]`` (a token's states share its end pose's validity)."""
        v = self.valid
        return torch.cat([v[..., :1], v[..., 1:].repeat_interleave(5, dim=-1)], -1)


@torch.no_grad()
def rollout(
    policy,
    vocab,
    batch: SceneBatch,
    num_rollouts: int = 32,
    sampler: Sampler | None = None,
    replay_mask: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    num_steps: int = N_FUTURE_TOK,
    decoding: str = "central",
) -> RolloutResult:
    """Roll out ``num_rollouts`` closed-loop futures for every scene of ``batch``.

    :param policy: a ``TrafficPolicy`` (``init_rollout`` / ``step``), in eval mode.
    :param vocab: the ``MotionVocab`` the policy was trained with.
    :param replay_mask: ``[B, A]`` bool, agents that follow the log instead of the policy.
    :param num_steps: future token steps (<= 16).
    :param decoding: how the 10 Hz states between boundary poses are made from the tokens
        (:func:`r1sim_sumo.rollout.kernel.decode_frames`: ``central`` retimes each token's path from the mean of
        the previous and the current token's speeds; ``tokens`` keeps the token's own frames). Boundary poses,
        tokens and log-probabilities do not depend on it.
    """
    sampler = sampler or Sampler()
    G = int(num_rollouts)
    B, A = batch.agent_mask.shape
    rep = lambda t: t.repeat(G, *([1] * (t.dim() - 1)))  # noqa: E731  [B, ...] -> [G*B, ...] (row g*B+b)
    dev = batch.agent_mask.device
    replay = torch.zeros(B, A, dtype=torch.bool, device=dev) if replay_mask is None else replay_mask.bool().to(dev)
    live0 = batch.pose_valid[:, :, CURRENT_POSE].bool() & batch.agent_mask.bool()  # [B, A]
    sim_mask = live0 & ~replay
    r_replay, r_sim = rep(replay), rep(sim_mask)
    gt_tok = rep(torch.where(batch.agent_token_valid.bool(), batch.agent_token, -1))  # [S, A, 18]
    gt_xy, gt_yaw, gt_valid = rep(batch.pose_xy), rep(batch.pose_yaw), rep(batch.pose_valid.bool())
    atype = rep(batch.agent_type.long())

    policy.eval()
    cache = policy.init_rollout(batch, num_rollouts=G, upto_step=CURRENT_POSE)
    ref = Replay(r_replay, gt_tok, gt_xy, gt_yaw, gt_valid) if replay.any() else None
    state = LoopState(gt_tok[:, :, CURRENT_POSE - 1], gt_xy[:, :, CURRENT_POSE], gt_yaw[:, :, CURRENT_POSE],
                      gt_valid[:, :, CURRENT_POSE] & rep(batch.agent_mask.bool()))
    rec = StepRecorder(state)
    for k in range(CURRENT_POSE, CURRENT_POSE + min(num_steps, N_FUTURE_TOK)):
        step = token_step(policy, cache, k, state, sampler, generator, vocab, atype, r_sim, replay=ref)
        rec.append(step)
        state = step.state
    out = rec.stack(vocab, atype, decoding)
    token, pose_xy, pose_yaw = out["token"], out["pose_xy"], out["pose_yaw"]  # [S, A, F], [S, A, F+1, 2], [S, A, F+1]
    xy10, yaw10 = out["xy_10hz"], out["yaw_10hz"]
    # replayed agents: 10 Hz states between boundaries from their own tokens placed at each GT boundary pose
    if ref is not None:
        seg_xy, seg_yaw = reconstruct_states(pose_xy[:, :, :-1], pose_yaw[:, :, :-1], token.unsqueeze(-1), vocab, atype.unsqueeze(-1).expand_as(token))
        rep_xy = torch.cat([pose_xy[:, :, :1], seg_xy[..., 1:, :].flatten(2, 3)], 2)  # [S, A, 5F+1, 2]
        rep_yaw = torch.cat([pose_yaw[:, :, :1], seg_yaw[..., 1:].flatten(2, 3)], 2)
        xy10 = torch.where(r_replay[..., None, None], rep_xy, xy10)
        yaw10 = torch.where(r_replay[..., None], rep_yaw, yaw10)

    def g(t: torch.Tensor) -> torch.Tensor:  # [S, ...] -> [G, B, ...]
        return t.reshape(G, B, *t.shape[1:])

    return RolloutResult(
        token=g(token), logp=g(out["logp"]), logp_full=g(out["logp_full"]), entropy=g(out["entropy"]), k=g(out["k"]),
        pose_xy=g(pose_xy), pose_yaw=g(pose_yaw), xy_10hz=g(xy10), yaw_10hz=g(yaw10), valid=g(out["valid"]), sim_mask=sim_mask,
    )
