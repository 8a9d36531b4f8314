"""Token-level rewards of closed-loop rollouts for GRPO fine-tuning (R1Sim, Eq. reward and the reward ablation).

For every rollout ``i``, scene ``b``, agent ``a`` and future token step ``t`` (0..F-1, the token that moves the
agent from boundary pose ``t`` to ``t+1``, i.e. 10 Hz states ``5t+1 .. 5t+5`` after "now"):

- collision flag ``c_{i,t}``: any separating-axis overlap (:func:`r1sim_sumo.geometry.boxes_overlap`, the one
  shared batched SAT) between the agent's box and the box of any other valid agent *of the same rollout*,
  checked at the token's five 10 Hz states (``collision_at="states"``, default: a pass-through inside the
  0.5 s is caught) or only at its end pose (``collision_at="end"``, the paper's ``SAT(C_{i,t})`` read
  literally). Collisions with log-replayed agents count. Optionally a SUMO-reported collision flag of the
  same shape is OR-ed in (:mod:`r1sim_sumo.train.sumo_inloop`).
- offroad flag ``o_{i,t}`` (only with ``RewardConfig.offroad``): WOSAC's rule, any corner of the agent's box outside
  the drivable area (the union of the scene map's lane polygons, :mod:`r1sim_sumo.metrics.map_features`, the same
  geometry as the metric's ``realism/offroad_rate``), checked at the same states as the collision flag;
- ``r_safe = -1`` on a collision (or, with ``offroad``, on leaving the road) else ``+1``;
- ``r_dis = exp(-alpha * ||S_{i,t} - y_t||)``: ``S`` the rolled-out end pose of the token (box centre, metres,
  world frame) and ``y_t`` the reference (matched ground-truth) pose at that boundary, ``batch.pose_xy[:, :, 3+t]``.
- optional speed kernel (``RewardConfig.speed_weight`` ``w_v > 0``, a design change of this project, not the
  paper's): ``r_dis := (1 - w_v) r_dis + w_v exp(-speed_alpha |v_{i,t} - v^ref_t|)`` with ``v`` the token's mean speed
  [m/s] (end-pose displacement over 0.5 s) and ``v^ref`` the reference's over the same token (both boundary poses
  valid; otherwise the position kernel alone). The position kernel credits a token for the lag accumulated before
  it; the speed kernel credits each token for its own speed, so a token that speeds up like the reference on a free
  road is rewarded even behind the reference.

Variants (``RewardConfig.kind``), all ``[G, B, A, F]``:

- ``spr`` (paper default, safety-aware process reward): ``r_safe * r_dis``. As written, a colliding token far from
  the reference scores ~0, *better* than a colliding one near it (-1); kept as the default, see ``gated``.
- ``apr`` (additive process reward): ``r_safe + r_dis``.
- ``or`` (outcome reward): one value per agent trajectory, ``r_safe^out * exp(-alpha * ADE)`` with
  ``r_safe^out = -1`` if the agent collides at any step of the rollout and ``ADE`` its mean distance to the
  reference over the valid steps; broadcast to every token step (equivalent to a final-step reward credited to
  every token, the paper's "assesses trajectory quality only at the final step by aggregating" terms).
- ``ahr`` / ``shr`` (hybrids): ``(1 - w) * process + w * outcome`` with the additive (``apr`` + additive outcome
  ``r_safe^out + exp(-alpha ADE)``) or the safety-aware (``spr`` + ``or``) pair; ``w = outcome_weight``.
- ``gated``: ``r_dis`` if no collision else ``collision_reward`` (0 or -1): a collision is never better than
  any collision-free token, whatever the distance.

Masks: a reward exists where the agent is driven by the policy (``sim_mask``), its token is valid and the
reference pose at the token's end is valid (the paper masks segments without ground truth). With
``safety_without_reference=True`` steps without a reference still get the safety part (``r_dis := 1``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from r1sim_sumo.geometry import boxes_overlap
from r1sim_sumo.tokens.constants import CURRENT_POSE, STEPS_PER_TOKEN

REWARD_KINDS = ("spr", "apr", "or", "ahr", "shr", "gated")


@dataclass
class RewardConfig:
    """Token-level reward of GRPO (see the module docstring for the formulas)."""

    kind: str = "spr"
    """One of spr (paper default), apr, or, ahr, shr, gated."""
    alpha: float = 0.2
    """Distance kernel rate [1/m]: r_dis = exp(-alpha * distance_m); 0.2 halves the reward at ~3.5 m."""
    collision_at: str = "states"
    """'states': SAT at the token's five 10 Hz states; 'end': only at its end pose."""
    outcome_weight: float = 0.5
    """Hybrids ahr/shr: weight w of the outcome part, (1 - w) of the process part."""
    collision_reward: float = 0.0
    """gated: reward of a colliding token (0 or -1)."""
    safety_without_reference: bool = False
    """Keep the safety part (r_dis := 1) where the reference pose is invalid instead of masking the step."""
    offroad: bool = False
    """Leaving the drivable area is unsafe like a collision (r_safe = -1); needs the scenes' maps (``maps=``)."""
    speed_weight: float = 0.0
    """Weight w_v of the per-token speed kernel mixed into r_dis (0: the paper's reward)."""
    speed_alpha: float = 0.5
    """Speed kernel rate [s/m]: exp(-speed_alpha * |v - v_ref|); 0.5 halves it at ~1.4 m/s."""
    lane_change_weight: float = 1.0
    """Multiplies the rewards (hence the group advantages) of agents whose reference changes lanes in the window
    (:func:`~r1sim_sumo.metrics.lane_changes.lane_change_direction`); 1: the paper's reward. About 7% of the agents
    of the SUMO training recipes change lanes in a window."""
    speed_up_weight: float = 1.0
    """Multiplies the rewards (hence the group advantages) of agents whose reference speeds up in the window: its last
    valid token's mean speed is at least ``speed_up_gain`` above its first one (:func:`speed_up_weights`); 1: the
    paper's reward. A design change of this project (session 58): the policy copies its speed where SUMO's drivers
    accelerate, and these agents are where the reference shows it."""
    speed_up_gain: float = 1.0
    """Speed gain [m/s] between the reference's first and last valid tokens that marks an agent as speeding up."""
    must_merge_weight: float = 1.0
    """Multiplies the rewards of agents that start on a lane that ends beside one that goes on
    (:func:`~r1sim_sumo.metrics.lane_changes.must_merge_lanes`, e.g. an acceleration lane); needs the scenes' maps
    (``maps=``); 1: the paper's reward."""

    def __post_init__(self) -> None:
        if self.kind not in REWARD_KINDS:
            raise ValueError(f"RewardConfig.kind: '{self.kind}' unknown; use one of {REWARD_KINDS}")
        if self.collision_at not in ("states", "end"):
            raise ValueError(f"RewardConfig.collision_at: '{self.collision_at}' unknown; use 'states' or 'end'")
        if self.alpha < 0:
            raise ValueError(f"RewardConfig.alpha must be >= 0 [1/m], got {self.alpha}")
        if not 0.0 <= self.outcome_weight <= 1.0:
            raise ValueError(f"RewardConfig.outcome_weight must be in [0, 1], got {self.outcome_weight}")
        if not 0.0 <= self.speed_weight <= 1.0:
            raise ValueError(f"RewardConfig.speed_weight must be in [0, 1], got {self.speed_weight}")
        if self.speed_alpha < 0:
            raise ValueError(f"RewardConfig.speed_alpha must be >= 0 [s/m], got {self.speed_alpha}")
        if self.must_merge_weight <= 0:
            raise ValueError(f"RewardConfig.must_merge_weight must be > 0 (1: no weighting), got {self.must_merge_weight}")
        if self.lane_change_weight <= 0:
            raise ValueError(f"RewardConfig.lane_change_weight must be > 0 (1: no weighting), got {self.lane_change_weight}")
        if self.speed_up_weight <= 0:
            raise ValueError(f"RewardConfig.speed_up_weight must be > 0 (1: no weighting), got {self.speed_up_weight}")
        if self.speed_up_gain <= 0:
            raise ValueError(f"RewardConfig.speed_up_gain must be > 0 [m/s], got {self.speed_up_gain}")


