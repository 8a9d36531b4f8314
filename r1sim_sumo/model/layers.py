"""Building blocks of the policy: Fourier embeddings, relative pose features, k-nearest neighbours, and a
pre-norm attention block whose keys/values carry relative positional encodings (as in SMART).

Shapes use ``S`` for sequences of scenes (scenes x rollouts), ``A`` agents, ``T`` token steps, ``E`` edges
(neighbours) per query, ``D`` hidden width, ``H`` heads. Positions are metres in the world frame, yaw is
radians counter-clockwise from +x; relative features are expressed in the query's (destination's) frame.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from r1sim_sumo.model import gathered_attention
from r1sim_sumo.model.residual_dropout import residual_dropout

# Scales that bring continuous inputs to O(1) before the Fourier features.
DIST_SCALE_M = 10.0  # [m]
POS_SCALE_M = 5.0  # [m] token-trajectory and map-token points are divided by this
MAP_SPEED_SCALE_MPS = 20.0  # [m/s] map-token speed limits are divided by this

REL_POSE_DIM = 5  # distance, cos/sin bearing, cos/sin relative heading
EINSUM_MIN_ROWS = 2048  # attention over more queries than this uses einsum (faster at training sizes); fewer: bmm


class FourierEmbedding(nn.Module):
    """Continuous features ``[..., F]`` -> ``[..., D]``.

    Each input x_f gives ``cos(w x_f), sin(w x_f)`` for ``bands`` learned angular frequencies w plus x_f
    itself; the concatenation goes through Linear (+ an optional additive ``bias [..., D]``, e.g. an edge-type
    embedding) -> LayerNorm -> ReLU [-> Linear]. ``out_linear=False`` drops the last Linear, for features that
    only feed linear maps (edge features of :class:`RelAttentionBlock`, where it would be redundant).
    """

    def __init__(self, in_dim: int, hidden_dim: int, bands: int, out_linear: bool = True) -> None:
        super().__init__()
        self.freqs = nn.Parameter(torch.randn(in_dim, bands) * 2 * math.pi)  # [F, K] angular frequencies
        self.lin1 = nn.Linear(in_dim * (2 * bands + 1), hidden_dim)
        self.norm = nn.LayerNorm(hidden_dim)
        self.lin2 = nn.Linear(hidden_dim, hidden_dim) if out_linear else None

    def forward(self, x: Tensor, bias: Tensor | None = None) -> Tensor:
        ang = x.unsqueeze(-1) * self.freqs  # [..., F, K]
        feats = torch.cat([ang.cos(), ang.sin(), x.unsqueeze(-1)], dim=-1).flatten(-2)  # [..., F*(2K+1)]
        h = self.lin1(feats)
        if bias is not None:
            h = h + bias
        h = torch.relu(F.layer_norm(h, self.norm.normalized_shape, self.norm.weight, self.norm.bias))
        return h if self.lin2 is None else self.lin2(h)


def pack_pose(xy: Tensor, yaw: Tensor) -> Tensor:
    """``xy [..., 2]`` [m], ``yaw [...]`` [rad] -> packed pose ``[..., 4]`` = (x, y, cos yaw, sin yaw)."""
    return torch.cat([xy, yaw.cos().unsqueeze(-1), yaw.sin().unsqueeze(-1)], -1)


def rel_pose_features(src: Tensor, dst: Tensor) -> Tensor:
    """Pose of each source relative to its destination, in the destination's frame.

    :param src: ``[..., E, 4]`` packed source poses (x [m], y [m], cos yaw, sin yaw).
    :param dst: ``[..., 4]`` packed destination poses.
    :return: ``[..., E, 5]`` = (distance / 10 m, cos and sin of the bearing of the source seen from the
        destination heading, cos and sin of the source yaw minus the destination yaw).
    """
    d = src - dst.unsqueeze(-2)  # [..., E, 4]; only the xy part of d is used
    c, s = dst[..., 2:3], dst[..., 3:4]  # [..., 1]
    dx, dy = d[..., 0], d[..., 1]
    lx = dx * c + dy * s  # [..., E] along the destination heading
    ly = dy * c - dx * s  # [..., E] to its left
    dist = torch.sqrt(lx * lx + ly * ly)
    inv = 1.0 / dist.clamp_min(1e-6)
    sc, ss = src[..., 2], src[..., 3]
    return torch.stack([dist * (1.0 / DIST_SCALE_M), lx * inv, ly * inv, sc * c + ss * s, ss * c - sc * s], dim=-1)


KD_MIN_PAIRS = 1 << 21  # query-key pairs from which knn searches with a k-d tree on the CPU
KD_MIN_KEYS = 256  # ... and keys per scene


def kdtree_neighbours(query: np.ndarray, keys, k: int, radius_m: float) -> np.ndarray:
    """``[Q, min(k, K)]`` int64 indices into ``keys [K, 2]`` of each query's (``query [Q, 2]``, float64 [m]) nearest keys
    within a hair beyond ``radius_m``, nearest first, ``-1`` where fewer were found: a ``scipy.spatial.cKDTree``, O(Q
    log K). ``keys`` may also be a ``cKDTree`` built over them (reused across calls). The callers redo the radius test
    in float32 as :func:`knn` does it, so the hair decides nothing."""
    from scipy.spatial import cKDTree

    tree = keys if isinstance(keys, cKDTree) else cKDTree(keys)
    n = min(k, tree.n)
    _, i = tree.query(query, k=n, distance_upper_bound=radius_m * (1.0 + 1e-5) + 1e-6)
    i = np.asarray(i, dtype=np.int64).reshape(len(query), n)
    return np.where(i < tree.n, i, -1)  # cKDTree marks a missing neighbour with index K


_TREES: list[tuple[tuple, Tensor, Tensor, list]] = []  # recent (fingerprint, key_xy, key_valid, per-scene trees)
_TREES_KEPT = 4


def _fingerprint(t: Tensor) -> tuple:
    """Identifies a CPU tensor's current contents while a reference to it is held: its memory, layout and version
    counter (bumped by every in-place write, shared by a view and its base)."""
    return (t.data_ptr(), tuple(t.shape), t.stride(), t.dtype, t._version)


def _scene_trees(key_xy: Tensor, key_valid: Tensor) -> list:
    """Per scene: (the indices of its valid, finite keys, a ``cKDTree`` over them) or ``None`` when it has none. The
    trees of the last few key sets are kept: a drop-in decision searches the same encoded map tokens every 0.5 s, and
    building a tree over 22,876 of them took ~3.5-7 ms against 0.6 ms for the 700 queries (session 26). A cached
    entry holds references to its tensors, so their memory cannot be reused by other contents with the same
    fingerprint."""
    from scipy.spatial import cKDTree

    fp = (_fingerprint(key_xy), _fingerprint(key_valid))
    for i, (f, _kx, _kv, trees) in enumerate(_TREES):
        if f == fp:  # the memory address is part of it; the held reference keeps it from being reused
            _TREES.insert(0, _TREES.pop(i))
            return trees
    kn = key_xy.detach().double().numpy()
    kv = key_valid.numpy() & np.isfinite(kn).all(-1)
    trees = []
    for b in range(key_xy.shape[0]):
        keys = np.flatnonzero(kv[b])
        trees.append((keys, cKDTree(kn[b, keys])) if len(keys) else None)
    _TREES.insert(0, (fp, key_xy, key_valid, trees))
    del _TREES[_TREES_KEPT:]
    return trees


def knn_kdtree(query_xy: Tensor, key_xy: Tensor, key_valid: Tensor, kk: int, radius_m: float,
               exclude_self: bool = False) -> tuple[Tensor, Tensor]:
    """:func:`knn` with a k-d tree over each scene's valid keys (:func:`kdtree_neighbours`, CPU): O(Q log K) instead of
    the O(Q K) distance matrix; the radius test is redone in float32 exactly as :func:`knn` does it. Missing neighbours
    point at key 0 and are invalid."""
    S, Q, _ = query_xy.shape
    idx = torch.zeros(S, Q, kk, dtype=torch.long)
    found = torch.zeros(S, Q, kk, dtype=torch.bool)
    qn = query_xy.detach().double().numpy()
    qn = np.where(np.isfinite(qn), qn, 1e12)  # a query without a position has no neighbour
    extra = 1 if exclude_self else 0
    for b, scene in enumerate(_scene_trees(key_xy, key_valid)):
        if scene is None:
            continue
        keys, tree = scene
        i = kdtree_neighbours(qn[b], tree, kk + extra, radius_m)
        g = np.where(i >= 0, keys[np.maximum(i, 0)], -1)  # scene key index, -1 missing
        if exclude_self:  # drop each query's own key, keep the kk nearest others
            own = g == np.arange(Q)[:, None]
            order = np.argsort(own | (g < 0), axis=1, kind="stable")[:, :kk]  # real non-self first, nearest first
            g = np.take_along_axis(np.where(own, -1, g), order, 1)
        g = g[:, :kk]
        m = g.shape[1]
        idx[b, :, :m] = torch.from_numpy(np.maximum(g, 0))
        found[b, :, :m] = torch.from_numpy(g >= 0)
    d = query_xy.unsqueeze(2) - torch.gather(key_xy, 1, idx.reshape(S, Q * kk, 1).expand(S, Q * kk, 2)).reshape(S, Q, kk, 2)
    d2 = torch.addcmul(d[..., 0] * d[..., 0], d[..., 1], d[..., 1])
    return idx, found & (d2 <= radius_m * radius_m)


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

    Large searches on the CPU (at least :data:`KD_MIN_PAIRS` query-key pairs and :data:`KD_MIN_KEYS` keys per scene,
    e.g. 700 vehicles of a city network against its map tokens) use a k-d tree per scene instead of the distance
    matrix (:func:`knn_kdtree`): the same neighbours within the radius up to exact distance ties at the k-th place
    (attention is order-invariant over map and agent slots); the columns past the last neighbour within the radius
    are invalid either way.
    """
    S, Q, _ = query_xy.shape
    K = key_xy.shape[1]
    kk = min(k, K)
    if kk == 0 or Q == 0:
        empty = query_xy.new_zeros((S, Q, kk))
        return empty.long(), empty.bool()
    if not query_xy.is_cuda and K >= KD_MIN_KEYS and S * Q * K >= KD_MIN_PAIRS:
        return knn_kdtree(query_xy, key_xy, key_valid, kk, radius_m, exclude_self)
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
    """Pre-norm feed-forward residual branch: ``x + Dropout(W2 ReLU(W1 LN(x)))`` (the dropout and the add in one
    pass: :func:`~r1sim_sumo.model.residual_dropout.residual_dropout`)."""

    def __init__(self, dim: int, mult: int, dropout: float) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.lin1 = nn.Linear(dim, mult * dim)
        self.lin2 = nn.Linear(mult * dim, dim)
        self.p = dropout

    def forward(self, x: Tensor) -> Tensor:
        h = F.layer_norm(x, self.norm.normalized_shape, self.norm.weight, self.norm.bias)
        h = F.linear(torch.relu(F.linear(h, self.lin1.weight, self.lin1.bias)), self.lin2.weight, self.lin2.bias)
        return residual_dropout(x, h, self.p, self.training)


