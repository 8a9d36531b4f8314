"""SMART-style next-token traffic policy with a per-layer key/value cache for rollouts.

Reads top to bottom: map encoder (once per scene) -> agent embedding (previous motion token + type + size +
speed) -> agent layers (temporal over the agent's own past steps, map-to-agent over the k nearest map tokens,
agent-to-agent over the k nearest agents at the same step) -> token head (one head of width V_max; ids at or
above the agent type's vocabulary size are masked to -inf).

Time: step ``k`` (0..17) sees boundary pose ``k`` and the previous token ``k-1`` (a per-type start embedding
when there is none) and its logits predict token ``k`` (the move from pose k to pose k+1, 0.5 s).
Rollouts stack ``G`` rollouts of ``B`` scenes as ``S = G * B`` sequences, row ``s = g * B + b``.
All neighbourhoods are gathered k-nearest sets (cost O(A * k) per step), relative encodings are computed once
per forward/step and shared by all layers (each layer maps its query into edge-feature space instead of
projecting every edge, see :class:`~r1sim_sumo.model.layers.RelAttentionBlock`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.layers import REL_POSE_DIM, FourierEmbedding, RelAttentionBlock, knn, rel_pose_features

N_TOK = 18  # token steps per window (tokens 0..17)
N_POSE = N_TOK + 1  # boundary poses
CURRENT_POSE = 2  # pose index of "now" (state 10)
FRAMES_PER_TOKEN = 6
TOKEN_DT_S = 0.5  # [s] per token
N_MAP_PTS = 11
TOKEN_FEAT_DIM = 4 * (FRAMES_PER_TOKEN - 1)  # (x/5, y/5, cos yaw, sin yaw) of frames 1..5
POS_SCALE_M = 5.0  # [m]


class MapContext(NamedTuple):
    """Encoded map of B scenes (run once per scene, shared by all rollouts)."""

    feat: Tensor  # [B, M, D] encoded map tokens
    xy: Tensor  # [B, M, 2] segment centres, world frame [m]
    cos: Tensor  # [B, M] cos of the segment yaw
    sin: Tensor  # [B, M]
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
    map_xy: Tensor  # [B, M, 2]
    map_cos: Tensor  # [B, M]
    map_sin: Tensor  # [B, M]
    map_valid: Tensor  # [B, M]
    map_tl: Tensor  # [B*M, N_POSE]
    map_feat: Tensor  # [B*M, D] encoded map tokens
    token_table: Tensor  # [V_total + n_types, D] embedding of every previous-token id
    agent_type: Tensor  # [S, A]
    agent_size: Tensor  # [S, A, 2] length, width [m]
    agent_mask: Tensor  # [S, A]
    t_xn: Tensor  # [L, S, A, span-1+18, D] normalised features of the cached steps per layer
    t_xy: Tensor  # [S, A, span-1+18, 2] poses of the cached steps [m]
    t_cos: Tensor  # [S, A, span-1+18]
    t_sin: Tensor  # [S, A, span-1+18]
    t_valid: Tensor  # [S, A, span-1+18] bool


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
        # map encoder
        self.map_in = nn.Sequential(nn.Linear(2 * N_MAP_PTS + 1, D), nn.LayerNorm(D), nn.ReLU(inplace=True), nn.Linear(D, D))
        self.map_kind = nn.Embedding(c.num_map_kinds, D)
        self.map_edge = FourierEmbedding(REL_POSE_DIM, D, c.fourier_bands)
        self.map_blocks = nn.ModuleList(RelAttentionBlock(D, c.num_heads, 2 * D, c.ffn_mult, c.dropout) for _ in range(c.map_layers))
        self.map_norm = nn.LayerNorm(D)
        self.tl_emb = nn.Embedding(c.num_tl_states, D)
        # agent embedding
        self.token_mlp = nn.Sequential(nn.Linear(TOKEN_FEAT_DIM, D), nn.ReLU(inplace=True), nn.Linear(D, D))
        self.token_emb = nn.Embedding(v_total + nT, D)  # learned part; the last nT rows are start tokens
        self.type_emb = nn.Embedding(nT, D)
        self.agent_feat = FourierEmbedding(4, D, c.fourier_bands)  # length, width, speed, yaw rate
        # relative encodings (computed once per forward/step, shared by all layers)
        self.t_edge = FourierEmbedding(REL_POSE_DIM + 1, D, c.fourier_bands)
        self.m_edge = FourierEmbedding(REL_POSE_DIM, D, c.fourier_bands)
        self.a_edge = FourierEmbedding(REL_POSE_DIM, D, c.fourier_bands)
        # every edge feature = [source content (D), relative encoding (D)]
        self.t_blocks = nn.ModuleList(RelAttentionBlock(D, c.num_heads, 2 * D, c.ffn_mult, c.dropout) for _ in range(L))
        self.m_blocks = nn.ModuleList(RelAttentionBlock(D, c.num_heads, 2 * D, c.ffn_mult, c.dropout) for _ in range(L))
        self.a_blocks = nn.ModuleList(RelAttentionBlock(D, c.num_heads, 2 * D, c.ffn_mult, c.dropout) for _ in range(L))
        self.head = nn.Sequential(nn.LayerNorm(D), nn.Linear(D, D), nn.ReLU(inplace=True), nn.Linear(D, c.vocab_max))

    # ------------------------------------------------------------------ vocabulary buffers

    def _register_vocab(self, token_traj: Sequence[Tensor]) -> None:
        c = self.config
        if len(token_traj) != c.num_agent_types:
            raise ValueError(f"token_traj: expected {c.num_agent_types} per-type tensors, got {len(token_traj)}")
        feats, motion = [], []
        for t, (traj, v) in enumerate(zip(token_traj, c.vocab_sizes)):
            traj = torch.as_tensor(traj, dtype=torch.float32)
            if traj.shape != (v, FRAMES_PER_TOKEN, 3):
                raise ValueError(
                    f"token_traj[{t}]: shape {tuple(traj.shape)} != (vocab_sizes[{t}]={v}, {FRAMES_PER_TOKEN}, 3); "
                    "build the PolicyConfig with vocab_sizes matching the vocabulary"
                )
            f = traj[:, 1:]  # [V, 5, 3]
            feats.append(torch.stack([f[..., 0] / POS_SCALE_M, f[..., 1] / POS_SCALE_M, f[..., 2].cos(), f[..., 2].sin()], -1).flatten(1))
            end = traj[:, -1]  # [V, 3]
            motion.append(torch.stack([end[:, :2].norm(dim=-1) / TOKEN_DT_S / 10.0, end[:, 2] / TOKEN_DT_S], -1))
        motion.append(torch.zeros(c.num_agent_types, 2))  # start tokens: no known motion
        sizes = torch.tensor(c.vocab_sizes)
        self.register_buffer("token_feat", torch.cat(feats), persistent=False)  # [V_total, 20]
        self.register_buffer("token_motion", torch.cat(motion), persistent=False)  # [V_total + nT, 2]
        self.register_buffer("type_offset", torch.cumsum(sizes, 0) - sizes, persistent=False)  # [nT]
        self.register_buffer("type_vocab", sizes, persistent=False)  # [nT]
        self.register_buffer("head_invalid", torch.arange(c.vocab_max)[None] >= sizes[:, None], persistent=False)  # [nT, Vmax]

    def token_table(self) -> Tensor:
        """Embedding of every previous-token id: ``[V_total + n_types, D]`` (type offsets, then start tokens)."""
        shape = self.token_mlp(self.token_feat)  # [V_total, D]
        shape = torch.cat([shape, shape.new_zeros(self.config.num_agent_types, shape.shape[1])])
        return shape + self.token_emb.weight

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
        feat_in = torch.cat([batch.map_pts.flatten(2) / POS_SCALE_M, batch.map_speed.unsqueeze(-1) / 20.0], -1)
        x = self.map_in(feat_in) + self.map_kind(batch.map_kind.clamp(0, c.num_map_kinds - 1))  # [B, M, D]
        valid = batch.map_mask.bool()
        idx, ok = knn(xy, xy, valid, c.map_k, c.map_radius_m)  # [B, M, k]
        ok = ok & valid.unsqueeze(-1)
        flat = idx + (torch.arange(B, device=idx.device) * M).view(B, 1, 1)
        rel = rel_pose_features(xy.reshape(-1, 2)[flat], cos.reshape(-1)[flat], sin.reshape(-1)[flat], xy, cos, sin)
        r = self.map_edge(rel)  # [B, M, k, D]
        for blk in self.map_blocks:
            xn = blk.norm(x)
            x = blk(x, xn, torch.cat([xn.reshape(B * M, D)[flat], r], -1), ok)
        tl = batch.map_tl.long().clamp(0, c.num_tl_states - 1)
        return MapContext(self.map_norm(x), xy, cos, sin, tl, valid)

    # ------------------------------------------------------------------ agent embedding and edges

    def _embed(self, table: Tensor, prev_token: Tensor, agent_type: Tensor, agent_size: Tensor) -> Tensor:
        """``prev_token [S, A, T]`` (-1 = none) -> input features ``[S, A, T, D]``."""
        ty = agent_type.unsqueeze(-1)  # [S, A, 1]
        idx = torch.where(prev_token >= 0, self.type_offset[ty] + prev_token, self.token_feat.shape[0] + ty)
        cont = torch.cat([(agent_size / agent_size.new_tensor([5.0, 2.0])).unsqueeze(2).expand(-1, -1, idx.shape[2], -1), self.token_motion[idx]], -1)
        return table[idx] + self.type_emb(agent_type).unsqueeze(2) + self.agent_feat(cont)

    def _map_edges(self, cache_like, xy: Tensor, cos: Tensor, sin: Tensor, valid: Tensor, steps: Tensor):
        """k nearest map tokens of each agent node ``[S, A, T]`` -> (flat map index, mask, steps of tl)."""
        c = self.config
        S, A, T = valid.shape
        B, M = cache_like.map_valid.shape
        G = S // B
        q = xy.reshape(G, B, A * T, 2).transpose(0, 1).reshape(B, G * A * T, 2)
        idx, ok = knn(q, cache_like.map_xy, cache_like.map_valid, c.map_agent_k, c.map_agent_radius_m)
        k = idx.shape[-1]
        idx = idx + (torch.arange(B, device=idx.device) * M).view(B, 1, 1)
        idx = idx.reshape(B, G, A, T, k).transpose(0, 1).reshape(S, A, T, k)
        ok = ok.reshape(B, G, A, T, k).transpose(0, 1).reshape(S, A, T, k) & valid.unsqueeze(-1)
        rel = rel_pose_features(
            cache_like.map_xy.reshape(-1, 2)[idx], cache_like.map_cos.reshape(-1)[idx], cache_like.map_sin.reshape(-1)[idx], xy, cos, sin
        )
        tl = cache_like.map_tl[idx, steps]  # [S, A, T, k]
        return idx, ok, rel, tl

    def _agent_edges(self, xy: Tensor, cos: Tensor, sin: Tensor, valid: Tensor):
        """k nearest other agents at the same step for nodes ``[S, A, T]`` -> (flat node index, mask, rel)."""
        c = self.config
        S, A, T = valid.shape
        q = xy.transpose(1, 2).reshape(S * T, A, 2)
        idx, ok = knn(q, q, valid.transpose(1, 2).reshape(S * T, A), c.agent_k, c.agent_radius_m, exclude_self=True)
        k = idx.shape[-1]
        base = (torch.arange(S, device=idx.device) * A).view(S, 1, 1, 1)
        t = torch.arange(T, device=idx.device).view(1, T, 1, 1)
        flat = ((base + idx.view(S, T, A, k)) * T + t).transpose(1, 2)  # [S, A, T, k]
        ok = ok.view(S, T, A, k).transpose(1, 2) & valid.unsqueeze(-1)
        fx = xy.reshape(-1, 2)
        rel = rel_pose_features(fx[flat], cos.reshape(-1)[flat], sin.reshape(-1)[flat], xy, cos, sin)
        return flat, ok, rel

    def _temporal_rel(self, wxy: Tensor, wcos: Tensor, wsin: Tensor, xy: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
        """Window poses ``[S, A, T, W, 2]`` relative to the query poses ``[S, A, T, 2]`` + time gap -> ``[.., W, 6]``."""
        W = wxy.shape[-2]
        rel = rel_pose_features(wxy, wcos, wsin, xy, cos, sin)
        gap = torch.arange(W - 1, -1, -1, device=xy.device, dtype=xy.dtype) / W  # oldest .. newest (self = 0)
        return torch.cat([rel, gap.view(W, 1).expand(rel.shape[:-1] + (1,))], -1)

    # ------------------------------------------------------------------ agent layers (shared by forward and step)

    def _decode(self, x, t_rel, t_mask, t_source, m_edge, m_mask, a_idx, a_rel, a_mask) -> Tensor:
        """Run the agent layers on nodes ``x [S, A, T, D]``.

        ``t_source(layer, xn [S, A, T, D]) -> [S, A, T, W, D]`` gives the normalised features of each node's
        temporal window; ``m_edge [S, A, T, k, 2D]`` are the map edge features (content + relative).
        """
        D = self.config.hidden_dim
        rt = self.t_edge(t_rel)  # [S, A, T, W, D]
        ra = self.a_edge(a_rel)  # [S, A, T, k, D]
        for bt, bm, ba in zip(self.t_blocks, self.m_blocks, self.a_blocks):
            xn = bt.norm(x)
            x = bt(x, xn, torch.cat([t_source(xn), rt], -1), t_mask)
            x = bm(x, bm.norm(x), m_edge, m_mask)
            xn = ba.norm(x)
            x = ba(x, xn, torch.cat([xn.reshape(-1, D)[a_idx], ra], -1), a_mask)
        return x

    def _head(self, x: Tensor, agent_type: Tensor) -> Tensor:
        """``x [S, A, T, D]`` -> logits ``[S, A, T, V_max]`` with ids beyond the type's vocabulary at -inf."""
        logits = self.head(x)
        return logits.masked_fill(self.head_invalid[agent_type].unsqueeze(2), float("-inf"))

    def _map_edge_feat(self, map_feat: Tensor, m_idx: Tensor, m_rel: Tensor, m_tl: Tensor) -> Tensor:
        """Map-to-agent edge features ``[S, A, T, k, 2D]``: map token + its traffic-light state, relative pose."""
        return torch.cat([map_feat[m_idx] + self.tl_emb(m_tl), self.m_edge(m_rel)], -1)

    # ------------------------------------------------------------------ teacher-forced forward

    def forward(self, batch, map_ctx: MapContext | None = None) -> Tensor:
        """Teacher-forced logits ``[B, A, 18, V_max]``; step k sees pose k and token k-1, predicts token k."""
        c = self.config
        ctx = self.encode_map(batch) if map_ctx is None else map_ctx
        tok, tok_valid = batch.agent_token, batch.agent_token_valid.bool()
        _check_tokens(tok, tok_valid, batch.agent_type, self.type_vocab)
        B, A, T = tok.shape
        W = c.temporal_span
        prev = torch.where(tok_valid, tok, -1)
        prev = torch.cat([prev.new_full((B, A, 1), -1), prev[:, :, :-1]], 2)  # [B, A, T]
        xy, yaw = batch.pose_xy[:, :, :T], batch.pose_yaw[:, :, :T]  # [B, A, T, 2], [B, A, T]
        cos, sin = yaw.cos(), yaw.sin()
        valid = batch.pose_valid[:, :, :T].bool() & batch.agent_mask.bool().unsqueeze(-1)  # [B, A, T]
        x = self._embed(self.token_table(), prev, batch.agent_type, batch.agent_size)
        # temporal windows (span W, left-padded)
        def win(t: Tensor, fill=0.0) -> Tensor:  # [B, A, T, ...] -> [B, A, T, W, ...]
            p = F.pad(t.movedim(2, -1), (W - 1, 0), value=fill).unfold(-1, W, 1)  # [B, A, ..., T, W]
            return p.movedim(-2, 2).movedim(-1, 3)
        t_rel = self._temporal_rel(win(xy), win(cos), win(sin), xy, cos, sin)
        t_mask = win(valid, False) & valid.unsqueeze(-1)
        steps = torch.arange(T, device=xy.device).view(1, 1, T, 1)
        m_idx, m_mask, m_rel, m_tl = self._map_edges(_MapView.of(ctx), xy, cos, sin, valid, steps)
        m_edge = self._map_edge_feat(ctx.feat.flatten(0, 1), m_idx, m_rel, m_tl)
        a_idx, a_mask, a_rel = self._agent_edges(xy, cos, sin, valid)
        x = self._decode(x, t_rel, t_mask, win, m_edge, m_mask, a_idx, a_rel, a_mask)
        return self._head(x, batch.agent_type)

    def loss(self, batch, logits: Tensor, label_smoothing: float = 0.1, include_history: bool = True) -> tuple[Tensor, Tensor]:
        """Label-smoothed cross-entropy over valid tokens (smoothing spread over the type's own vocabulary).

        :return: (mean loss, top-1 accuracy) over tokens with ``agent_token_valid & agent_mask`` (and, when
            ``include_history`` is False, only future tokens 2..17).
        """
        valid = batch.agent_token_valid.bool() & batch.agent_mask.bool().unsqueeze(-1) & batch.pose_valid[:, :, : logits.shape[2]].bool()
        if not include_history:
            valid = valid.clone()
            valid[:, :, :CURRENT_POSE] = False
        ty = batch.agent_type.unsqueeze(-1).expand_as(valid)[valid]  # [n]
        lg = logits[valid]  # [n, V]
        target = batch.agent_token[valid]  # [n]
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

    def init_rollout(self, batch, num_rollouts: int = 1, upto_step: int = CURRENT_POSE, map_ctx: MapContext | None = None) -> RolloutCache:
        """Encode the map once, run the teacher-forced steps ``0 .. upto_step-1`` for ``G = num_rollouts`` copies
        of every scene, and return the cache; the next call is ``step(cache, upto_step, ...)``."""
        c = self.config
        G = int(num_rollouts)
        ctx = self.encode_map(batch) if map_ctx is None else map_ctx
        B, A = batch.agent_mask.shape
        S, W, D, L = G * B, c.temporal_span, c.hidden_dim, c.agent_layers
        rep = lambda t: t.repeat(G, *([1] * (t.dim() - 1)))  # noqa: E731  [B, ...] -> [G*B, ...]
        f32 = ctx.xy.dtype
        n_slots = W - 1 + N_TOK
        dev = ctx.xy.device
        cache = RolloutCache(
            num_scenes=B, num_rollouts=G, next_step=0,
            map_xy=ctx.xy, map_cos=ctx.cos, map_sin=ctx.sin, map_valid=ctx.valid, map_tl=ctx.tl.flatten(0, 1),
            map_feat=ctx.feat.flatten(0, 1), token_table=self.token_table(),
            agent_type=rep(batch.agent_type.long()), agent_size=rep(batch.agent_size.to(f32)), agent_mask=rep(batch.agent_mask.bool()),
            t_xn=torch.zeros(L, S, A, n_slots, D, dtype=ctx.feat.dtype, device=dev),
            t_xy=torch.zeros(S, A, n_slots, 2, dtype=f32, device=dev),
            t_cos=torch.zeros(S, A, n_slots, dtype=f32, device=dev), t_sin=torch.zeros(S, A, n_slots, dtype=f32, device=dev),
            t_valid=torch.zeros(S, A, n_slots, dtype=torch.bool, device=dev),
        )
        tok = torch.where(batch.agent_token_valid.bool(), batch.agent_token, -1)
        for k in range(upto_step):
            prev = tok[:, :, k - 1] if k > 0 else tok.new_full((B, A), -1)
            self.step(cache, k, rep(prev), rep(batch.pose_xy[:, :, k]), rep(batch.pose_yaw[:, :, k]), rep(batch.pose_valid[:, :, k].bool()))
        return cache

    def step(self, cache: RolloutCache, step_k: int, prev_token: Tensor, pose_xy: Tensor, pose_yaw: Tensor, valid: Tensor) -> Tensor:
        """Process only step ``step_k``: ``prev_token [S, A]`` (token k-1, -1 = none), ``pose_xy [S, A, 2]`` [m],
        ``pose_yaw [S, A]`` [rad], ``valid [S, A]`` -> logits ``[S, A, V_max]`` for token k. Updates the cache."""
        c = self.config
        if step_k != cache.next_step:
            raise ValueError(f"step: expected step_k={cache.next_step} (steps run in order), got {step_k}")
        if not 0 <= step_k < N_TOK:
            raise ValueError(f"step: step_k must be in [0, {N_TOK}), got {step_k}")
        W = c.temporal_span
        slot = step_k + W - 1
        valid = valid.bool() & cache.agent_mask  # [S, A]
        _check_tokens(prev_token.unsqueeze(-1), prev_token.unsqueeze(-1) >= 0, cache.agent_type, self.type_vocab)
        cos, sin = pose_yaw.cos(), pose_yaw.sin()
        cache.t_xy[:, :, slot] = pose_xy
        cache.t_cos[:, :, slot] = cos
        cache.t_sin[:, :, slot] = sin
        cache.t_valid[:, :, slot] = valid
        xy, cos, sin, valid = pose_xy.unsqueeze(2), cos.unsqueeze(2), sin.unsqueeze(2), valid.unsqueeze(2)  # T = 1
        x = self._embed(cache.token_table, prev_token.unsqueeze(-1), cache.agent_type, cache.agent_size)  # [S, A, 1, D]
        lo, hi = step_k, step_k + W
        t_rel = self._temporal_rel(
            cache.t_xy[:, :, lo:hi].unsqueeze(2), cache.t_cos[:, :, lo:hi].unsqueeze(2), cache.t_sin[:, :, lo:hi].unsqueeze(2), xy, cos, sin
        )
        t_mask = cache.t_valid[:, :, lo:hi].unsqueeze(2) & valid.unsqueeze(-1)  # [S, A, 1, W]

        layer = iter(range(c.agent_layers))

        def t_source(xn: Tensor) -> Tensor:  # called once per layer, in order
            li = next(layer)
            cache.t_xn[li, :, :, slot] = xn[:, :, 0]
            return cache.t_xn[li, :, :, lo:hi].unsqueeze(2)  # [S, A, 1, W, D]

        m_idx, m_mask, m_rel, m_tl = self._map_edges(cache, xy, cos, sin, valid, torch.full((), step_k, device=xy.device))
        m_edge = self._map_edge_feat(cache.map_feat, m_idx, m_rel, m_tl)
        a_idx, a_mask, a_rel = self._agent_edges(xy, cos, sin, valid)
        x = self._decode(x, t_rel, t_mask, t_source, m_edge, m_mask, a_idx, a_rel, a_mask)
        cache.next_step = step_k + 1
        return self._head(x, cache.agent_type)[:, :, 0]

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


class _MapView(NamedTuple):
    """The map fields ``_map_edges`` reads, under the names the rollout cache uses."""

    map_xy: Tensor
    map_cos: Tensor
    map_sin: Tensor
    map_valid: Tensor
    map_tl: Tensor

    @classmethod
    def of(cls, ctx: MapContext) -> _MapView:
        return cls(ctx.xy, ctx.cos, ctx.sin, ctx.valid, ctx.tl.flatten(0, 1))


def _check_tokens(tok: Tensor, tok_valid: Tensor, agent_type: Tensor, type_vocab: Tensor) -> None:
    """Valid token ids must lie in ``[0, vocab size of the agent's type)``."""
    limit = type_vocab[agent_type].unsqueeze(-1)  # [S, A, 1]
    bad = tok_valid & ((tok < 0) | (tok >= limit))
    if bool(bad.any()):
        s, a, k = (int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"agent_token[{s}, {a}, {k}] = {int(tok[s, a, k])} is outside the vocabulary of agent type "
            f"{int(agent_type[s, a])} (size {int(limit[s, a, 0])}); tokenize with the checkpoint's vocabulary"
        )