class Rewards(NamedTuple):
    """Per-token rewards and their ingredients, all ``[G, B, A, F]``."""

    reward: torch.Tensor  # float32, 0 where ~mask
    mask: torch.Tensor  # bool, a reward exists (policy-driven agent, valid token, reference valid)
    collision: torch.Tensor  # bool, SAT (or simulator) collision during the token
    offroad: torch.Tensor  # bool, a box corner off the drivable area during the token (all False unless cfg.offroad)
    distance_m: torch.Tensor  # float32, ||S_{i,t} - y_t|| [m] (0 where the reference is invalid)


def token_collisions(xy_10hz: torch.Tensor, yaw_10hz: torch.Tensor, valid_10hz: torch.Tensor, agent_size: torch.Tensor,
                     collision_at: str = "states") -> torch.Tensor:
    """Per-token collision flags ``[G, B, A, F]`` from 10 Hz states (index 0 = now, ``5t+5`` = end of token t).

    :param xy_10hz: ``[G, B, A, 5F+1, 2]`` box centres [m]; ``yaw_10hz`` ``[G, B, A, 5F+1]`` [rad];
        ``valid_10hz`` ``[G, B, A, 5F+1]`` bool.
    :param agent_size: ``[B, A, 2]`` (length, width) [m].
    :param collision_at: ``"states"`` (the token's five states) or ``"end"`` (its end pose only).
    """
    G, B, A, N, _ = xy_10hz.shape
    F = (N - 1) // STEPS_PER_TOKEN
    idx = torch.arange(1, N, device=xy_10hz.device)  # states after "now"
    if collision_at == "end":
        idx = idx[STEPS_PER_TOKEN - 1 :: STEPS_PER_TOKEN]
    S = idx.numel() // F  # states per token checked
    x = xy_10hz[..., idx, 0].movedim(2, -1)  # [G, B, T, A]
    y = xy_10hz[..., idx, 1].movedim(2, -1)
    yaw = yaw_10hz[..., idx].movedim(2, -1)
    v = valid_10hz[..., idx].movedim(2, -1).bool()
    size = agent_size.to(x.dtype)  # [B, A, 2]
    # bounding circles first: two boxes can only overlap when their centres are closer than the sum of their
    # half-diagonals, so the exact SAT runs on those few candidate pairs instead of all A^2 (same flags, ~10x cheaper
    # in scenes of ~100 agents)
    radius = (0.5 * torch.linalg.vector_norm(size, dim=-1))[None, :, None, :].expand_as(x)  # [G, B, T, A]
    pts = torch.stack([x, y], -1).reshape(-1, A, 2)
    rad = radius.reshape(-1, A)
    dist = torch.cdist(pts, pts, compute_mode="donot_use_mm_for_euclid_dist")  # exact, also far from the origin
    near = dist <= (rad.unsqueeze(-1) + rad.unsqueeze(-2)) + 1e-6  # [GBT, A, A]
    vv = v.reshape(-1, A)
    near &= vv.unsqueeze(-1) & vv.unsqueeze(-2) & ~torch.eye(A, dtype=torch.bool, device=x.device)
    n_i, a_i, a_j = near.nonzero(as_tuple=True)
    hit = torch.zeros(G * B * idx.numel(), A, dtype=torch.bool, device=x.device)
    if n_i.numel():
        xf, yf, af = x.reshape(-1, A), y.reshape(-1, A), yaw.reshape(-1, A)
        b_of = (n_i // idx.numel()) % B
        li, wi = size[b_of, a_i, 0], size[b_of, a_i, 1]
        lj, wj = size[b_of, a_j, 0], size[b_of, a_j, 1]
        ov = boxes_overlap(xf[n_i, a_i], yf[n_i, a_i], af[n_i, a_i], li, wi, xf[n_i, a_j], yf[n_i, a_j], af[n_i, a_j], lj, wj)
        hit[n_i[ov], a_i[ov]] = True
    hit = hit.reshape(G, B, idx.numel(), A)  # [G, B, T, A]
    return hit.reshape(G, B, F, S, A).any(3).movedim(2, -1)  # [G, B, A, F]


def token_offroad(xy_10hz: torch.Tensor, yaw_10hz: torch.Tensor, valid_10hz: torch.Tensor, agent_size: torch.Tensor,
                  maps, collision_at: str = "states") -> torch.Tensor:
    """Per-token offroad flags ``[G, B, A, F]``: any box corner outside the drivable area (WOSAC, tolerance 0 m).

    :param xy_10hz, yaw_10hz, valid_10hz, agent_size, collision_at: as :func:`token_collisions` (world frame, box
        centres [m], yaw [rad]).
    :param maps: one :class:`~r1sim_sumo.scenario.MapPolylines` per scene ``b`` (the scene's map, in the same world
        frame as the rollouts); its drivable area is built once and cached (:func:`drivable_area`).
    """
    from r1sim_sumo.metrics.map_features import distance_to_road_edge, drivable_area, offroad_flags

    G, B, A, N, _ = xy_10hz.shape
    if len(maps) != B:
        raise ValueError(f"token_offroad: {len(maps)} maps for {B} scenes")
    F = (N - 1) // STEPS_PER_TOKEN
    idx = torch.arange(1, N)
    if collision_at == "end":
        idx = idx[STEPS_PER_TOKEN - 1 :: STEPS_PER_TOKEN]
    S = idx.numel() // F
    xy, yaw = xy_10hz[..., idx, :].detach().cpu().double().numpy(), yaw_10hz[..., idx].detach().cpu().double().numpy()
    v = valid_10hz[..., idx].bool().cpu().numpy()
    size = agent_size.detach().cpu().double().numpy()
    out = torch.zeros(G, B, A, F, dtype=torch.bool)
    areas = [drivable_area(m) if v[:, b].any() else None for b, m in enumerate(maps)]  # built (or cached) once each

    def scene(b: int) -> None:
        if areas[b] is None:
            return
        d = distance_to_road_edge(areas[b], xy[:, b, ..., 0], xy[:, b, ..., 1], yaw[:, b],
                                  size[b, :, 0], size[b, :, 1], v[:, b])  # [G, A, T]
        flags = torch.from_numpy(offroad_flags(d) & v[:, b])
        out[:, b] = flags.reshape(G, A, F, S).any(-1)

    workers = min(B, torch.get_num_threads())  # numpy / shapely / cKDTree release the GIL: scenes side by side
    if workers > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(scene, range(B)))
    else:
        for b in range(B):
            scene(b)
    return out.to(xy_10hz.device)