def edge_attention(qe: Tensor, e: Tensor, mask: Tensor, big: bool = False) -> Tensor:
    """Attention of each query over its own edges, in edge-feature space.

    :param qe: ``[N, H, De]`` queries mapped into edge space per head (``W_k^T q``, scale included).
    :param e: ``[N, E, De]`` edge features of each query's neighbours.
    :param mask: ``[N, 1, E]`` bool, True = real neighbour.
    :param big: use ``einsum`` (faster on CPU for thousands of queries) instead of ``bmm``; same result.
    :return: ``[N, H, De]`` attention-weighted edge features (zero for a query without neighbours).
    """
    logits = torch.einsum("nhd,ned->nhe", qe, e) if big else torch.bmm(qe, e.transpose(1, 2))  # [N, H, E]
    logits = logits.masked_fill_(~mask, torch.finfo(logits.dtype).min)  # the logits' dtype: bf16 under autocast
    w = torch.softmax(logits, dim=-1) * mask  # zero for a query without neighbours
    return torch.einsum("nhe,ned->nhd", w, e) if big else torch.bmm(w, e)


class EdgeAttention(torch.autograd.Function):
    """:func:`edge_attention` with a hand-written backward, for training.

    Autograd's backward of the plain version runs four batched products, two of them with an inner size of
    only ``H`` (the gradients of the edge features through the logits and through the weighted sum), and then
    adds the two ``[N, E, De]`` gradients. Here those two are one product with inner size ``2H``
    (``[g_logits, w]^T [qe, g_agg]``) and the softmax backward is done in place on the saved weights: on the
    real pretraining batches the attention core's forward + backward took about 1.5x less time
    (``benchmarks/bench_training.py``). Same values as autograd up to float rounding
    (``tests/test_fast_training.py``)."""

    @staticmethod
    def forward(ctx, qe: Tensor, e: Tensor, mask: Tensor) -> Tensor:
        dev = qe.device.type
        dtype = torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev) else torch.promote_types(qe.dtype, e.dtype)
        with torch.autocast(dev, enabled=False):  # the products in autocast's dtype, as the plain version gets them
            qe, e = qe.to(dtype), e.to(dtype)
            logits = torch.einsum("nhd,ned->nhe", qe, e).masked_fill_(~mask, torch.finfo(dtype).min)
            w = torch.softmax(logits, dim=-1).mul_(mask)
            ctx.save_for_backward(qe, e, w)
            return torch.einsum("nhe,ned->nhd", w, e)

    @staticmethod
    def backward(ctx, g_agg: Tensor):
        qe, e, w = ctx.saved_tensors
        g_agg = g_agg.to(e.dtype)
        g_w = torch.einsum("nhd,ned->nhe", g_agg, e)  # [N, H, E]
        # softmax backward: w (g_w - sum(w g_w)); masked edges have w = 0 and get no gradient
        g_logits = g_w.sub_((w * g_w).sum(-1, keepdim=True)).mul_(w)
        g_qe = torch.einsum("nhe,ned->nhd", g_logits, e) if ctx.needs_input_grad[0] else None
        g_e = None
        if ctx.needs_input_grad[1]:
            g_e = torch.einsum("nke,nkd->ned", torch.cat([g_logits, w], 1), torch.cat([qe, g_agg], 1))
        return g_qe, g_e, None


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
        bound = edge_dim**-0.5 * dh**-0.5  # includes the 1/sqrt(dh) attention scale
        self.w_k = nn.Parameter(torch.empty(heads, dh, edge_dim).uniform_(-bound, bound))  # [H, dh, De]
        bound = edge_dim**-0.5
        self.w_v = nn.Parameter(torch.empty(heads, edge_dim, dh).uniform_(-bound, bound))  # [H, De, dh]
        self.out = nn.Linear(dim, dim)
        self.p = dropout
        self.ffn = FeedForward(dim, ffn_mult, dropout)

    def normed(self, x: Tensor) -> Tensor:
        return F.layer_norm(x, self.norm.normalized_shape, self.norm.weight, self.norm.bias)

    def forward(self, x: Tensor, xn: Tensor, e: Tensor, mask: Tensor) -> Tensor:
        """:param x: ``[..., D]`` queries (residual stream); ``xn`` = ``self.normed(x)``.
        :param e: ``[..., E, De]`` edge features of each query's neighbours.
        :param mask: ``[..., E]`` bool, True = real neighbour. A query with no neighbour gets a zero update.
        :return: ``[..., D]`` updated residual stream.
        """
        E, De = e.shape[-2], self.edge_dim
        N = xn.numel() // x.shape[-1]
        e2, m = e.reshape(N, E, De), mask.reshape(N, 1, E)

        def attend(qe: Tensor) -> Tensor:
            if torch.is_grad_enabled() and (qe.requires_grad or e2.requires_grad):
                return EdgeAttention.apply(qe, e2, m)  # training: one hand-written backward  [N, H, De]
            return edge_attention(qe, e2, m, big=N > EINSUM_MIN_ROWS)

        return self._update(x, xn, attend)

    def forward_gathered(self, x: Tensor, xn: Tensor, src: Tensor, idx: Tensor | None, rel: Tensor,
                         mask: Tensor) -> Tensor:
        """:meth:`forward` with the edge features ``e = cat([src[idx], rel], -1)`` given by parts (packed nodes).

        :param x: ``[N, D]`` queries; ``xn`` = ``self.normed(x)``.
        :param src: ``[Ns, Dc]`` source rows; ``idx`` ``[N, E]`` int64 rows of it (``None``: ``src`` is ``[N * E,
            Dc]``, one row per edge); ``rel`` ``[N, E, Dr]``.
        :param mask: ``[N, E]`` bool. Where the C kernel applies (CPU, fp32 or bf16 autocast,
            :mod:`r1sim_sumo.model.gathered_attention`) ``e`` is never materialised and the queries stay head-major
            (no transposes); otherwise ``e`` is built and :meth:`forward` runs. Same values up to float rounding."""
        if not gathered_attention.usable(x, src, rel):
            content = src.view(*mask.shape, -1) if idx is None else src[idx]
            return self.forward(x, xn, torch.cat([content, rel], -1), mask)
        N, D = x.shape
        H = self.heads
        q = F.linear(xn, self.q.weight, self.q.bias).view(N, H, D // H).transpose(0, 1)  # [H, N, dh]
        # under bf16 autocast qe and agg are bf16 (half the memory traffic); the kernel computes in fp32
        agg = gathered_attention.gathered_edge_attention(torch.bmm(q, self.w_k), src, idx, rel, mask)  # [H, N, De]
        o = torch.bmm(agg, self.w_v).transpose(0, 1).reshape(N, D)
        return self._residual(x, o)

    def _update(self, x: Tensor, xn: Tensor, attend) -> Tensor:
        """Residual update of ``x`` with ``attend(qe [N, H, De]) -> [N, H, De]`` (attention-weighted edge features)."""
        D = x.shape[-1]
        H = self.heads
        N = xn.numel() // D
        q = F.linear(xn.reshape(N, D), self.q.weight, self.q.bias).view(N, H, D // H)
        qe = torch.bmm(q.transpose(0, 1), self.w_k).transpose(0, 1)  # [N, H, De] query in edge space
        agg = attend(qe)
        o = torch.bmm(agg.transpose(0, 1), self.w_v).transpose(0, 1).reshape(N, D)  # [N, D]
        return self._residual(x, o)

    def _residual(self, x: Tensor, o: Tensor) -> Tensor:
        """``x + Dropout(out(o))`` then the feed-forward branch; ``o`` ``[N, D]`` the heads' values, ``x [..., D]``."""
        upd = F.linear(o, self.out.weight, self.out.bias)
        return self.ffn(residual_dropout(x, upd.view(x.shape), self.p, self.training))


def check_tokens(tok: Tensor, tok_valid: Tensor, limit: Tensor) -> None:
    """Valid token ids must lie in ``[0, limit)``; ``limit [S, A]`` = vocabulary size of each agent's type."""
    if tok.dim() == limit.dim() + 1:
        limit = limit.unsqueeze(-1)
    bad = tok_valid & ((tok < 0) | (tok >= limit))
    if bool(bad.any()):
        where = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"agent_token{list(where)} = {int(tok[where])} is outside the vocabulary of the agent's type "
            f"(size {int(limit.expand_as(tok)[where])}); tokenize with the checkpoint's vocabulary"
        )


def map_kind_index(kind: torch.Tensor, num_map_kinds: int) -> torch.Tensor:
    """Row of the map-kind embedding for map token kinds ``kind`` (0 lane centre, 1 road edge, 2 ending lane: see
    :mod:`r1sim_sumo.tokens.map_tokens`). A model with fewer kinds reads a kind it does not know as a lane centre
    (the ending lane is one), so checkpoints trained before kind 2 existed give the same logits as before."""
    return torch.where((kind >= num_map_kinds) | (kind < 0), torch.zeros_like(kind), kind)
