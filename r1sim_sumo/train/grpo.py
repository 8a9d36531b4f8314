"""GRPO fine-tuning of the traffic policy (R1Sim, Algorithm 1) and the fine-tuning loop shared with closed-loop SFT.

One iteration on ``B`` scenes:

1. roll out ``G`` closed-loop futures per scene with the current policy (= the "old" policy) and the configured
   sampler (entropy-guided top-K_t by default), recording each sampled token's log-probability;
2. token-level rewards :func:`r1sim_sumo.train.rewards.compute_rewards` ``r_{i,t}`` per rollout, agent and token step;
3. group-relative advantages ``A_{i,t} = r_{i,t} - mean_i r_{i,t}`` over the ``G`` rollouts of the same scene, agent and
   step ("GRPO-refined", paper default) or additionally divided by the std over the group ("GRPO-standard");
   optional reward-to-go credit (``A`` computed from the discounted sum of future rewards);
4. ``ppo_epochs`` passes over ``num_minibatches`` minibatches of the ``G * B`` rollouts: a teacher-forced forward of the
   current policy over a :class:`SceneBatch` rebuilt from the rollouts (:func:`rebuild_batch`) gives
   ``logp_new`` of every rolled-out token; ratio ``rho = exp(logp_new - logp_old)``; loss per valid token
   ``-(min(rho A, clip(rho, 1 - eps_low, 1 + eps_high) A) - beta_KL * k3)`` with the k3 estimator
   ``k3 = exp(logp_ref - logp_new) - (logp_ref - logp_new) - 1`` of KL(pi_theta || pi_ref) at the sampled token
   (frozen reference = the initial policy), averaged over the minibatch's valid tokens.

Choice of ``logp_old`` / ``logp_new`` (``logp_kind``): ``"truncated"`` uses the sampler's own log-probability of the
token, i.e. the probability under the distribution it was actually drawn from (top-K_t, renormalised, tempered;
``RolloutResult.logp``), and recomputes ``logp_new`` under the same K_t and temperature (top-K_t of the current logits;
the sampled token is always kept in the normaliser); ``"full"`` uses full-softmax log-probabilities on both sides
(``RolloutResult.logp_full``). Both make ``rho = 1`` on the first minibatch of an iteration (the weights have not moved
yet; up to float rounding between the cached rollout step and the teacher-forced forward, measured ~1e-6). The two
ratios differ by the factor ``Z_old / Z_new`` with ``Z`` the full-softmax mass of the kept set, so their gradients
differ by ``-A_{i,t} grad log Z(s_t)``. That term has zero expectation only where the state ``s_t`` is the same for
every member of the group, i.e. at the first future step (one scene, one history, group-mean-centred advantages sum to
zero); from the second step on ``s_t`` depends on the tokens drawn before, which are correlated with the advantage, and
the term does not cancel. ``truncated`` is the importance ratio of the sampling distribution itself (what the clip
range is meant to bound); ``full`` is smooth in the weights (the kept set and the entropy-guided K_t do not move with
them). Measured (``scripts/compare_grpo_logp_kind.py``, ``docs/grpo_logp_kind.json``: r1sim-nano, 4 SUMO scenes, 4
iterations x 2 scenes x 8 rollouts, entropy-guided (16, 80), 2 seeds, then 8 fresh rollouts per scene): token reward
0.840 truncated vs 0.839 full (initial 0.815), collision rate 0.0053 vs 0.0052, distance to the log 1.199 vs 1.200 m,
clip fraction 0.015 vs 0.018; the seed-to-seed spread (reward 0.835-0.846) is larger than the gap. With no measured
difference the default is ``truncated``, the ratio of the distribution actually sampled from.

KL term: ``k3 = exp(logp_ref - logp_new) - (logp_ref - logp_new) - 1`` at tokens sampled from the current policy is
the unbiased, non-negative estimator of ``KL(pi_theta || pi_ref)`` used by DeepSeekMath's GRPO (Schulman's k3). The
R1Sim paper writes the penalty as ``D_KL(pi_ref || pi_theta)``; we keep DeepSeekMath's direction, the one this
estimator estimates for on-policy samples (an estimate of the paper's direction would need reference samples or an
importance weight). With ``logp_kind="truncated"`` both log-probabilities are taken under the same top-K_t truncation.

Dropout is switched off during fine-tuning (the model stays in eval mode): the rollout policy, the old-policy
log-probabilities and the optimised forward must be the same function for the ratio to mean anything.
Freezing (``freeze``): ``paper`` trains only the last map-encoder layer (+ its output norm), the last agent layer
(temporal, map-to-agent, agent-to-agent blocks) and the token head; ``agent`` the same without the map layer, which is
much cheaper (the map encoder feeds every agent layer, so a trainable map layer makes the backward pass run through
all agent layers; with ``agent`` it stops at the last one); ``head`` only the head; ``none`` everything.
"""

from __future__ import annotations