def token_speeds(pose_xy: torch.Tensor) -> torch.Tensor:
    """Mean speed [m/s] of each token ``[..., F]`` from its boundary poses ``[..., F+1, 2]`` (metres, 0.5 s apart)."""
    return torch.linalg.vector_norm(pose_xy[..., 1:, :] - pose_xy[..., :-1, :], dim=-1) / (STEPS_PER_TOKEN * 0.1)


def _mix_speed_kernel(r_dis: torch.Tensor, result, batch, cfg: RewardConfig) -> torch.Tensor:
    """``(1 - w_v) r_dis + w_v exp(-speed_alpha |v - v_ref|)`` where both tokens' boundary poses are valid."""
    G, B, A, F = result.token.shape
    ref = batch.pose_xy[:, :, CURRENT_POSE : CURRENT_POSE + F + 1]  # [B, A, F+1, 2]
    ref_valid = batch.pose_valid[:, :, CURRENT_POSE : CURRENT_POSE + F + 1].bool()
    v_ref = token_speeds(ref).unsqueeze(0)  # [1, B, A, F]
    ok = (ref_valid[..., 1:] & ref_valid[..., :-1]).unsqueeze(0) & result.valid[..., 1:].bool() & result.valid[..., :-1].bool()
    r_v = torch.exp(-cfg.speed_alpha * (token_speeds(result.pose_xy) - v_ref).abs())
    w = cfg.speed_weight
    return torch.where(ok, (1 - w) * r_dis + w * r_v, r_dis)


