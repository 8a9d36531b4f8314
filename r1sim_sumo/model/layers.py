"""Building blocks of the policy: Fourier embeddings, relative pose features, k-nearest neighbours, and a
pre-norm attention block whose keys/values carry relative positional encodings (as in SMART).

Shapes use ``S`` for sequences of scenes (scenes x rollouts), ``A`` agents, ``T`` token steps, ``E`` edges
(neighbours) per query, ``D`` hidden width, ``H`` heads. Positions are metres in the world frame, yaw is
radians counter-clockwise from +x; relative features are expressed in the query's (destination's) frame.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

# Scales that bring continuous inputs to O(1) before the Fourier features.
DIST_SCALE_M = 10.0  # [m]

REL_POSE_DIM = 5  # distance, cos/sin bearing, cos/sin relative heading


class FourierEmbedding(nn.Module):
    """Continuous features ``[..., F]`` -> ``[..., D]``.

    Each input x_f gives ``cos(2 pi w x_f), sin(2 pi w x_f)`` for ``bands`` learned frequencies w plus x_f
    itself; the concatenation goes through Linear -> LayerNorm -> ReLU -> Linear.
    """

    def __init__(self, in_dim: int, hidden_dim: int, bands: int) -> None:
        super().__init__()
        self.freqs = nn.Parameter(torch.randn(in_dim, bands))  # [F, K]
        self.mlp = nn.Sequential(
            nn.Linear(in_dim * (2 * bands + 1), hidden_dim),
            nn.LayerNorm(hidden_dim),
            nn.ReLU(inplace=True),
            nn.Linear(hidden_dim, hidden_dim),
        )

    def forward(self, x: Tensor) -> Tensor:
        ang = x.unsqueeze(-1) * (2 * math.pi) * self.freqs  # [..., F, K]
        feats = torch.cat([ang.cos(), ang.sin(), x.unsqueeze(-1)], dim=-1)  # [..., F, 2K+1]
        return self.mlp(feats.flatten(-2))


def rel_pose_features(
    src_xy: Tensor, src_cos: Tensor, src_sin: Tensor, dst_xy: Tensor, dst_cos: Tensor, dst_sin: Tensor
) -> Tensor:
    """Pose of each source relative to its destination, in the destination's frame.

    :param src_xy: ``[..., E, 2]`` source positions [m]; ``src_cos/src_sin`` ``[..., E]`` of the source yaw.
    :param dst_xy: ``[..., 2]`` destination positions [m]; ``dst_cos/dst_sin`` ``[...]`` of its yaw.
    :return: ``[..., E, 5]`` = (distance / 10 m, cos and sin of the bearing of the source seen from the
        destination heading, cos and sin of the source yaw minus the destination yaw).
    """
    d = src_xy - dst_xy.unsqueeze(-2)  # [..., E, 2]
    c, s = dst_cos.unsqueeze(-1), dst_sin.unsqueeze(-1)  # [..., 1]
    dx, dy = d[..., 0], d[..., 1]
    lx = dx * c + dy * s  # [..., E] along the destination heading
    ly = dy * c - dx * s  # [..., E] to its left
    dist = torch.sqrt(lx * lx + ly * ly)
    inv = 1.0 / dist.clamp_min(1e-6)
    rel_c = src_cos * c + src_sin * s
    rel_s = src_sin * c - src_cos * s
    return torch.stack([dist * (1.0 / DIST_SCALE_M), lx * inv, ly * inv, rel_c, rel_s], dim=-1)


def knn(
    query_xy: Tensor,
    key_xy: Tensor,
    key_valid: Tensor,
    k: int,
    radius_m: float,
    exclude_self: bool = False,
    chunk_elems: int = 1 << 22,
) -> tuple[Tensor, Tensor]:
    """The ``k`` nearest valid keys within ``radius_m`` of each query, per scene.

    :param query_xy: ``[S, Q, 2]`` [m]; ``key_xy`` ``[S, K, 2]`` [m]; ``key_valid`` ``[S, K]`` bool.
    :param exclude_self: queries and keys are the same set (Q == K) and a node is not its own neighbour.
    :return: ``idx`` ``[S, Q, min(k, K)]`` key indices, ``valid`` the same shape (False where no key within
        the radius). Squared distances are computed elementwise (no matmul trick), so the same inputs select
        the same neighbours whatever the batch shape. Queries are processed in chunks of about
        ``chunk_elems`` distances to bound memory.
    """
    S, Q, _ = query_xy.shape
    K = key_xy.shape[1]
    kk = min(k, K)
    if kk == 0 or Q == 0:
        empty = query_xy.new_zeros((S, Q, kk))
        return empty.long(), empty.bool()
    rows = max(1, chunk_elems // max(1, S * K))
    idx_out, d_out = [], []
    key_bad = ~key_valid.unsqueeze(1)  # [S, 1, K]
    for q0 in range(0, Q, rows):
        q = query_xy[:, q0 : q0 + rows]  # [S, q, 2]
        dx = q[..., 0:1] - key_xy[..., 0].unsqueeze(1)  # [S, q, K]
        dy = q[..., 1:2] - key_xy[..., 1].unsqueeze(1)
        d2 = torch.addcmul(dx * dx, dy, dy).masked_fill_(key_bad, float("inf"))  # [S, q, K] squared [m^2]
        if exclude_self:
            ar = torch.arange(q0, q0 + q.shape[1], device=q.device)
            d2[:, torch.arange(q.shape[1], device=q.device), ar] = float("inf")
        d, i = torch.topk(d2, kk, dim=-1, largest=False, sorted=False)  # [S, q, kk]
        idx_out.append(i)
        d_out.append(d)
    idx = idx_out[0] if len(idx_out) == 1 else torch.cat(idx_out, 1)
    dist2 = d_out[0] if len(d_out) == 1 else torch.cat(d_out, 1)
    return idx, dist2 <= radius_m * radius_m


class FeedForward(nn.Module):
    """Pre-norm feed-forward residual branch: ``x + Dropout(W2 ReLU(W1 LN(x)))``."""

    def __init__(self, dim: int, mult: int, dropout: float) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.LayerNorm(dim), nn.Linear(dim, mult * dim), nn.ReLU(inplace=True), nn.Linear(mult * dim, dim), nn.Dropout(dropout)
        )

    def forward(self, x: Tensor) -> Tensor:
        return x + self.net(x)


class RelAttentionBlock(nn.Module):
    """Pre-norm attention of each query over its gathered neighbours, then a feed-forward branch.

    Every edge carries one feature vector ``e_ij [De]`` (the neighbour's content features concatenated with
    the relative positional encoding of the pair). Keys and values are linear in it, ``k_ij = W_k e_ij`` and
    ``v_ij = W_v e_ij`` (SMART's ``k = W x_j + W_r r_ij``), but they are never materialised per edge:
    the query is mapped into edge space per head (``W_k^T q``) and the attention-weighted *edge features*
    are mapped back (``W_v sum_j w_ij e_ij``). Per edge this costs ``O(H * De)`` instead of ``O(D * De)``.
    Key biases would cancel in the softmax and value biases are absorbed by ``out``, so none are used.
    """

    def __init__(self, dim: int, heads: int, edge_dim: int, ffn_mult: int, dropout: float) -> None:
        super().__init__()
        self.heads, self.edge_dim = heads, edge_dim
        dh = dim // heads
        self.norm = nn.LayerNorm(dim)
        self.q = nn.Linear(dim, dim)
        bound = edge_dim**-0.5
        self.w_k = nn.Parameter(torch.empty(heads, dh, edge_dim).uniform_(-bound, bound))  # [H, dh, De]
        self.w_v = nn.Parameter(torch.empty(heads, dh, edge_dim).uniform_(-bound, bound))  # [H, dh, De]
        self.out = nn.Linear(dim, dim)
        self.drop = nn.Dropout(dropout)
        self.ffn = FeedForward(dim, ffn_mult, dropout)
        self.scale = dh**-0.5

    def forward(self, x: Tensor, xn: Tensor, e: Tensor, mask: Tensor) -> Tensor:
        """:param x: ``[..., D]`` queries (residual stream); ``xn`` = ``self.norm(x)``.
        :param e: ``[..., E, De]`` edge features of each query's neighbours.
        :param mask: ``[..., E]`` bool, True = real neighbour. A query with no neighbour gets a zero update.
        :return: ``[..., D]`` updated residual stream.
        """
        lead, D = x.shape[:-1], x.shape[-1]
        E, De, H = e.shape[-2], self.edge_dim, self.heads
        N = xn.numel() // D
        q = (self.q(xn) * self.scale).reshape(N, H, D // H)
        qe = torch.einsum("nhd,hde->nhe", q, self.w_k)  # [N, H, De]
        e2 = e.reshape(N, E, De)
        logits = torch.bmm(qe, e2.transpose(1, 2))  # [N, H, E]
        m = mask.reshape(N, 1, E)
        logits = logits.masked_fill(~m, torch.finfo(logits.dtype).min)
        w = torch.softmax(logits, dim=-1) * m  # zero for a query without neighbours
        agg = torch.einsum("nhe,hde->nhd", torch.bmm(w, e2), self.w_v)  # [N, H, dh]
        return self.ffn(x + self.drop(self.out(agg.reshape(lead + (D,)))))