import copy
import csv
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from r1sim_sumo.config import load_config, save_config
from r1sim_sumo.model.packed import future_logits
from r1sim_sumo.rollout.engine import N_FUTURE_TOK, rollout
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.tokens.constants import CURRENT_POSE
from r1sim_sumo.train.rewards import RewardConfig, compute_rewards
from r1sim_sumo.train.rollout_batch import index_batch, rebuild_batch
from r1sim_sumo.train.sft import sft_iteration
from r1sim_sumo.train.steady_history import steady_history, straight_token_table

METHODS = ("grpo", "grpo-std", "sft")
SCENE_FOCUS = ("all", "must-merge")
FREEZE_MODES = ("paper", "agent", "head", "none")


@dataclass
class GRPOConfig:
    """Fine-tuning by GRPO (``method: grpo`` / ``grpo-std``) or closed-loop SFT (``method: sft``)."""

    init_checkpoint: str | None = None
    """Policy checkpoint to fine-tune (directory or bundled name; None = the shipped default)."""
    train_data: str = "data/generated/default/train"
    """Dataset folder (manifest.json + shards) whose scenarios are rolled out."""
    extra_train_data: list[str] = field(default_factory=list)
    """More scenario datasets (e.g. ``data/generated/rings/train``, training-only roundabouts) whose scenes are drawn
    together with ``train_data``'s, uniformly over all scenes; not with ``rollout_source: sumo``. A folder listed n times
    is drawn n times as often (read and tokenized once)."""
    token_cache: str | None = None
    """Folder of the tokenized-scene cache (default: out_dir/token_cache; each extra dataset gets its own subfolder)."""
    method: str = "grpo"
    """grpo (advantage = r - mean), grpo-std (also / std, standard GRPO), sft (closed-loop SFT, CAT-K)."""
    num_rollouts: int = 32
    """G rollouts per scenario (the group)."""
    batch_scenes: int = 2
    """Scenarios per iteration (B)."""
    sampler: str = "entropy:16,80"
    """Rollout sampler spec (topk:32, entropy:16,80, entropy-norm:16,80, full, optional @TEMP)."""
    num_steps: int = N_FUTURE_TOK
    """Future token steps rolled out (<= 16; 0.5 s each)."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    reward_to_go: bool = False
    """Credit each token with the discounted sum of its future rewards before the group baseline."""
    gamma: float = 1.0
    """Discount per token step for reward_to_go."""
    std_eps: float = 1e-4
    """grpo-std: advantage / (std + std_eps)."""
    logp_kind: str = "truncated"
    """truncated (the sampler's top-K_t log-probs, default) or full (full-softmax ratio); see the module docstring.
    Measured on a short fine-tune (docs/grpo_logp_kind.json): no difference beyond seed noise, so the default is the
    ratio of the distribution actually sampled from."""
    eps_low: float = 0.2
    """Lower clip range: rho >= 1 - eps_low for negative advantages."""
    eps_high: float = 0.28
    """Upper clip range: rho <= 1 + eps_high for positive advantages."""
    beta_kl: float = 0.04
    """Weight of the k3 KL to the frozen reference policy."""
    ppo_epochs: int = 2
    """Passes over the rollouts of one iteration (> 1 so the ratio leaves 1 and clipping acts)."""
    num_minibatches: int = 4
    """Minibatches per pass (over the G * B rollouts)."""
    freeze: str = "paper"
    """paper (last map + last agent layer + head trainable), agent (last agent layer + head), head, none."""
    lr: float = 3e-5
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    epochs: int = 1
    """Passes over train_data when max_iters is None (the paper fine-tunes 1 epoch)."""
    max_iters: int | None = None
    """Iterations to run (None = epochs * len(train_data) / batch_scenes)."""
    sft_top_k: int = 32
    """sft: candidates (top-K of the policy) among which the one closest to the reference is chosen."""
    sft_yaw_weight_m: float = 1.0
    """sft: metres added per radian of heading error when ranking candidates."""
    sft_label_smoothing: float = 0.0
    steady_start_prob: float = 0.0
    """Share of the vehicles whose reference speeds up at the first rolled-out token (>= 0.4 m/s faster than the last
    history token, >= 2 m/s below their desired speed) that start from a steady-speed past instead of their logged one
    (:func:`r1sim_sumo.train.steady_history.steady_history` with ``at=CURRENT_POSE``): the closed-loop counterpart of
    pretraining's ``steady_history_prob``, for a policy that holds its speed on a free road."""
    train_tokens: list[str] = field(default_factory=list)
    """Compact token datasets (``r1sim tokens build`` folders) whose ``train`` split is rolled out instead of
    ``train_data`` / ``extra_train_data``, scenes drawn uniformly over all of them: a few MB each where the scenario
    datasets are hundreds, so they travel to a lent GPU machine. Their vocabulary must be the policy's; the offroad
    reward reads each folder's ``train.polylines.npz`` (built since session 38)."""
    device: str = "cpu"
    """Where rollouts, rewards and updates run: ``cpu`` or ``cuda`` (a GPU machine; the offroad check stays on the
    CPU). ``cuda`` takes method grpo / grpo-std with model rollouts."""
    rollout_source: str = "model"
    """model (in-model batched rollouts) or sumo (the policy drives the scenes' vehicles inside SUMO restored from the
    dataset's state files, :mod:`r1sim_sumo.train.sumo_inloop`; needs train_data generated with --save-states)."""
    sumo_workers: int = 2
    """rollout_source=sumo: worker processes (one libsumo each); 0 runs them in this process."""
    sumo_backend: str = "process"
    """rollout_source=sumo: ``process`` (local worker processes) or ``ray`` (Ray actors; ``ray.init()`` locally or
    the cluster of ``RAY_ADDRESS``)."""
    seed: int = 0
    threads: int = 2
    log_every: int = 1
    ckpt_every: int = 20
    scene_focus: str = "all"
    """all: every scene of the sources; must-merge: only scenes with an agent on a must-merge lane at the start
    (:func:`~r1sim_sumo.metrics.lane_changes.must_merge_lanes`, e.g. an acceleration lane); needs train_tokens."""
    keep_every: int = 0  # also export a checkpoint folder ckpt-XXXXXX every this many iterations (0: none)
    out_dir: str = "runs/grpo"

    def __post_init__(self) -> None:
        problems = []
        if self.method not in METHODS:
            problems.append(f"method '{self.method}' unknown; use one of {METHODS}")
        if self.freeze not in FREEZE_MODES:
            problems.append(f"freeze '{self.freeze}' unknown; use one of {FREEZE_MODES}")
        if self.logp_kind not in ("full", "truncated"):
            problems.append(f"logp_kind '{self.logp_kind}' unknown; use full or truncated")
        if self.sumo_backend not in ("process", "ray"):
            problems.append(f"sumo_backend '{self.sumo_backend}' unknown; use process or ray")
        if self.rollout_source not in ("model", "sumo"):
            problems.append(f"rollout_source '{self.rollout_source}' unknown; use model or sumo")
        elif self.rollout_source == "sumo" and self.method == "sft":
            problems.append("rollout_source=sumo needs method grpo or grpo-std (sft rolls out in the model)")
        if not 1 <= self.num_steps <= N_FUTURE_TOK:
            problems.append(f"num_steps must be in [1, {N_FUTURE_TOK}], got {self.num_steps}")
        if not 0.0 <= float(self.steady_start_prob) <= 1.0:
            problems.append(f"steady_start_prob must be in [0, 1], got {self.steady_start_prob}")
        elif self.steady_start_prob > 0 and self.rollout_source == "sumo":
            problems.append("steady_start_prob needs rollout_source=model (SUMO-in-the-loop rollouts start from SUMO's states)")
        if self.device != "cpu" and not str(self.device).startswith("cuda"):
            problems.append(f"device '{self.device}' unknown; use cpu or cuda")
        elif self.device != "cpu" and (self.method == "sft" or self.rollout_source == "sumo" or self.steady_start_prob > 0):
            problems.append(f"device '{self.device}' takes method grpo / grpo-std with rollout_source=model and "
                            "steady_start_prob 0; run the others with device: cpu")
        if self.scene_focus not in SCENE_FOCUS:
            problems.append(f"scene_focus '{self.scene_focus}' unknown; use one of {SCENE_FOCUS}")
        elif self.scene_focus != "all" and not self.train_tokens:
            problems.append(f"scene_focus '{self.scene_focus}' reads the scenes' maps from compact token datasets: set "
                            "train_tokens (r1sim tokens build folders)")
        if self.train_tokens and (self.extra_train_data or self.rollout_source == "sumo"):
            problems.append("train_tokens replaces train_data and extra_train_data (leave extra_train_data empty) and "
                            "needs rollout_source=model")
        for name in ("num_rollouts", "batch_scenes", "ppo_epochs", "num_minibatches", "epochs"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if isinstance(self.reward, dict):
            self.reward = RewardConfig(**self.reward)
        if self.reward.must_merge_weight != 1.0 and not self.reward.offroad:
            problems.append("reward.must_merge_weight reads the scenes' maps, which finetune passes with reward.offroad: true")
        kind = parse_sampler(self.sampler).kind  # parse_sampler raises a clear error for a bad spec
        if kind == "intent":
            problems.append(f"sampler '{self.sampler}': intent draws a side, not a token of a top-K set, so GRPO's "
                            "ratio has no distribution to recompute; use topk:K, entropy:KMIN,KMAX or full")
        elif kind == "median":
            problems.append(f"sampler '{self.sampler}': median decoding is deterministic (the drop-in's), so a group's "
                            "rollouts would all be the same and no advantage is left; use topk:K, entropy:KMIN,KMAX or full")
        if problems:
            raise ValueError("GRPOConfig: " + "; ".join(problems))


# ---------------------------------------------------------------------------- pure pieces


def group_advantages(reward: torch.Tensor, mask: torch.Tensor, std_normalise: bool = False, std_eps: float = 1e-4,
                     reward_to_go: bool = False, gamma: float = 1.0) -> torch.Tensor:
    """Group-relative advantages ``[G, ...]`` over the rollout dim 0, per (scene, agent, step).

    ``A = r - mean_i r`` over the rollouts where ``mask`` holds (refined GRPO, paper Eq. advantage), or
    ``(r - mean) / (std + std_eps)`` (standard GRPO, unbiased std over the valid members). With ``reward_to_go``
    ``r_t`` is first replaced by ``sum_{s >= t} gamma^(s-t) r_s`` over the valid steps of the last dim.
    Entries outside ``mask`` get 0; a group with one valid member gets 0.
    """
    m = mask.float()
    r = reward.float() * m
    if reward_to_go:
        out, acc = torch.zeros_like(r), torch.zeros_like(r[..., 0])
        for t in range(r.shape[-1] - 1, -1, -1):
            acc = r[..., t] + gamma * acc
            out[..., t] = acc
        r = out * m
    n = m.sum(0, keepdim=True)
    mean = r.sum(0, keepdim=True) / n.clamp(min=1)
    adv = (r - mean) * m
    if std_normalise:
        var = (adv**2).sum(0, keepdim=True) / (n - 1).clamp(min=1)
        adv = adv / (var.sqrt() + std_eps)
    return adv


def token_logp(logits: torch.Tensor, token: torch.Tensor, kind: str = "full", k: torch.Tensor | None = None,
               temperature: float = 1.0) -> torch.Tensor:
    """Log-probability ``[...]`` of ``token [...]`` under ``logits [..., V]``.

    ``full``: full softmax. ``truncated``: softmax at ``temperature`` over the top-``k`` logits (``k [...]`` per
    row, the sampler's K_t) plus the token itself if it fell outside them (so the value stays finite).
    """
    tok = token.clamp(min=0).unsqueeze(-1)
    if kind == "full":
        return torch.log_softmax(logits.float(), -1).gather(-1, tok).squeeze(-1)
    if k is None:
        raise ValueError("token_logp(kind='truncated') needs the sampler's k")
    scaled = logits.float() / max(float(temperature), 1e-6)
    kk = k.clamp(min=1)
    top = scaled.topk(int(kk.max()), -1).values  # [..., kmax]
    rank = torch.arange(top.shape[-1], device=top.device)
    top = torch.where(rank < kk.unsqueeze(-1), top, torch.full_like(top, float("-inf")))
    own = scaled.gather(-1, tok)  # [..., 1]
    kth = top.gather(-1, (kk - 1).unsqueeze(-1))
    extra = torch.where(own < kth, own, torch.full_like(own, float("-inf")))
    return (own - torch.logsumexp(torch.cat([top, extra], -1), -1, keepdim=True)).squeeze(-1)


def rollout_logp(net, sub, mask: torch.Tensor, token: torch.Tensor, kind: str, k: torch.Tensor, temperature: float,
                 packed: bool = True) -> torch.Tensor:
    """``[n, A, F]`` log-probabilities (:func:`token_logp`) of the future tokens ``token`` of the rebuilt rollouts
    ``sub`` (``n`` scenes), 0 outside ``mask [n, A, F]``. ``packed`` (default): the packed forward over the masked
    tokens (:func:`r1sim_sumo.model.packed.future_logits`), else or where it does not apply the padded one."""
    F = mask.shape[-1]
    rows = future_logits(net, sub, mask, CURRENT_POSE) if packed else None
    if rows is None:
        logits = net(sub)[:, :, CURRENT_POSE : CURRENT_POSE + F]  # [n, A, F, V]
        return torch.where(mask, token_logp(logits, token, kind, k, temperature), 0.0)
    lp = torch.zeros(mask.shape, dtype=torch.float32, device=mask.device)
    lp[mask] = token_logp(rows, token[mask], kind, k[mask], temperature)
    return lp


def grpo_loss(logp_new: torch.Tensor, logp_old: torch.Tensor, logp_ref: torch.Tensor, adv: torch.Tensor,
              mask: torch.Tensor, eps_low: float, eps_high: float, beta_kl: float) -> tuple[torch.Tensor, dict]:
    """Clipped surrogate + k3 KL, averaged over the ``mask``-ed tokens; returns ``(loss, stats)``.

    stats (floats): ``kl`` mean k3, ``clip_frac`` fraction of tokens whose clipped branch is active (zero gradient),
    ``ratio_dev`` max ``|rho - 1|``, ``ratio_mean``.
    """
    m = mask.bool()
    n = m.sum().clamp(min=1)
    d = torch.where(m, logp_new - logp_old, torch.zeros_like(logp_new))
    ratio = torch.exp(d)
    surr = torch.minimum(ratio * adv, ratio.clamp(1.0 - eps_low, 1.0 + eps_high) * adv)
    dr = torch.where(m, logp_ref - logp_new, torch.zeros_like(logp_new))
    kl = torch.exp(dr) - dr - 1.0
    loss = -((surr - beta_kl * kl) * m).sum() / n
    with torch.no_grad():
        clipped = ((adv > 0) & (ratio > 1.0 + eps_high)) | ((adv < 0) & (ratio < 1.0 - eps_low))
        stats = {
            "kl": float((kl * m).sum() / n),
            "clip_frac": float((clipped & m).sum() / n),
            "ratio_dev": float(((ratio - 1).abs() * m).max()) if bool(m.any()) else 0.0,
            "ratio_mean": float((ratio * m).sum() / n),
        }
    return loss, stats


def apply_freeze(model: torch.nn.Module, mode: str) -> list[torch.nn.Parameter]:
    """Set ``requires_grad`` per the freezing mode (see the module docstring); returns the trainable parameters."""
    if mode not in FREEZE_MODES:
        raise ValueError(f"freeze '{mode}' unknown; use one of {FREEZE_MODES}")
    if mode == "none":
        keep = list(model.parameters())
    elif mode == "head":
        keep = list(model.head.parameters())
    elif mode == "agent":
        mods = [model.t_blocks[-1], model.m_blocks[-1], model.a_blocks[-1], model.head]
        keep = [p for mod in mods for p in mod.parameters()]
    else:
        mods = [model.map_blocks[-1], model.map_norm, model.t_blocks[-1], model.m_blocks[-1], model.a_blocks[-1], model.head]
        keep = [p for mod in mods for p in mod.parameters()]
    ids = {id(p) for p in keep}
    for p in model.parameters():
        p.requires_grad_(id(p) in ids)
    return [p for p in model.parameters() if p.requires_grad]


# ---------------------------------------------------------------------------- the learner


class GRPOLearner:
    """One GRPO (or SFT) update per call of :meth:`iteration`; holds the policy, the frozen reference and the optimiser.

    :param model: the :class:`TrafficPolicy` to fine-tune (modified in place; kept in eval mode, no dropout).
    :param ref_model: the frozen reference policy (a copy of the initial weights); unused by SFT.
    :param vocab: the policy's :class:`MotionVocab`.
    """

    def __init__(self, model, ref_model, vocab, cfg: GRPOConfig):
        self.model, self.ref, self.vocab, self.cfg = model.eval(), ref_model, vocab, cfg
        if ref_model is not None:
            self.ref.eval().requires_grad_(False)
        self.params = apply_freeze(model, cfg.freeze)
        self.opt = torch.optim.AdamW(self.params, lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.sampler = parse_sampler(cfg.sampler)

    def iteration(self, batch, generator: torch.Generator, maps=None) -> dict:
        """One iteration on ``batch``; ``maps`` (the scenes' maps) feed the offroad part of the reward."""
        if self.cfg.method == "sft":
            return sft_iteration(self, batch)
        return self.grpo_iteration(batch, generator, maps=maps)

    def _update(self, loss: torch.Tensor) -> None:
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        if self.cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.params, self.cfg.grad_clip)
        self.opt.step()

    def grpo_iteration(self, batch, generator: torch.Generator, result=None, extra_collision=None, maps=None) -> dict:
        """Roll out (unless ``result`` is given, e.g. from SUMO), score, and run the minibatch updates."""
        cfg, model = self.cfg, self.model
        t0 = time.time()
        model.eval()
        if result is None:
            result = rollout(model, self.vocab, batch, cfg.num_rollouts, self.sampler, generator=generator, num_steps=cfg.num_steps)
        t_roll = time.time() - t0
        rw = compute_rewards(result, batch, cfg.reward, extra_collision, maps)
        adv = group_advantages(rw.reward, rw.mask, cfg.method == "grpo-std", cfg.std_eps, cfg.reward_to_go, cfg.gamma)
        G, B, A, F = result.token.shape
        S = G * B
        rb = rebuild_batch(batch, result.token, result.pose_xy, result.pose_yaw, result.valid)

        def flat(t: torch.Tensor) -> torch.Tensor:  # [G, B, ...] -> [S, ...]
            return t.reshape(S, *t.shape[2:])

        tok, mask, adv_f, k_f = flat(result.token), flat(rw.mask), flat(adv), flat(result.k)
        old = flat(result.logp_full if cfg.logp_kind == "full" else result.logp)
        temp = self.sampler.temperature

        def logp_of(net, idx: torch.Tensor) -> torch.Tensor:
            return rollout_logp(net, index_batch(rb, idx), mask[idx], tok[idx], cfg.logp_kind, k_f[idx], temp)

        nmb = min(cfg.num_minibatches, S)
        chunks = [c for c in torch.arange(S).chunk(nmb)]
        with torch.no_grad():
            ref_lp = torch.cat([logp_of(self.ref, c) for c in chunks])  # [S, A, F]
        stats_acc: dict[str, list[float]] = {}
        first_dev = None
        for _ in range(cfg.ppo_epochs):
            perm = torch.randperm(S, generator=generator, device=generator.device if generator is not None else "cpu")
            for idx in perm.chunk(nmb):
                new = logp_of(model, idx)
                loss, st = grpo_loss(new, old[idx], ref_lp[idx], adv_f[idx], mask[idx], cfg.eps_low, cfg.eps_high, cfg.beta_kl)
                if first_dev is None:
                    first_dev = st["ratio_dev"]
                self._update(loss)
                st["loss"] = float(loss.detach())
                for k, v in st.items():
                    stats_acc.setdefault(k, []).append(v)
        m = rw.mask
        nm = m.sum().clamp(min=1)
        act = result.sim_mask[None, :, :, None] & (result.token >= 0)
        adv_m = adv[m]
        out = {k: sum(v) / len(v) for k, v in stats_acc.items() if k != "ratio_dev"}
        out.update(
            reward=float(rw.reward[m].sum() / nm),
            adv_mean=float(adv_m.mean()) if adv_m.numel() else 0.0,
            adv_std=float(adv_m.std()) if adv_m.numel() > 1 else 0.0,
            ratio_dev_max=max(stats_acc.get("ratio_dev", [0.0])),
            first_ratio_dev=first_dev or 0.0,
            entropy=float(result.entropy[act].mean()) if act.any() else 0.0,
            k_mean=float(result.k[act].float().mean()) if act.any() else 0.0,
            collision_rate=float(rw.collision.sum() / act.sum().clamp(min=1)),
            agent_collision_rate=float(rw.collision.any(-1).sum() / act.any(-1).sum().clamp(min=1)),
            distance_m=float(rw.distance_m[m].sum() / nm),
            rollout_s=t_roll,
            update_s=time.time() - t0 - t_roll,
        )
        if cfg.reward.offroad:  # only measured when the reward uses it (the log's column stays empty otherwise)
            out["offroad_rate"] = float(rw.offroad.sum() / act.sum().clamp(min=1))
        return out


# ---------------------------------------------------------------------------- scene sources


class SceneSource(Protocol):
    def __len__(self) -> int: ...

    def batch(self, indices: list[int]): ...


class DatasetSource:
    """Scenes of a tokenized dataset (:class:`~r1sim_sumo.tokens.TokenizedDataset`), collated on demand; ``extra``
    datasets append their scenes after the first one's (index ``len(dataset)`` is the first extra scene)."""

    def __init__(self, dataset, extra=()):
        self.ds = dataset
        self.parts = [dataset, *extra]
        self._ends = np.cumsum([len(d) for d in self.parts])

    def __len__(self) -> int:
        return int(self._ends[-1])

    def _locate(self, i: int) -> tuple[object, int]:
        """The part holding joined scene ``i`` and its index there."""
        k = int(np.searchsorted(self._ends, i, side="right"))
        return self.parts[k], i - (int(self._ends[k - 1]) if k else 0)

    def scene(self, i: int):
        part, j = self._locate(i)
        return part[j]

    def batch(self, indices: list[int]):
        from r1sim_sumo.tokens.batch import collate

        return collate([self.scene(i) for i in indices])

    def maps(self, indices: list[int]) -> list:
        """The scenes' maps (:class:`~r1sim_sumo.scenario.MapPolylines`, world frame) from their scenario datasets."""
        return [part.data[j].map for part, j in map(self._locate, indices)]


def open_once(folders: list[str], open_folder) -> list:
    """``[open_folder(k, folder) for k, folder in enumerate(folders)]``, except that a folder listed again (same resolved
    path) reuses the object opened for its first listing: listing a dataset n times draws its scenes n times as often
    (:class:`DatasetSource` samples uniformly over the joined scenes) without reading or tokenizing it n times."""
    opened: dict[str, object] = {}
    out = []
    for k, folder in enumerate(folders):
        key = str(Path(folder).resolve())
        if key not in opened:
            opened[key] = open_folder(k, folder)
        out.append(opened[key])
    return out


class FocusedSource:
    """The scenes ``keep`` of another source, renumbered 0..len(keep)-1 (``GRPOConfig.scene_focus``)."""

    def __init__(self, inner, keep: np.ndarray):
        if len(keep) == 0:
            raise ValueError("scene_focus left no scene: none of the train_tokens scenes has an agent on a must-merge lane")
        self.inner, self.keep = inner, np.asarray(keep, np.int64)

    def __len__(self) -> int:
        return len(self.keep)

    def batch(self, indices: list[int]):
        return self.inner.batch([int(self.keep[i]) for i in indices])

    def maps(self, indices: list[int]) -> list:
        return self.inner.maps([int(self.keep[i]) for i in indices])


def must_merge_scenes(source: CompactSource) -> np.ndarray:
    """Joined indices of ``source``'s scenes with a valid agent whose logged current pose lies on a must-merge lane."""
    from r1sim_sumo.metrics.lane_changes import must_merge_lanes, poses_on_lanes

    keep, base = [], 0
    for part in source.parts:
        scene_of_agent = np.repeat(np.arange(len(part)), part.a["n_agents"])
        ok = part.a["gt_valid"][:, CURRENT_POSE]
        xy = np.stack([part.a["gt_x"][:, CURRENT_POSE], part.a["gt_y"][:, CURRENT_POSE]], -1).astype(np.float64)
        yaw = part.a["gt_yaw"][:, CURRENT_POSE].astype(np.float64)
        for k in np.unique(part.a["map_of_scene"]):
            scenes = np.nonzero(part.a["map_of_scene"] == k)[0]
            m = part.polylines(int(scenes[0]))
            lanes = must_merge_lanes(m)
            if not lanes:
                continue
            rows = np.nonzero(np.isin(scene_of_agent, scenes) & ok)[0]
            on = poses_on_lanes(m, lanes, xy[rows], yaw[rows])
            keep.append(base + np.unique(scene_of_agent[rows[on]]))
        base += len(part)
    return np.sort(np.concatenate(keep)) if keep else np.zeros(0, np.int64)


class CompactSource(DatasetSource):
    """Scenes of compact token datasets' train splits (:class:`~r1sim_sumo.tokens.compact.CompactTokenDataset`),
    joined as :class:`DatasetSource` joins scenario datasets; their maps' geometry comes from each folder's
    ``train.polylines.npz``."""

    def maps(self, indices: list[int]) -> list:
        return [part.polylines(j) for part, j in map(self._locate, indices)]


def compact_source(folders: list[str], vocab) -> CompactSource:
    """A :class:`CompactSource` over the ``train`` splits of ``folders``; each must index ``vocab`` (the policy's)."""
    from r1sim_sumo.tokens.compact import CompactTokenDataset

    parts = []
    for folder in folders:
        ds = CompactTokenDataset(folder, "train")
        if ds.vocab.fingerprint() != vocab.fingerprint():
            raise ValueError(f"train_tokens: {folder}/vocab.safetensors is not the policy's vocabulary (fingerprint "
                             f"{ds.vocab.fingerprint()} vs {vocab.fingerprint()}); rebuild it with `r1sim tokens build "
                             f"--data <dataset folder> --out {folder} --vocab <the policy's vocab>`")
        parts.append(ds)
    return CompactSource(parts[0], parts[1:])


class TensorSource:
    """Scenes of one prebuilt (padded) batch, e.g. ``r1sim_sumo.model.synthetic.synthetic_batch`` (tests, benchmarks)."""

    def __init__(self, batch):
        self.full = batch

    def __len__(self) -> int:
        return int(self.full.agent_mask.shape[0])

    def batch(self, indices: list[int]):
        return index_batch(self.full, torch.as_tensor(indices, dtype=torch.long))


# ---------------------------------------------------------------------------- the loop


LOG_FIELDS = [
    "iter", "scenes", "reward", "adv_mean", "adv_std", "kl", "clip_frac", "ratio_mean", "ratio_dev_max", "first_ratio_dev",
    "entropy", "k_mean", "collision_rate", "agent_collision_rate", "offroad_rate", "distance_m", "loss", "sft_dist_m", "rollout_s", "update_s",
    "rollouts_per_s", "wall_s",
]


def finetune(cfg: GRPOConfig, resume: bool = False, progress: bool = True, policy=None, source: SceneSource | None = None) -> Path:
    """Run (or resume) fine-tuning; returns the exported checkpoint folder ``out_dir/final``.

    :param policy: a loaded policy (``.model``, ``.vocab``) to start from instead of ``cfg.init_checkpoint``
        (it is copied, not modified).
    :param source: scenes to roll out instead of ``cfg.train_data``.

    Determinism: iteration ``it`` uses scenes from the epoch permutation of ``seed + epoch`` (as pretraining), torch
    seeded with ``seed * 1_000_003 + it`` and a rollout generator seeded with ``seed * 7_919 + it``; a killed and
    resumed run (``--resume``, from ``out_dir/state``) produces the same weights as an uninterrupted one.
    """
    from tqdm import tqdm

    from r1sim_sumo.model.checkpoint import save_checkpoint
    from r1sim_sumo.train.pretrain import EpochBatches
    from r1sim_sumo.train.train_state import load_train_state, save_train_state

    torch.set_num_threads(cfg.threads)
    out = Path(cfg.out_dir)
    state_dir = out / "state"
    has_state = (state_dir / "state.json").exists() or state_dir.with_name("state.old").exists()
    if has_state and not resume:
        raise FileExistsError(f"{out} holds a fine-tuning run; pass --resume to continue it or choose another out_dir")
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.yaml")

    if policy is None:
        from r1sim_sumo import load_policy

        policy = load_policy(cfg.init_checkpoint)
        if not (resume and has_state):  # which weights a bundled name meant when the run started
            from r1sim_sumo.train.pretrain import record_init

            record_init(out, str(cfg.init_checkpoint), policy.info.get("weights", {}).get("sha256"))
    vocab = policy.vocab
    dev = torch.device(cfg.device)
    model = copy.deepcopy(policy.model).float().to(dev)
    ref = copy.deepcopy(policy.model).float().to(dev) if cfg.method != "sft" else None
    if source is None and cfg.train_tokens:
        source = compact_source(cfg.train_tokens, vocab)
        if cfg.scene_focus == "must-merge":
            source = FocusedSource(source, must_merge_scenes(source))
            print(f"[finetune] scene_focus must-merge: {len(source)} scenes")
    if source is None:
        from r1sim_sumo.scenario import ScenarioDataset
        from r1sim_sumo.tokens.batch import TokenizedDataset

        cache = Path(cfg.token_cache) if cfg.token_cache else out / "token_cache"
        # random scene order touches every shard: keep decompressed shards in memory (~50 MB per 256 scenes)
        extra = open_once(cfg.extra_train_data, lambda k, d: TokenizedDataset(ScenarioDataset(d, cache_shards=128), vocab,
                                                                                cache_dir=cache / f"extra{k}"))
        source = DatasetSource(TokenizedDataset(ScenarioDataset(cfg.train_data, cache_shards=128), vocab, cache_dir=cache / "train"),
                               extra)
    learner = GRPOLearner(model, ref, vocab, cfg)
    it = 0
    if resume and has_state:
        it = int(load_train_state(state_dir, model, learner.opt)["iter"])
        print(f"[finetune] resumed from {state_dir} at iteration {it}")

    batches = EpochBatches(len(source), cfg.batch_scenes, cfg.seed)
    max_iters = cfg.max_iters if cfg.max_iters is not None else cfg.epochs * batches.per_epoch
    log_path = out / "log.csv"
    if it == 0 or not log_path.exists():
        with open(log_path, "w", newline="") as f:
            csv.writer(f).writerow(LOG_FIELDS)
    else:  # drop rows past the resumed iteration (they are recomputed identically)
        with open(log_path) as f:
            rows = [r for r in csv.DictReader(f) if int(r["iter"]) <= it]
        with open(log_path, "w", newline="") as f:
            w = csv.DictWriter(f, LOG_FIELDS)
            w.writeheader()
            w.writerows(rows)

    if cfg.reward.offroad and not hasattr(source, "maps"):
        raise ValueError(f"reward.offroad: the scene source {type(source).__name__} has no maps; use train_data (a scenario "
                         "dataset folder) or set reward.offroad: false")
    sumo = None
    if cfg.rollout_source == "sumo":
        from r1sim_sumo.train.sumo_inloop import SumoInLoop

        if not isinstance(source, DatasetSource) or len(source.parts) > 1:
            raise ValueError("rollout_source=sumo needs scenes from train_data (a dataset with SUMO state files) and no "
                             "extra_train_data")
        sumo = SumoInLoop(cfg, model, vocab, source.ds.data, out / "sumo_inloop", workers=cfg.sumo_workers)
    straight = straight_token_table(vocab.traj[0]) if cfg.steady_start_prob > 0 else None
    t0 = time.time()
    bar = tqdm(total=max_iters, initial=it, disable=not progress, desc=f"finetune {cfg.method}", dynamic_ncols=True)
    while it < max_iters:
        torch.manual_seed(cfg.seed * 1_000_003 + it)
        gen = torch.Generator(device=dev).manual_seed(cfg.seed * 7_919 + it)
        idx = batches(it)
        batch = source.batch(idx).to(dev)
        if straight is not None:  # a steady past for vehicles whose reference speeds up now (steady_start_prob)
            batch, _ = steady_history(batch, None, cfg.steady_start_prob, gen, straight, at=CURRENT_POSE)
        maps = source.maps(idx) if cfg.reward.offroad else None
        ti = time.time()
        if sumo is not None:
            st = sumo.iteration(learner, idx, [source.ds[i] for i in idx], batch, gen, it, maps=maps)
        else:
            st = learner.iteration(batch, gen, maps=maps)
        it += 1
        dt = time.time() - ti
        n_roll = len(idx) * (1 if cfg.method == "sft" else cfg.num_rollouts)
        row = {k: st.get(k, "") for k in LOG_FIELDS}
        row.update(iter=it, scenes=len(idx), rollouts_per_s=n_roll / max(dt, 1e-9), wall_s=time.time() - t0)
        bar.update(1)
        bar.set_postfix({k: f"{st[k]:.3f}" for k in ("reward", "kl", "clip_frac", "collision_rate", "offroad_rate", "sft_dist_m")
                         if k in st})
        if it % cfg.log_every == 0 or it == max_iters:
            with open(log_path, "a", newline="") as f:
                csv.DictWriter(f, LOG_FIELDS).writerow(row)
        if it % cfg.ckpt_every == 0 or it == max_iters:
            save_train_state(state_dir, model, learner.opt, {"iter": it, "config": asdict(cfg)})
        if cfg.keep_every and it % cfg.keep_every == 0:
            save_checkpoint(out / f"ckpt-{it:06d}", model, vocab,
                            extra={"finetune": {"method": cfg.method, "iters": it, "config": asdict(cfg)}})
    bar.close()
    if sumo is not None:
        sumo.close()
    final = out / "final"
    save_checkpoint(final, model, vocab, extra={"finetune": {"method": cfg.method, "iters": it, "wall_s": time.time() - t0,
                                                             "config": asdict(cfg)}})
    return final


def run_from_cli(config_path: str | None, overrides: list[str], resume: bool, method: str | None = None) -> Path:
    if method:
        overrides = [*overrides, f"method={method}"]
    cfg = load_config(GRPOConfig, config_path, overrides)
    return finetune(cfg, resume=resume, progress=os.environ.get("R1SIM_NO_PROGRESS") is None)