def lane_change_weights(batch, num_steps: int, weight: float) -> torch.Tensor:
    """``[B, A]`` reward weights: ``weight`` for agents whose reference (``batch``'s matched poses over the next
    ``num_steps`` tokens) changes lanes, 1 for the others."""
    from r1sim_sumo.metrics.lane_changes import lane_change_direction

    fut = slice(CURRENT_POSE + 1, CURRENT_POSE + 1 + num_steps)
    lc = lane_change_direction(batch.pose_xy[:, :, fut], batch.pose_yaw[:, :, fut], batch.pose_valid[:, :, fut],
                               batch.pose_xy[:, :, CURRENT_POSE], batch.pose_yaw[:, :, CURRENT_POSE],
                               batch.pose_valid[:, :, CURRENT_POSE])
    return torch.where(lc != 0, torch.full(lc.shape, float(weight), device=lc.device), torch.ones(lc.shape, device=lc.device))


def speed_up_weights(batch, num_steps: int, weight: float, gain_mps: float) -> torch.Tensor:
    """``[B, A]`` reward weights: ``weight`` for agents whose reference (``batch``'s matched boundary poses, metres,
    0.5 s apart, from "now" over ``num_steps`` tokens) has its last valid token's mean speed at least ``gain_mps``
    [m/s] above its first valid token's, 1 for the others (and for agents with fewer than two valid tokens)."""
    ref = batch.pose_xy[:, :, CURRENT_POSE : CURRENT_POSE + num_steps + 1]  # [B, A, F+1, 2]
    ok = batch.pose_valid[:, :, CURRENT_POSE : CURRENT_POSE + num_steps + 1].bool()
    ok = ok[..., 1:] & ok[..., :-1]  # [B, A, F] tokens with both boundary poses
    v = token_speeds(ref)
    steps = torch.arange(v.shape[-1], device=v.device)
    first = torch.where(ok, steps, v.shape[-1]).min(-1).values.clamp(max=v.shape[-1] - 1)
    last = torch.where(ok, steps, -1).max(-1).values.clamp(min=0)
    gain = v.gather(-1, last.unsqueeze(-1)).squeeze(-1) - v.gather(-1, first.unsqueeze(-1)).squeeze(-1)
    up = (ok.sum(-1) >= 2) & (gain >= gain_mps)
    return torch.where(up, torch.full(up.shape, float(weight), device=v.device), torch.ones(up.shape, device=v.device))


