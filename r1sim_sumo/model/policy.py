"""SMART-style next-token traffic policy with a per-layer key/value cache for rollouts.

Reads top to bottom: map encoder (once per scene) -> agent embedding (previous motion token + type + size)
-> agent layers (temporal over the agent's own recent steps, map-to-agent over the k nearest map tokens,
agent-to-agent over the k nearest agents at the same step) -> token head (one head of width V_max; ids at or
above the agent type's vocabulary size are masked to -inf).

Time: step ``k`` (0..17) sees boundary pose ``k`` and the previous token ``k-1`` (a per-type start embedding
when there is none) and its logits predict token ``k`` (the move from pose k to pose k+1, 0.5 s).
Rollouts stack ``G`` rollouts of ``B`` scenes as ``S = G * B`` sequences, row ``s = g * B + b``.
Neighbourhoods are gathered k-nearest sets (cost O(A * k) per step). The relative encodings of all edges
(temporal, map, agent) are computed by one Fourier embedding per forward/step and shared by every layer;
each layer maps its queries into edge-feature space (see :class:`~r1sim_sumo.model.layers.RelAttentionBlock`).
Poses are packed as ``[x, y, cos yaw, sin yaw]`` (metres, world frame).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from r1sim_sumo._threads import few_threads
from r1sim_sumo.model import gathered_attention
from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.layers import (
    MAP_SPEED_SCALE_MPS,
    POS_SCALE_M,
    REL_POSE_DIM,
    FourierEmbedding,
    RelAttentionBlock,
    check_tokens,
    knn,
    map_kind_index,
    pack_pose,
    rel_pose_features,
)
from r1sim_sumo.model.packed import packed_logits
from r1sim_sumo.tokens.constants import CURRENT_POSE, FRAMES_PER_TOKEN, N_MAP_PTS, N_TOK, TOKEN_DT_S

TOKEN_FEAT_DIM = 4 * (FRAMES_PER_TOKEN - 1)  # (x/5, y/5, cos yaw, sin yaw) of frames 1..5
SLOT_FEAT_DIM = 4  # per edge slot: time gap, is temporal, is map, is agent
DESIRED_SPEED_SCALE_MPS = 30.0  # desired speeds enter the model divided by this [m/s]
SPEED_GAP_SCALE_MPS = 10.0  # desired minus previous-token speed enters the model divided by this [m/s]
SPEED_TREND_SCALE_MPS = 2.0  # previous-token speed minus the one before it enters the model divided by this [m/s]


def _desired(batch) -> Tensor | None:
    """The batch's per-agent desired speeds ``[B, A]`` [m/s] (``None`` for batches without them)."""
    return getattr(batch, "agent_desired_speed", None)


class MapContext(NamedTuple):
    """Encoded map of B scenes (run once per scene, shared by all rollouts)."""

    feat: Tensor  # [B, M, D] encoded map tokens
    pose: Tensor  # [B, M, 4] packed pose of the segment centres (x, y [m], cos, sin of the segment yaw)
    tl: Tensor  # [B, M, N_POSE] int64 traffic-light state per boundary pose
    valid: Tensor  # [B, M] bool


@dataclass
class RolloutCache:
    """State of a cached rollout over ``S = G * B`` sequences (row ``g * B + b``); built by ``init_rollout``.

    The temporal buffers have ``span - 1`` leading padding slots; step ``k`` lives in slot ``k + span - 1``.
    """

    num_scenes: int  # B
    num_rollouts: int  # G
    next_step: int  # the step the next ``step`` call must process
    map_ctx: MapContext
    token_table: Tensor  # [V_total + n_types, D] embedding of every previous-token id
    agent_static: Tensor  # [S, A, D] type + size embedding
    agent_type: Tensor  # [S, A]
    agent_mask: Tensor  # [S, A]
    vocab_limit: Tensor  # [S, A] vocabulary size of each agent's type
    head_invalid: Tensor  # [S, A, V_max] bool, ids outside the agent type's vocabulary
    t_xn: Tensor  # [L, S, A, span-1+18, D] normalised features of the cached steps per layer
    t_pose: Tensor  # [S, A, span-1+18, 4] packed poses of the cached steps
    t_valid: Tensor  # [S, A, span-1+18] bool
    desired_speed: Tensor | None = None  # [S, A] [m/s], NaN unknown (models with ``speed_gap_input``)
    prev_speed: Tensor | None = None  # [S, A] [m/s] mean speed of the last step's input token, NaN unknown (``speed_trend_input``)


