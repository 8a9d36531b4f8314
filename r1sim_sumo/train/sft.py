"""Closed-loop supervised fine-tuning baseline (CAT-K): roll out by picking, among the policy's top-K candidate tokens,
the one whose end pose is closest to the reference; label every visited state with the token that leads back to the
reference; train by cross-entropy on those labels.

:func:`closed_loop_targets` runs one cached closed-loop rollout per scene: at token step ``k`` (2..2+F-1) every
policy-driven agent (valid at the current pose) ranks its top-``K`` tokens by ``||end_xy - y_{k+1}|| +
yaw_weight_m * |wrap(end_yaw - yaw_{k+1})|`` (metres; ``y`` the matched reference boundary pose) and advances with the
best one, so the rollout stays close to the log while visiting the states the policy itself reaches (the *input*
token). The *label* of that step is, as in the official CAT-K code, the nearest token over the **whole** vocabulary of
the agent's type from the rolled-out pose at ``k`` to the reference pose at ``k + 1``, by mean box-corner distance
(:func:`nearest_token_labels`); it need not be among the top-K. Reference = the matched boundary pose of the batch
(CAT-K uses the raw logged state; the batch carries only the rolling-matched poses, which lie within the vocabulary's
matching tolerance of it). Where the reference pose is invalid the agent takes the policy's most likely token and that
step is not a training target. :func:`sft_iteration` then runs a teacher-forced forward over the batch rebuilt from
this rollout (:func:`r1sim_sumo.train.grpo.rebuild_batch`, ``G = 1``, inputs = the rolled-out tokens) and minimises
the cross-entropy of the labels.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import torch

from r1sim_sumo.geometry import wrap_angle
from r1sim_sumo.model.packed import future_logits
from r1sim_sumo.tokens.constants import CURRENT_POSE
from r1sim_sumo.tokens.matching import advance_pose
from r1sim_sumo.train.rollout_batch import rebuild_batch


class SFTTargets(NamedTuple):
    """One closed-loop rollout per scene: ``token [B, A, F]`` the rolled-out (input) tokens (-1 invalid),
    ``label [B, A, F]`` the CAT-K label (nearest token over the vocabulary from the rolled-out pose to the reference;
    -1 where no target), ``target_ok [B, A, F]`` (a training target), ``pose_xy [B, A, F+1, 2]``, ``pose_yaw
    [B, A, F+1]``, ``valid [B, A, F+1]``, ``dist_m [B, A, F]`` the picked end pose's distance to the reference [m]
    (0 where none)."""

    token: torch.Tensor
    label: torch.Tensor
    target_ok: torch.Tensor
    pose_xy: torch.Tensor
    pose_yaw: torch.Tensor
    valid: torch.Tensor
    dist_m: torch.Tensor


def nearest_token_labels(vocab, xy: torch.Tensor, yaw: torch.Tensor, agent_type: torch.Tensor, ref_xy: torch.Tensor,
                         ref_yaw: torch.Tensor) -> torch.Tensor:
    """CAT-K label ``[...]``: the token of the agent's type whose end box, placed at the pose ``(xy [..., 2] [m],
    yaw [...] [rad])`` (world frame, box centre), is nearest to the box at ``(ref_xy, ref_yaw)`` by mean corner
    distance [m], over the whole vocabulary (padding ids excluded). Boxes are the vocabulary's per-type boxes."""
    _, corners, tok_ok = vocab.torch_tables(device=xy.device)  # [3, V, 6, 4, 2], [3, V]
    at = agent_type.long()
    end = corners[:, :, -1][at]  # [..., V, 4, 2] end box in the start frame
    box0 = corners[:, 0, 0][at]  # [..., 4, 2] the box at the origin
    d = (ref_xy - xy).float()
    c, s = torch.cos(yaw.float()), torch.sin(yaw.float())
    lx, ly = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]  # reference centre in the start frame
    dy = wrap_angle(ref_yaw.float() - yaw.float())
    cr, sr = torch.cos(dy)[..., None], torch.sin(dy)[..., None]
    ref_c = torch.stack([cr * box0[..., 0] - sr * box0[..., 1] + lx[..., None],
                         sr * box0[..., 0] + cr * box0[..., 1] + ly[..., None]], -1)  # [..., 4, 2]
    dist = torch.linalg.vector_norm(end - ref_c.unsqueeze(-3), dim=-1).mean(-1)  # [..., V]
    dist = torch.where(tok_ok[at], dist, torch.full_like(dist, float("inf")))
    return dist.argmin(-1)