def must_merge_weights(batch, maps, weight: float) -> torch.Tensor:
    """``[B, A]`` reward weights: ``weight`` for agents whose current pose lies on a must-merge lane of their scene's
    map (:func:`~r1sim_sumo.metrics.lane_changes.poses_on_lanes`), 1 for the others."""
    from r1sim_sumo.metrics.lane_changes import must_merge_lanes, poses_on_lanes

    B, A = batch.pose_xy.shape[:2]
    w = torch.ones(B, A)
    xy = batch.pose_xy[:, :, CURRENT_POSE].detach().double().cpu().numpy()
    yaw = batch.pose_yaw[:, :, CURRENT_POSE].detach().double().cpu().numpy()
    ok = batch.pose_valid[:, :, CURRENT_POSE].detach().cpu().numpy()
    for b, m in enumerate(maps):
        lanes = must_merge_lanes(m)
        if lanes:
            w[b, torch.as_tensor(ok[b] & poses_on_lanes(m, lanes, xy[b], yaw[b]))] = float(weight)
    return w


def compute_rewards(result, batch, cfg: RewardConfig, extra_collision: torch.Tensor | None = None, maps=None) -> Rewards:
    """Token-level rewards of a :class:`~r1sim_sumo.rollout.engine.RolloutResult` against ``batch``'s reference.

    :param result: rollouts ``[G, B, A, F]`` (``token``, ``pose_xy``, ``xy_10hz``, ``yaw_10hz``, ``valid``, ``sim_mask``).
    :param batch: the :class:`~r1sim_sumo.tokens.SceneBatch` the rollouts started from (reference poses, sizes).
    :param extra_collision: optional ``[G, B, A, F]`` bool collisions reported by a simulator, OR-ed with SAT.
    :param maps: the ``B`` scenes' maps (:class:`~r1sim_sumo.scenario.MapPolylines`), needed by ``cfg.offroad``.
    """
    G, B, A, F = result.token.shape
    coll = token_collisions(result.xy_10hz, result.yaw_10hz, result.valid_10hz(), batch.agent_size, cfg.collision_at)
    if extra_collision is not None:
        coll = coll | extra_collision.bool()
    if cfg.offroad:
        if maps is None:
            raise ValueError("RewardConfig.offroad needs the scenes' maps: pass maps= (finetune takes them from train_data)")
        off = token_offroad(result.xy_10hz, result.yaw_10hz, result.valid_10hz(), batch.agent_size, maps, cfg.collision_at)
    else:
        off = torch.zeros_like(coll)
    unsafe = coll | off
    ref_xy = batch.pose_xy[:, :, CURRENT_POSE + 1 : CURRENT_POSE + 1 + F].unsqueeze(0)  # [1, B, A, F, 2]
    ref_ok = batch.pose_valid[:, :, CURRENT_POSE + 1 : CURRENT_POSE + 1 + F].bool().unsqueeze(0).expand(G, B, A, F)
    dist = torch.linalg.vector_norm(result.pose_xy[..., 1:, :] - ref_xy, dim=-1)  # [G, B, A, F]
    dist = torch.where(ref_ok, dist, torch.zeros_like(dist))
    act = result.sim_mask.bool()[None, :, :, None] & (result.token >= 0) & result.valid[..., 1:].bool()
    mask = act & (ref_ok | cfg.safety_without_reference)
    r_safe = 1.0 - 2.0 * unsafe.float()
    r_dis = torch.where(ref_ok, torch.exp(-cfg.alpha * dist), torch.ones_like(dist))
    if cfg.speed_weight > 0:
        r_dis = _mix_speed_kernel(r_dis, result, batch, cfg)

    def outcome(additive: bool) -> torch.Tensor:  # one value per agent trajectory, broadcast over t
        n = (act & ref_ok).sum(-1, keepdim=True)
        ade = (dist * (act & ref_ok)).sum(-1, keepdim=True) / n.clamp(min=1)
        d_out = torch.where(n > 0, torch.exp(-cfg.alpha * ade), torch.ones_like(ade))
        s_out = 1.0 - 2.0 * (unsafe & act).any(-1, keepdim=True).float()
        return (s_out + d_out if additive else s_out * d_out).expand(G, B, A, F)

    w = cfg.outcome_weight
    if cfg.kind == "spr":
        r = r_safe * r_dis
    elif cfg.kind == "apr":
        r = r_safe + r_dis
    elif cfg.kind == "or":
        r = outcome(additive=False)
    elif cfg.kind == "ahr":
        r = (1 - w) * (r_safe + r_dis) + w * outcome(additive=True)
    elif cfg.kind == "shr":
        r = (1 - w) * (r_safe * r_dis) + w * outcome(additive=False)
    else:  # gated
        r = torch.where(unsafe, torch.full_like(r_dis, cfg.collision_reward), r_dis)
    if cfg.lane_change_weight != 1.0:
        r = r * lane_change_weights(batch, F, cfg.lane_change_weight).unsqueeze(0).unsqueeze(-1)
    if cfg.speed_up_weight != 1.0:
        r = r * speed_up_weights(batch, F, cfg.speed_up_weight, cfg.speed_up_gain).to(r.device).unsqueeze(0).unsqueeze(-1)
    if cfg.must_merge_weight != 1.0:
        if maps is None:
            raise ValueError("RewardConfig.must_merge_weight needs the scenes' maps: pass maps= (finetune takes them from its scenes)")
        r = r * must_merge_weights(batch, maps, cfg.must_merge_weight).to(r.device).unsqueeze(0).unsqueeze(-1)
    r = torch.where(mask, r, torch.zeros_like(r)).float()
    return Rewards(r, mask, coll & act, off & act, dist)