class TrafficPolicy(nn.Module):
    """Next-token prediction over motion tokens of all agents of a scene.

    :param config: sizes and neighbourhoods.
    :param token_traj: per agent type (vehicle, cyclist, pedestrian) the vocabulary trajectories
        ``[V_t, 6, 3]`` (x, y, yaw of the 6 frames in the start pose's frame; token 0 = standing still).
        They define the shape features of the previous-token embedding; the checkpoint stores them.
    """

    def __init__(self, config: PolicyConfig, token_traj: Sequence[Tensor]) -> None:
        super().__init__()
        self.config = c = config
        D, L, nT = c.hidden_dim, c.agent_layers, c.num_agent_types
        self._register_vocab(token_traj)
        v_total = sum(c.vocab_sizes)

        def block() -> RelAttentionBlock:  # every edge feature = [source content (D), relative encoding (D)]
            return RelAttentionBlock(D, c.num_heads, 2 * D, c.ffn_mult, c.dropout)

        # map encoder
        self.map_in = nn.Sequential(nn.Linear(2 * N_MAP_PTS + 1, D), nn.LayerNorm(D), nn.ReLU(inplace=True), nn.Linear(D, D))
        self.map_kind = nn.Embedding(c.num_map_kinds, D)
        self.map_edge = FourierEmbedding(REL_POSE_DIM, D, c.fourier_bands, out_linear=False)
        self.map_blocks = nn.ModuleList(block() for _ in range(c.map_layers))
        self.map_norm = nn.LayerNorm(D)
        self.tl_emb = nn.Embedding(c.num_tl_states, D)
        # agent embedding: previous token (shape + motion + learned) + type + size
        self.token_mlp = nn.Sequential(nn.Linear(TOKEN_FEAT_DIM, D), nn.ReLU(inplace=True), nn.Linear(D, D))
        self.token_motion_emb = FourierEmbedding(2, D, c.fourier_bands)  # speed, yaw rate of the token
        self.token_emb = nn.Embedding(v_total + nT, D)  # learned part; the last nT rows are start tokens
        self.type_emb = nn.Embedding(nT, D)
        self.size_emb = FourierEmbedding(2, D, c.fourier_bands)  # length, width
        if c.desired_speed_input:  # the driver's desired speed; the output starts at zero, so adding it to a
            self.desired_speed_emb = FourierEmbedding(1, D, c.fourier_bands)  # trained model leaves its logits unchanged
            nn.init.zeros_(self.desired_speed_emb.lin2.weight)
            nn.init.zeros_(self.desired_speed_emb.lin2.bias)
        if c.speed_gap_input:  # desired minus previous-token speed, per node; zero output at the start likewise
            self.speed_gap_emb = FourierEmbedding(1, D, c.fourier_bands)
            nn.init.zeros_(self.speed_gap_emb.lin2.weight)
            nn.init.zeros_(self.speed_gap_emb.lin2.bias)
        if c.speed_trend_input:  # previous-token speed minus the one before, per node; zero output at the start likewise
            self.speed_trend_emb = FourierEmbedding(1, D, c.fourier_bands)
            nn.init.zeros_(self.speed_trend_emb.lin2.weight)
            nn.init.zeros_(self.speed_trend_emb.lin2.bias)
        # relative encoding of every edge (temporal, map, agent), shared by all agent layers
        self.edge_emb = FourierEmbedding(REL_POSE_DIM + 1, D, c.fourier_bands, out_linear=False)
        self.edge_slot = nn.Linear(SLOT_FEAT_DIM, D, bias=False)
        self.t_blocks = nn.ModuleList(block() for _ in range(L))
        self.m_blocks = nn.ModuleList(block() for _ in range(L))
        self.a_blocks = nn.ModuleList(block() for _ in range(L))
        self.head = nn.Sequential(nn.LayerNorm(D), nn.Linear(D, D), nn.ReLU(inplace=True), nn.Linear(D, c.vocab_max))

    # ------------------------------------------------------------------ vocabulary buffers

    def _register_vocab(self, token_traj: Sequence[Tensor]) -> None:
        c = self.config
        if len(token_traj) != c.num_agent_types:
            raise ValueError(f"token_traj: expected {c.num_agent_types} per-type tensors, got {len(token_traj)}")
        feats, motion, speed = [], [], []
        for t, (traj, v) in enumerate(zip(token_traj, c.vocab_sizes, strict=True)):
            traj = torch.as_tensor(traj, dtype=torch.float32)
            if traj.shape != (v, FRAMES_PER_TOKEN, 3):
                raise ValueError(
                    f"token_traj[{t}]: shape {tuple(traj.shape)} != (vocab_sizes[{t}]={v}, {FRAMES_PER_TOKEN}, 3); "
                    "build the PolicyConfig with vocab_sizes matching the vocabulary"
                )
            f = traj[:, 1:]  # [V, 5, 3]
            feats.append(torch.stack([f[..., 0] / POS_SCALE_M, f[..., 1] / POS_SCALE_M, f[..., 2].cos(), f[..., 2].sin()], -1).flatten(1))
            end = traj[:, -1]  # [V, 3]
            speed.append(end[:, :2].norm(dim=-1) / TOKEN_DT_S)  # [V] mean speed over the token [m/s]
            motion.append(torch.stack([speed[-1] / 10.0, end[:, 2] / TOKEN_DT_S], -1))
        motion.append(torch.zeros(c.num_agent_types, 2))  # start tokens: no known motion
        speed.append(torch.full((c.num_agent_types,), float("nan")))  # start tokens: unknown speed
        self.register_buffer("token_speed", torch.cat(speed), persistent=False)  # [V_total + nT] mean speed [m/s]
        sizes = torch.tensor(c.vocab_sizes)
        self.register_buffer("token_feat", torch.cat(feats), persistent=False)  # [V_total, 20]
        self.register_buffer("token_motion", torch.cat(motion), persistent=False)  # [V_total + nT, 2]
        self.register_buffer("type_offset", torch.cumsum(sizes, 0) - sizes, persistent=False)  # [nT]
        self.register_buffer("type_vocab", sizes, persistent=False)  # [nT]
        self.register_buffer("head_invalid", torch.arange(c.vocab_max)[None] >= sizes[:, None], persistent=False)  # [nT, Vmax]
        W = c.temporal_span
        slot = torch.zeros(W + c.map_agent_k + c.agent_k, SLOT_FEAT_DIM)  # per edge slot, see _edges
        slot[:W, 0] = torch.arange(W - 1, -1, -1) / W  # time gap, oldest .. newest (self = 0)
        slot[:W, 1], slot[W : W + c.map_agent_k, 2], slot[W + c.map_agent_k :, 3] = 1.0, 1.0, 1.0
        self.register_buffer("slot_feat", slot, persistent=False)

    def token_table(self) -> Tensor:
        """Embedding of every previous-token id: ``[V_total + n_types, D]`` (type offsets, then start tokens).

        In inference (eval mode, no grad) the table is computed once and reused until a weight it depends on
        changes (tracked by the tensors' version counters): online planning builds a cache every decision."""
        if self.training or torch.is_grad_enabled():
            return self._compute_token_table()
        srcs = [self.token_feat, self.token_motion, *self.token_mlp.parameters(), self.token_emb.weight,
                *self.token_motion_emb.parameters()]
        key = tuple((t.data_ptr(), t._version) for t in srcs)
        cached = getattr(self, "_token_table_cache", None)
        if cached is None or cached[0] != key:
            cached = (key, self._compute_token_table())
            self._token_table_cache = cached
        return cached[1]

    def _compute_token_table(self) -> Tensor:
        shape = self.token_mlp(self.token_feat)  # [V_total, D]
        shape = torch.cat([shape, shape.new_zeros(self.config.num_agent_types, shape.shape[1])])
        return shape + self.token_emb.weight + self.token_motion_emb(self.token_motion)

    def _agent_static(self, agent_type: Tensor, agent_size: Tensor, desired_speed: Tensor | None = None) -> Tensor:
        """Type + size (+ desired speed) embedding ``[S, A, D]`` from ``agent_size [S, A, 2]`` (length, width [m])
        and ``desired_speed [S, A]`` [m/s] (NaN = unknown: no contribution; used when the config has
        ``desired_speed_input``)."""
        x = self.type_emb(agent_type) + self.size_emb(agent_size / agent_size.new_tensor([5.0, 2.0]))
        if self.config.desired_speed_input:
            if desired_speed is None:
                raise ValueError("this model takes each agent's desired speed (config desired_speed_input); the batch "
                                 "has no 'agent_desired_speed' (build it with r1sim_sumo.tokens.batch.collate)")
            v = desired_speed.to(agent_size.dtype)
            known = torch.isfinite(v)
            emb = self.desired_speed_emb((torch.where(known, v, 0.0) / DESIRED_SPEED_SCALE_MPS).unsqueeze(-1))
            x = x + emb * known.unsqueeze(-1).to(emb.dtype)
        return x

    def _speed_gap(self, token_index: Tensor, desired_speed: Tensor | None) -> Tensor | float:
        """Embedding ``[..., D]`` of desired speed minus the previous token's mean speed for rows ``token_index``
        of ``token_table`` and ``desired_speed`` [m/s] of the same shape (NaN = unknown: no contribution); ``0.0``
        for models without ``speed_gap_input``."""
        if not self.config.speed_gap_input:
            return 0.0
        if desired_speed is None:
            raise ValueError("this model takes each agent's desired speed (config speed_gap_input); the batch has no "
                             "'agent_desired_speed' (build it with r1sim_sumo.tokens.batch.collate)")
        gap = desired_speed.float() - self.token_speed[token_index]
        known = torch.isfinite(gap)
        emb = self.speed_gap_emb((torch.where(known, gap, 0.0) / SPEED_GAP_SCALE_MPS).unsqueeze(-1))
        return emb * known.unsqueeze(-1).to(emb.dtype)

    def _speed_trend(self, token_index: Tensor, before_index: Tensor) -> Tensor | float:
        """Embedding ``[..., D]`` of the previous token's mean speed minus the mean speed of the token before it
        [m/s] (rows ``token_index`` and ``before_index`` of ``token_table``, same shape; a start token = unknown:
        no contribution); ``0.0`` for models without ``speed_trend_input``."""
        if not self.config.speed_trend_input:
            return 0.0
        return self._speed_trend_emb(self.token_speed[token_index] - self.token_speed[before_index])

    def _speed_trend_emb(self, trend: Tensor) -> Tensor:
        """Embedding ``[..., D]`` of speed changes ``trend [...]`` [m/s] (NaN = unknown: no contribution)."""
        known = torch.isfinite(trend)
        emb = self.speed_trend_emb((torch.where(known, trend, 0.0) / SPEED_TREND_SCALE_MPS).unsqueeze(-1))
        return emb * known.unsqueeze(-1).to(emb.dtype)

    def _token_index(self, prev_token: Tensor, agent_type: Tensor) -> Tensor:
        """Row of ``token_table`` for ``prev_token [S, A, T]`` (-1 = none -> the type's start token)."""
        ty = agent_type.unsqueeze(-1)
        return torch.where(prev_token >= 0, self.type_offset[ty] + prev_token, self.token_feat.shape[0] + ty)

    # ------------------------------------------------------------------ map encoder

    def encode_map(self, batch) -> MapContext:
        """Encode the map tokens of ``batch`` (``map_pts [B, M, 11, 2]`` in each segment's own frame, ``map_pos``
        [m, world], ``map_yaw``, ``map_kind``, ``map_speed`` [m/s], ``map_tl``, ``map_mask``) -> :class:`MapContext`."""
        c = self.config
        B, M = batch.map_mask.shape
        D = c.hidden_dim
        cos, sin = batch.map_yaw.cos(), batch.map_yaw.sin()  # [B, M]
        mid = batch.map_pts[:, :, N_MAP_PTS // 2]  # [B, M, 2] segment middle, own frame
        xy = batch.map_pos + torch.stack([mid[..., 0] * cos - mid[..., 1] * sin, mid[..., 0] * sin + mid[..., 1] * cos], -1)
        pose = torch.cat([xy, cos.unsqueeze(-1), sin.unsqueeze(-1)], -1)  # [B, M, 4]
        feat_in = torch.cat([batch.map_pts.flatten(2) / POS_SCALE_M, batch.map_speed.unsqueeze(-1) / MAP_SPEED_SCALE_MPS], -1)
        x = self.map_in(feat_in) + self.map_kind(map_kind_index(batch.map_kind, c.num_map_kinds))  # [B, M, D]
        valid = batch.map_mask.bool()
        idx, ok = knn(xy, xy, valid, c.map_k, c.map_radius_m)  # [B, M, k]
        ok = ok & valid.unsqueeze(-1)
        flat = idx + (torch.arange(B, device=idx.device) * M).view(B, 1, 1)
        r = self.map_edge(rel_pose_features(pose.reshape(-1, 4)[flat], pose))  # [B, M, k, D]
        for blk in self.map_blocks:
            xn = blk.normed(x)
            x = blk(x, xn, torch.cat([xn.reshape(B * M, D)[flat], r], -1), ok)
        tl = batch.map_tl.long().clamp(0, c.num_tl_states - 1)
        return MapContext(self.map_norm(x), pose, tl, valid)

    # ------------------------------------------------------------------ edges

    def _edges(self, ctx: MapContext, pose: Tensor, valid: Tensor, win_pose: Tensor, win_valid: Tensor, steps: Tensor):
        """Neighbourhoods and edge features of agent nodes ``pose [S, A, T, 4]``, ``valid [S, A, T]``.

        :param win_pose: ``[S, A, T, W, 4]`` poses of each node's temporal window (``win_valid`` its mask).
        :param steps: token step of each node, broadcastable to ``[S, A, T, 1]`` (for traffic-light states).
        :return: dict with relative encodings ``rt/rm/ra [S, A, T, E_x, D]``, masks ``t_mask/m_mask/a_mask``,
            map content ``m_content [S, A, T, k_m, D]`` and the flat agent-node index ``a_idx [S, A, T, k_a]``.
        """
        c = self.config
        S, A, T = valid.shape
        B, M = ctx.valid.shape
        G = S // B
        W = win_pose.shape[-2]
        map_pose = ctx.pose.reshape(B * M, 4)
        # k nearest map tokens (per scene, over all rollouts of it)
        q = pose[..., :2].reshape(G, B, A * T, 2).transpose(0, 1).reshape(B, G * A * T, 2)
        m_idx, m_ok = knn(q, ctx.pose[..., :2], ctx.valid, c.map_agent_k, c.map_agent_radius_m)
        km = m_idx.shape[-1]
        m_idx = (m_idx + (torch.arange(B, device=q.device) * M).view(B, 1, 1)).view(B, G, A, T, km).transpose(0, 1).reshape(S, A, T, km)
        m_ok = m_ok.view(B, G, A, T, km).transpose(0, 1).reshape(S, A, T, km)
        # k nearest other agents at the same step
        qa = pose[..., :2].transpose(1, 2).reshape(S * T, A, 2)
        a_idx, a_ok = knn(qa, qa, valid.transpose(1, 2).reshape(S * T, A), c.agent_k, c.agent_radius_m, exclude_self=True)
        ka = a_idx.shape[-1]
        base = (torch.arange(S, device=q.device) * A).view(S, 1, 1, 1)
        t = torch.arange(T, device=q.device).view(1, T, 1, 1)
        a_idx = ((base + a_idx.view(S, T, A, ka)) * T + t).transpose(1, 2)  # [S, A, T, ka] flat node index
        a_ok = a_ok.view(S, T, A, ka).transpose(1, 2)
        # one relative encoding for all edges
        src = torch.cat([win_pose, map_pose[m_idx], pose.reshape(S * A * T, 4)[a_idx]], -2)  # [S, A, T, E, 4]
        rel = rel_pose_features(src, pose)  # [S, A, T, E, 5]
        slot = self.slot_feat  # [E, 4]; fewer map/agent slots when a scene has fewer than k of them
        if km != c.map_agent_k or ka != c.agent_k:
            Wm = W + c.map_agent_k
            slot = torch.cat([slot[:W], slot[W : W + km], slot[Wm : Wm + ka]])
        feat = torch.cat([rel, slot[:, :1].expand(rel.shape[:-1] + (1,))], -1)  # + time gap
        phi = self.edge_emb(feat, self.edge_slot(slot))  # [S, A, T, E, D]
        v = valid.unsqueeze(-1)
        return dict(
            rt=phi[..., :W, :], rm=phi[..., W : W + km, :], ra=phi[..., W + km :, :],
            t_mask=win_valid & v, m_mask=m_ok & v, a_mask=a_ok & v, a_idx=a_idx,
            m_content=ctx.feat.reshape(B * M, -1)[m_idx] + self.tl_emb(ctx.tl.reshape(B * M, -1)[m_idx, steps]),
        )

    # ------------------------------------------------------------------ agent layers (shared by forward and step)

    def _decode(self, x: Tensor, ed: dict, t_source) -> Tensor:
        """Run the agent layers on nodes ``x [S, A, T, D]`` with the edges ``ed`` of :meth:`_edges`.

        ``t_source(layer, xn [S, A, T, D]) -> [S, A, T, W, D]`` gives the normalised features of each node's
        temporal window at that layer.
        """
        D = self.config.hidden_dim
        if "t_idx" in ed and gathered_attention.usable(x, ed["rt"]):  # packed nodes on a CPU: the C kernel
            return self._decode_gathered(x, ed)
        if not torch.is_grad_enabled() and gathered_attention.usable(x, ed["rt"]):  # inference on a CPU (steps)
            return self._decode_dense_gathered(x, ed, t_source)
        m_edge = torch.cat([ed["m_content"], ed["rm"]], -1)  # [S, A, T, km, 2D], the same for every layer
        for li, (bt, bm, ba) in enumerate(zip(self.t_blocks, self.m_blocks, self.a_blocks, strict=True)):
            xn = bt.normed(x)
            x = bt(x, xn, torch.cat([t_source(li, xn), ed["rt"]], -1), ed["t_mask"])
            x = bm(x, bm.normed(x), m_edge, ed["m_mask"])
            xn = ba.normed(x)
            x = ba(x, xn, torch.cat([xn.reshape(-1, D)[ed["a_idx"]], ed["ra"]], -1), ed["a_mask"])
        return x

    def _decode_dense_gathered(self, x: Tensor, ed: dict, t_source) -> Tensor:
        """:meth:`_decode` without building the edge features: the dense edges of :meth:`_edges` (every node's window,
        map and agent neighbours, as in a rollout step) handed to the C kernel by parts (temporal and map content one
        row per edge, agent neighbours as rows of the layer's normalised nodes). Inference only (no backward through
        the per-edge sources); same values up to float rounding; ~1.3x faster agent layers at 700 agents."""
        S, A, T, D = x.shape
        N = S * A * T
        rt, rm, ra = ed["rt"], ed["rm"], ed["ra"]
        W, km, ka = rt.shape[-2], rm.shape[-2], ra.shape[-2]
        rt, rm, ra = rt.reshape(N, W, -1), rm.reshape(N, km, -1), ra.reshape(N, ka, -1)
        t_mask, m_mask = ed["t_mask"].reshape(N, W), ed["m_mask"].reshape(N, km)
        a_mask, a_idx = ed["a_mask"].reshape(N, ka), ed["a_idx"].reshape(N, ka)
        m_src = ed["m_content"].reshape(N * km, D)
        x = x.reshape(N, D)
        for li, (bt, bm, ba) in enumerate(zip(self.t_blocks, self.m_blocks, self.a_blocks, strict=True)):
            xn = bt.normed(x)
            t_src = t_source(li, xn.view(S, A, T, D)).reshape(N * W, D)
            x = bt.forward_gathered(x, xn, t_src, None, rt, t_mask)
            x = bm.forward_gathered(x, bm.normed(x), m_src, None, rm, m_mask)
            xn = ba.normed(x)
            x = ba.forward_gathered(x, xn, xn, a_idx, ra, a_mask)
        return x.view(S, A, T, D)

    def _decode_gathered(self, x: Tensor, ed: dict) -> Tensor:
        """:meth:`_decode` on packed nodes ``x [N, D]`` whose edges come as index lists (``t_idx``, ``a_idx`` into
        the nodes), with the neighbours' features gathered inside the attention kernel
        (:meth:`RelAttentionBlock.forward_gathered`) instead of concatenated per edge. Same values up to rounding."""
        N, km, D = ed["m_content"].shape
        m_src = ed["m_content"].reshape(N * km, D)  # map content differs per edge (signal state at the node's step)
        for bt, bm, ba in zip(self.t_blocks, self.m_blocks, self.a_blocks, strict=True):
            xn = bt.normed(x)
            x = bt.forward_gathered(x, xn, xn, ed["t_idx"], ed["rt"], ed["t_mask"])
            x = bm.forward_gathered(x, bm.normed(x), m_src, None, ed["rm"], ed["m_mask"])
            xn = ba.normed(x)
            x = ba.forward_gathered(x, xn, xn, ed["a_idx"], ed["ra"], ed["a_mask"])
        return x

    # ------------------------------------------------------------------ teacher-forced forward

    def forward(self, batch, map_ctx: MapContext | None = None, last_step_only: bool = False,
                out_mask: Tensor | None = None, prev_hidden: Tensor | None = None) -> Tensor:
        """Teacher-forced logits ``[B, A, T, V_max]`` (T = 18 token steps, or 1 with ``last_step_only``: the
        head then runs only on the last step, for online planning); step k sees pose k and token k-1, predicts
        token k.

        With ``out_mask [B, A, T]`` (training): only the real map tokens and valid agent nodes are computed
        (:func:`r1sim_sumo.model.packed.packed_logits`) and the logits ``[n, V_max]`` of the ``out_mask`` nodes
        are returned in ``out_mask.nonzero()`` order; equal to ``forward(batch)[out_mask]`` up to rounding.
        ``prev_hidden`` (packed only): nodes whose previous-token input is hidden (history masking in training)."""
        if out_mask is not None:
            return packed_logits(self, batch, out_mask, prev_hidden)
        c = self.config
        ctx = self.encode_map(batch) if map_ctx is None else map_ctx
        tok, tok_valid = batch.agent_token, batch.agent_token_valid.bool()
        B, A, T = tok.shape
        check_tokens(tok, tok_valid, self.type_vocab[batch.agent_type])
        W = c.temporal_span
        prev = torch.where(tok_valid, tok, -1)
        prev = torch.cat([prev.new_full((B, A, 1), -1), prev[:, :, :-1]], 2)  # [B, A, T]
        pose = pack_pose(batch.pose_xy[:, :, :T], batch.pose_yaw[:, :, :T])  # [B, A, T, 4]
        valid = batch.pose_valid[:, :, :T].bool() & batch.agent_mask.bool().unsqueeze(-1)  # [B, A, T]
        tix = self._token_index(prev, batch.agent_type)  # [B, A, T]
        desired = _desired(batch)
        x = self.token_table()[tix] + self._agent_static(batch.agent_type, batch.agent_size, desired).unsqueeze(2)
        x = x + self._speed_gap(tix, None if desired is None else desired.unsqueeze(2).expand_as(tix))
        if c.speed_trend_input:  # token k-2 of each node: the input token of the node before
            before = torch.cat([prev.new_full((B, A, 1), -1), prev[:, :, :-1]], 2)
            x = x + self._speed_trend(tix, self._token_index(before, batch.agent_type))

        def win(t: Tensor, fill=0.0) -> Tensor:  # [B, A, T, ...] -> [B, A, T, W, ...], left-padded windows
            p = F.pad(t.movedim(2, -1), (W - 1, 0), value=fill).unfold(-1, W, 1)  # [B, A, ..., T, W]
            return p.movedim(-2, 2).movedim(-1, 3)

        steps = torch.arange(T, device=pose.device).view(1, 1, T, 1)
        ed = self._edges(ctx, pose, valid, win(pose), win(valid, False), steps)
        x = self._decode(x, ed, lambda li, xn: win(xn))
        logits = self.head(x[:, :, -1:] if last_step_only else x)
        return logits.masked_fill_(self.head_invalid[batch.agent_type].unsqueeze(2), float("-inf"))

    def loss(self, batch, logits: Tensor, label_smoothing: float = 0.1, include_history: bool = True,
             targets: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Label-smoothed cross-entropy over valid tokens (smoothing spread over the type's own vocabulary).

        :param targets: ``[B, A, n_tok]`` labels instead of ``batch.agent_token`` (noised matching: the inputs
            are the drawn tokens, the labels the recovering ones, see :func:`r1sim_sumo.tokens.matching.match_agents`).
        :return: (mean loss, top-1 accuracy) over tokens with ``agent_token_valid & agent_mask`` (and, when
            ``include_history`` is False, only future tokens 2..17).
        """
        valid = batch.agent_token_valid.bool() & batch.agent_mask.bool().unsqueeze(-1) & batch.pose_valid[:, :, : logits.shape[2]].bool()
        if not include_history:
            valid = valid.clone()
            valid[:, :, :CURRENT_POSE] = False
        if targets is not None:  # -1: a label to ignore (e.g. rewritten steps of r1sim_sumo.train.steady_history)
            valid = valid & (targets >= 0)
        ty = batch.agent_type.unsqueeze(-1).expand_as(valid)[valid]  # [n]
        lg = logits[valid]  # [n, V]
        target = (batch.agent_token if targets is None else targets)[valid]  # [n]
        if lg.shape[0] == 0:
            zero = logits.sum() * 0.0
            return zero, zero.detach()
        logp = torch.log_softmax(lg.float(), -1)
        nll = -logp.gather(-1, target.unsqueeze(-1)).squeeze(-1)
        smooth = -logp.masked_fill(self.head_invalid[ty], 0.0).sum(-1) / self.type_vocab[ty]
        loss = ((1.0 - label_smoothing) * nll + label_smoothing * smooth).mean()
        acc = (lg.argmax(-1) == target).float().mean()
        return loss, acc.detach()

    # ------------------------------------------------------------------ cached rollout

    def init_rollout(self, batch, num_rollouts: int = 1, upto_step: int = CURRENT_POSE, map_ctx: MapContext | None = None,
                     last_step: int = N_TOK - 1) -> RolloutCache:
        """Encode the map once, run the teacher-forced steps ``0 .. upto_step-1`` for ``G = num_rollouts`` copies
        of every scene, and return the cache; the next call is ``step(cache, upto_step, ...)``. The cache holds the
        slots of steps up to ``last_step`` (a caller that stops earlier, e.g. one drop-in decision, allocates less)."""
        c = self.config
        G = int(num_rollouts)
        ctx = self.encode_map(batch) if map_ctx is None else map_ctx
        B, A = batch.agent_mask.shape
        if not upto_step - 1 <= last_step < N_TOK:
            raise ValueError(f"init_rollout: last_step must be in [{upto_step - 1}, {N_TOK}), got {last_step}")
        if G > 1:  # the teacher-forced history is the same for every rollout: run it once, then copy the cache
            one = self.init_rollout(batch, num_rollouts=1, upto_step=upto_step, map_ctx=ctx, last_step=last_step)
            rep = lambda t: t.repeat(G, *([1] * (t.dim() - 1)))  # noqa: E731  [B, ...] -> [G*B, ...]
            return replace(
                one, num_rollouts=G, agent_static=rep(one.agent_static), agent_type=rep(one.agent_type),
                agent_mask=rep(one.agent_mask), vocab_limit=rep(one.vocab_limit), head_invalid=rep(one.head_invalid),
                t_xn=one.t_xn.repeat(1, G, 1, 1, 1), t_pose=rep(one.t_pose), t_valid=rep(one.t_valid),
                desired_speed=None if one.desired_speed is None else rep(one.desired_speed),
                prev_speed=None if one.prev_speed is None else rep(one.prev_speed),
            )
        S, W, D, L = B, c.temporal_span, c.hidden_dim, c.agent_layers
        rep = lambda t: t  # noqa: E731
        n_slots = W + last_step  # step k writes slot k + W - 1 and attends slots k .. k + W - 1
        dev, dt = ctx.feat.device, ctx.feat.dtype
        agent_type = rep(batch.agent_type.long())
        cache = RolloutCache(
            num_scenes=B, num_rollouts=G, next_step=0, map_ctx=ctx, token_table=self.token_table(),
            agent_static=self._agent_static(agent_type, rep(batch.agent_size.to(dt)), _desired(batch)),
            agent_type=agent_type, agent_mask=rep(batch.agent_mask.bool()),
            vocab_limit=self.type_vocab[agent_type], head_invalid=self.head_invalid[agent_type],
            t_xn=torch.zeros(L, S, A, n_slots, D, dtype=dt, device=dev),
            t_pose=torch.zeros(S, A, n_slots, 4, dtype=dt, device=dev),
            t_valid=torch.zeros(S, A, n_slots, dtype=torch.bool, device=dev),
            desired_speed=rep(_desired(batch)) if c.speed_gap_input else None,
            prev_speed=torch.full((S, A), float("nan"), device=dev) if c.speed_trend_input else None,
        )
        tok = torch.where(batch.agent_token_valid.bool(), batch.agent_token, -1)
        for k in range(upto_step):
            prev = tok[:, :, k - 1] if k > 0 else tok.new_full((B, A), -1)
            self.step(cache, k, rep(prev), rep(batch.pose_xy[:, :, k]), rep(batch.pose_yaw[:, :, k]), rep(batch.pose_valid[:, :, k].bool()))
        return cache

    def step(self, cache: RolloutCache, step_k: int, prev_token: Tensor, pose_xy: Tensor, pose_yaw: Tensor, valid: Tensor,
             before_token: Tensor | None = None) -> Tensor:
        """Process only step ``step_k``: ``prev_token [S, A]`` (token k-1, -1 = none), ``pose_xy [S, A, 2]`` [m],
        ``pose_yaw [S, A]`` [rad], ``valid [S, A]`` -> logits ``[S, A, V_max]`` for token k. Updates the cache.
        ``before_token [S, A]`` (token k-2, -1 = none; models with ``speed_trend_input``): given when the cache did
        not run step k-1 itself (an online decision over remembered features); else the cache's own is used.
        Run it under ``torch.inference_mode()`` (or ``no_grad``) for speed. A step is ~500 small ops: with
        2+ threads on a CPU shared with other processes, set ``OMP_WAIT_POLICY=PASSIVE`` before torch is
        imported (spinning OpenMP workers made steps 10-30x slower in ``benchmarks/bench_policy.py``).
        Small steps (at most ``r1sim_sumo._threads.SMALL_ROWS`` agent rows) run on one CPU thread: their tiny matmuls only lose
        to waking OpenMP workers; the thread count is restored."""
        with few_threads(prev_token.numel(), pose_xy.device):
            return self._step(cache, step_k, prev_token, pose_xy, pose_yaw, valid, before_token)

    def _step(self, cache: RolloutCache, step_k: int, prev_token: Tensor, pose_xy: Tensor, pose_yaw: Tensor, valid: Tensor,
              before_token: Tensor | None = None) -> Tensor:
        if step_k != cache.next_step:
            raise ValueError(f"step: expected step_k={cache.next_step} (steps run in order), got {step_k}")
        W = self.config.temporal_span
        if not 0 <= step_k < min(N_TOK, cache.t_valid.shape[2] - W + 1):
            raise ValueError(f"step: step_k must be in [0, {min(N_TOK, cache.t_valid.shape[2] - W + 1)}) for this cache, got {step_k}")
        slot, lo, hi = step_k + W - 1, step_k, step_k + W
        valid = valid.bool() & cache.agent_mask  # [S, A]
        check_tokens(prev_token, prev_token >= 0, cache.vocab_limit)
        pose = pack_pose(pose_xy, pose_yaw)  # [S, A, 4]
        cache.t_pose[:, :, slot] = pose
        cache.t_valid[:, :, slot] = valid
        tix = self._token_index(prev_token.unsqueeze(-1), cache.agent_type)  # [S, A, 1]
        x = cache.token_table[tix] + cache.agent_static.unsqueeze(2)  # [S, A, 1, D]
        if self.config.speed_gap_input:
            x = x + self._speed_gap(tix, cache.desired_speed.unsqueeze(-1))
        if self.config.speed_trend_input:
            speed = self.token_speed[tix]  # [S, A, 1] mean speed of token k-1 [m/s], NaN for a start token
            if before_token is not None:
                check_tokens(before_token, before_token >= 0, cache.vocab_limit)
                before = self.token_speed[self._token_index(before_token.unsqueeze(-1), cache.agent_type)]
            else:
                before = cache.prev_speed.unsqueeze(-1)
            x = x + self._speed_trend_emb(speed - before)
            cache.prev_speed = speed[..., 0]
        ed = self._edges(
            cache.map_ctx, pose.unsqueeze(2), valid.unsqueeze(2),
            cache.t_pose[:, :, lo:hi].unsqueeze(2), cache.t_valid[:, :, lo:hi].unsqueeze(2), torch.tensor(step_k, device=pose.device),
        )

        def t_source(li: int, xn: Tensor) -> Tensor:
            cache.t_xn[li, :, :, slot] = xn[:, :, 0]
            return cache.t_xn[li, :, :, lo:hi].unsqueeze(2)  # [S, A, 1, W, D]

        x = self._decode(x, ed, t_source)
        cache.next_step = step_k + 1
        # the head's last Linear as a product and an in-place bias add: nn.Linear's addmm first copies the bias into
        # every row of the [S*A, V_max] output (~2 ms of a 700-agent decision on one thread, half of the head's time);
        # the same values (the bias is added to the same products)
        out = self.head[-1]
        logits = torch.matmul(self.head[:-1](x[:, :, 0]), out.weight.t()).add_(out.bias)  # [S, A, V_max]
        if bool((cache.vocab_limit < logits.shape[-1]).any()):  # some agent's type has fewer tokens (else a no-op pass)
            logits.masked_fill_(cache.head_invalid, float("-inf"))
        return logits

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


def token_nll_and_correct(batch, logits: Tensor, future_only: bool = True) -> tuple[float, int, int]:
    """Evaluation sums, no label smoothing: (summed negative log-likelihood [nats], number of top-1 hits, number of
    scored tokens) over valid tokens (``agent_token_valid & agent_mask``); ``future_only`` scores only the future
    tokens (``CURRENT_POSE`` .. 17), as the held-out metrics of pretraining and the model card do."""
    valid = batch.agent_token_valid.bool() & batch.agent_mask.bool().unsqueeze(-1)
    if future_only:
        valid = valid.clone()
        valid[:, :, :CURRENT_POSE] = False
    lg = logits[valid].float()  # [n, V]
    if lg.shape[0] == 0:
        return 0.0, 0, 0
    target = batch.agent_token[valid]  # [n]
    nll = -torch.log_softmax(lg, -1).gather(-1, target.unsqueeze(-1)).squeeze(-1)
    return float(nll.sum()), int((lg.argmax(-1) == target).sum()), int(target.numel())