@torch.no_grad()
def closed_loop_targets(model, vocab, batch, top_k: int = 32, num_steps: int = 16, yaw_weight_m: float = 1.0) -> SFTTargets:
    """Closed-loop rollout choosing, among the top-``top_k`` tokens, the one closest to the reference, with CAT-K labels
    (see the module doc)."""
    model.eval()
    B, A = batch.agent_mask.shape
    live = batch.pose_valid[:, :, CURRENT_POSE].bool() & batch.agent_mask.bool()  # [B, A] policy-driven agents
    atype = batch.agent_type.long()
    gt_tok = torch.where(batch.agent_token_valid.bool(), batch.agent_token, -1)
    cache = model.init_rollout(batch, num_rollouts=1, upto_step=CURRENT_POSE)
    prev = gt_tok[:, :, CURRENT_POSE - 1]
    xy, yaw, valid = batch.pose_xy[:, :, CURRENT_POSE], batch.pose_yaw[:, :, CURRENT_POSE], live
    toks, labels, oks, dists, pxy, pyaw, pval = [], [], [], [], [xy], [yaw], [valid]
    for k in range(CURRENT_POSE, CURRENT_POSE + num_steps):
        logits = model.step(cache, k, prev, xy, yaw, valid).float()  # [B, A, V]
        kk = min(top_k, logits.shape[-1])
        top_val, cand = logits.topk(kk, -1)  # [B, A, K]
        c_xy, c_yaw = advance_pose(xy.unsqueeze(2).expand(B, A, kk, 2), yaw.unsqueeze(2).expand(B, A, kk), cand, vocab,
                                   atype.unsqueeze(-1).expand(B, A, kk))
        ref_ok = batch.pose_valid[:, :, k + 1].bool()  # [B, A]
        d = torch.linalg.vector_norm(c_xy - batch.pose_xy[:, :, k + 1].unsqueeze(2), dim=-1)
        d = d + yaw_weight_m * wrap_angle(c_yaw - batch.pose_yaw[:, :, k + 1].unsqueeze(2)).abs()
        d = torch.where(torch.isfinite(top_val), d, torch.full_like(d, float("inf")))
        pick = torch.where(ref_ok, d.argmin(-1), torch.zeros_like(ref_ok, dtype=torch.long))  # top-1 without reference
        tok = cand.gather(-1, pick.unsqueeze(-1)).squeeze(-1)
        tok = torch.where(valid, tok, torch.full_like(tok, -1))
        nxt_xy, nxt_yaw = advance_pose(xy, yaw, tok, vocab, atype)
        nxt_xy = torch.where(valid.unsqueeze(-1), nxt_xy, xy)
        nxt_yaw = torch.where(valid, nxt_yaw, yaw)
        ok = valid & ref_ok
        label = nearest_token_labels(vocab, xy, yaw, atype, batch.pose_xy[:, :, k + 1], batch.pose_yaw[:, :, k + 1])
        toks.append(tok)
        labels.append(torch.where(ok, label, torch.full_like(label, -1)))
        oks.append(ok)
        dists.append(torch.where(ok, torch.linalg.vector_norm(nxt_xy - batch.pose_xy[:, :, k + 1], dim=-1), torch.zeros_like(yaw)))
        prev, xy, yaw = tok, nxt_xy, nxt_yaw
        pxy.append(xy)
        pyaw.append(yaw)
        pval.append(valid)
    return SFTTargets(torch.stack(toks, -1), torch.stack(labels, -1), torch.stack(oks, -1), torch.stack(pxy, 2),
                      torch.stack(pyaw, 2),
                      torch.stack(pval, -1), torch.stack(dists, -1))


def sft_loss(logits: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, label_smoothing: float = 0.0) -> torch.Tensor:
    """Mean cross-entropy of ``target [...]`` under ``logits [..., V]`` over ``mask``; smoothing over finite logits."""
    m = mask.bool()
    if not bool(m.any()):
        return logits.sum() * 0.0
    lp = torch.log_softmax(logits[m].float(), -1)  # [n, V]
    nll = -lp.gather(-1, target[m].clamp(min=0).unsqueeze(-1)).squeeze(-1)
    if label_smoothing > 0:
        fin = torch.isfinite(lp)
        smooth = -torch.where(fin, lp, torch.zeros_like(lp)).sum(-1) / fin.sum(-1).clamp(min=1)
        nll = (1 - label_smoothing) * nll + label_smoothing * smooth
    return nll.mean()


def rollout_loss(model, rb, tg: SFTTargets, label_smoothing: float = 0.0, packed: bool = True) -> torch.Tensor:
    """Cross-entropy of the CAT-K labels ``tg.label`` under the teacher-forced logits of the batch ``rb`` rebuilt from
    the rollout (future steps ``CURRENT_POSE .. CURRENT_POSE+F-1``, where ``tg.target_ok``). ``packed`` (default): the
    packed forward over the target tokens (:func:`r1sim_sumo.model.packed.future_logits`), else or where it does not
    apply the padded one."""
    F = tg.token.shape[-1]
    target = tg.target_ok.bool()
    rows = future_logits(model, rb, target, CURRENT_POSE) if packed else None
    if rows is None:
        return sft_loss(model(rb)[:, :, CURRENT_POSE : CURRENT_POSE + F], tg.label, target, label_smoothing)
    label = tg.label[target]  # [n], in the rows' order
    return sft_loss(rows, label, torch.ones_like(label, dtype=torch.bool), label_smoothing)


def sft_iteration(learner, batch) -> dict:
    """One closed-loop SFT update of ``learner.model`` (a :class:`r1sim_sumo.train.grpo.GRPOLearner`) on ``batch``."""
    cfg, model = learner.cfg, learner.model
    t0 = time.time()
    tg = closed_loop_targets(model, learner.vocab, batch, cfg.sft_top_k, cfg.num_steps, cfg.sft_yaw_weight_m)
    t_roll = time.time() - t0
    rb = rebuild_batch(batch, tg.token[None], tg.pose_xy[None], tg.pose_yaw[None], tg.valid[None])
    loss = rollout_loss(model, rb, tg, cfg.sft_label_smoothing)
    learner._update(loss)
    n = tg.target_ok.sum().clamp(min=1)
    return {"loss": float(loss.detach()), "sft_dist_m": float(tg.dist_m.sum() / n), "distance_m": float(tg.dist_m.sum() / n),
            "rollout_s": t_roll, "update_s": time.time() - t0 - t_roll}
