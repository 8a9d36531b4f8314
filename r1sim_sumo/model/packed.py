"""The training forward pass over *packed* nodes: only real map tokens and valid agent nodes, no padding.

:meth:`TrafficPolicy.forward` runs every padded ``(scene, agent, step)`` node and every padded map token of a
:class:`~r1sim_sumo.tokens.batch.SceneBatch`; on real batches of the default recipe a third of the agent nodes
and almost half of the map tokens are padding, and the map-to-map neighbour search is quadratic in the padded
map size. :func:`packed_logits` computes the same logits for the valid nodes only:

* map tokens: the real tokens of every scene, concatenated (``[M_tot, ...]``); neighbour search per scene;
* agent nodes: the valid ``(scene, agent, step)`` nodes (``pose_valid & agent_mask``, steps 0..17) in
  ``(scene, agent, step)`` order (``[N, ...]``); temporal windows, map and agent neighbours are index lists
  into these packed arrays;
* the head runs only on the requested output rows (the loss's valid tokens), and the per-type vocabulary mask
  is applied only when a row's type has a smaller vocabulary than the head (no in-place fill on a view).

It uses the model's own modules (:meth:`TrafficPolicy._decode`, the same blocks and embeddings), so the
logits equal the padded forward's at the same positions up to float rounding (``tests/test_fast_training.py``):
the layers of a valid node never read an invalid node (every edge to one is masked) and padding never enters
a softmax. The rollout path (``init_rollout`` / ``step``) is unchanged.

:func:`reach_radius_m` gives the distance beyond which no map token can influence an agent node
(map-to-agent radius + one map radius per map layer); :func:`r1sim_sumo.tokens.batch.crop_map_to_reach`
drops those tokens before collation, which leaves every logit unchanged.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from r1sim_sumo.model.layers import (
    MAP_SPEED_SCALE_MPS,
    POS_SCALE_M,
    check_tokens,
    kdtree_neighbours,
    knn,
    map_kind_index,
    pack_pose,
    rel_pose_features,
)
from r1sim_sumo.tokens.constants import N_MAP_PTS


def reach_radius_m(config) -> float:
    """[m] Map tokens farther than this from every agent node cannot change any logit: an agent node reads map
    tokens within ``map_agent_radius_m``, and each of the ``map_layers`` map layers reads tokens within
    ``map_radius_m`` of its query (segment middles)."""
    return float(config.map_agent_radius_m + config.map_layers * config.map_radius_m)


def _knn_per_scene(q_xy: Tensor, q_off: Tensor, k_xy: Tensor, k_off: Tensor, k: int, radius_m: float) -> tuple[Tensor, Tensor]:
    """k nearest keys of each query within its own scene, for packed queries/keys (positions [m], world frame)
    with scene offsets ``q_off``/``k_off`` ``[B+1]``. Returns global key indices ``[Q, k]`` and validity (False
    beyond ``radius_m`` and for the missing columns of scenes with fewer than ``k`` keys, which point at key 0).

    On the CPU a k-d tree per scene (:func:`~r1sim_sumo.model.layers.kdtree_neighbours`) finds the candidates: O(Q log K) instead of the
    brute-force O(Q K) distance matrix + top-k of :func:`~r1sim_sumo.model.layers.knn` (which GPUs keep); about 10x
    less time in the searches of a training step in one side-by-side measurement on a loaded machine. The radius test is then redone in float32 exactly as :func:`knn` does it, so both
    select the same neighbours up to exact distance ties at the k-th place (attention is order-invariant over
    map and agent slots)."""
    Q = q_xy.shape[0]
    if q_xy.is_cuda:
        return _knn_per_scene_dense(q_xy, q_off, k_xy, k_off, k, radius_m)
    idx = torch.zeros(Q, k, dtype=torch.long)
    found = torch.zeros(Q, k, dtype=torch.bool)
    qn, kn = q_xy.detach().double().numpy(), k_xy.detach().double().numpy()
    qo, ko = q_off.tolist(), k_off.tolist()
    for b in range(len(qo) - 1):
        q0, q1, k0, k1 = qo[b], qo[b + 1], ko[b], ko[b + 1]
        if q1 == q0 or k1 == k0:
            continue
        i = torch.from_numpy(kdtree_neighbours(qn[q0:q1], kn[k0:k1], k, radius_m))  # a hair wide: the test below decides
        kk = i.shape[1]
        hit = i >= 0
        idx[q0:q1, :kk] = torch.where(hit, i + k0, 0)
        found[q0:q1, :kk] = hit
    d = q_xy.unsqueeze(1) - k_xy[idx]  # [Q, k, 2]
    d2 = torch.addcmul(d[..., 0] * d[..., 0], d[..., 1], d[..., 1])
    return idx, found & (d2 <= radius_m * radius_m)


def _knn_per_scene_dense(q_xy: Tensor, q_off: Tensor, k_xy: Tensor, k_off: Tensor, k: int,
                         radius_m: float) -> tuple[Tensor, Tensor]:
    """:func:`_knn_per_scene` by brute force (:func:`~r1sim_sumo.model.layers.knn` per scene), for GPUs."""
    Q = q_xy.shape[0]
    idx = torch.zeros(Q, k, dtype=torch.long, device=q_xy.device)
    ok = torch.zeros(Q, k, dtype=torch.bool, device=q_xy.device)
    qo, ko = q_off.tolist(), k_off.tolist()
    for b in range(len(qo) - 1):
        q0, q1, k0, k1 = qo[b], qo[b + 1], ko[b], ko[b + 1]
        if q1 == q0 or k1 == k0:
            continue
        keys = k_xy[k0:k1].unsqueeze(0)
        i, v = knn(q_xy[q0:q1].unsqueeze(0), keys, torch.ones(1, k1 - k0, dtype=torch.bool, device=q_xy.device),
                   k, radius_m)
        kk = i.shape[-1]
        idx[q0:q1, :kk] = i[0] + k0
        ok[q0:q1, :kk] = v[0]
    return idx, ok


def _offsets(counts: Tensor) -> Tensor:
    return F.pad(torch.cumsum(counts, 0), (1, 0))


def encode_map_packed(model, batch) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Encode the real map tokens of ``batch``: ``(feat [M_tot, D], pose [M_tot, 4], tl [M_tot, 19], offsets [B+1])``.

    Same computation as :meth:`TrafficPolicy.encode_map` on the valid tokens (positions [m] world frame, pose
    packed as x, y, cos, sin of the segment yaw)."""
    c = model.config
    mvalid = batch.map_mask.bool()
    off = _offsets(mvalid.sum(1))
    yaw = batch.map_yaw[mvalid]
    cos, sin = yaw.cos(), yaw.sin()
    pts = batch.map_pts[mvalid]  # [Mt, 11, 2] own frame
    mid = pts[:, N_MAP_PTS // 2]
    xy = batch.map_pos[mvalid] + torch.stack([mid[:, 0] * cos - mid[:, 1] * sin, mid[:, 0] * sin + mid[:, 1] * cos], -1)
    pose = torch.cat([xy, cos.unsqueeze(-1), sin.unsqueeze(-1)], -1)  # [Mt, 4]
    feat_in = torch.cat([pts.flatten(1) / POS_SCALE_M, batch.map_speed[mvalid].unsqueeze(-1) / MAP_SPEED_SCALE_MPS], -1)
    x = model.map_in(feat_in) + model.map_kind(map_kind_index(batch.map_kind[mvalid], c.num_map_kinds))  # [Mt, D]
    idx, ok = _knn_per_scene(xy, off, xy, off, c.map_k, c.map_radius_m)  # [Mt, k]
    r = model.map_edge(rel_pose_features(pose[idx], pose))  # [Mt, k, D]
    for blk in model.map_blocks:
        xn = blk.normed(x)
        x = blk.forward_gathered(x, xn, xn, idx, r, ok)
    tl = batch.map_tl[mvalid].long().clamp(0, c.num_tl_states - 1)
    return model.map_norm(x), pose, tl, off


def _node_desired_speed(batch, nb: Tensor, na: Tensor) -> Tensor | None:
    """Desired speed [m/s] of each node's agent ``[N]`` (``None`` for batches without desired speeds)."""
    v = getattr(batch, "agent_desired_speed", None)
    return None if v is None else v[nb, na]


def packed_logits(model, batch, out_mask: Tensor, prev_hidden: Tensor | None = None) -> Tensor:
    """Teacher-forced logits ``[n, V_max]`` of the nodes where ``out_mask [B, A, 18]`` is True, in
    ``out_mask.nonzero()`` order; ``out_mask`` must lie within the valid nodes (``pose_valid & agent_mask``).

    ``prev_hidden [B, A, 18]`` (training only): nodes whose previous-token input is replaced by the type's start
    token (as if the token were unknown), so the step must be predicted from the pose history; labels unchanged.

    Equal (up to float rounding) to ``model(batch)[out_mask]``; see the module docstring."""
    c = model.config
    W = c.temporal_span
    tok, tok_valid = batch.agent_token, batch.agent_token_valid.bool()
    B, A, T = tok.shape
    dev = tok.device
    map_feat, map_pose, map_tl, m_off = encode_map_packed(model, batch)

    valid = batch.pose_valid[:, :, :T].bool() & batch.agent_mask.bool().unsqueeze(-1)  # [B, A, T]
    if bool((out_mask & ~valid).any()):
        raise ValueError("packed_logits: out_mask selects nodes without a valid pose")
    nb, na, nt = valid.nonzero(as_tuple=True)  # [N], (scene, agent, step) order
    N = nb.shape[0]
    nid = torch.full((B, A, T), -1, dtype=torch.long, device=dev)
    nid[nb, na, nt] = torch.arange(N, device=dev)
    n_off = _offsets(valid.flatten(1).sum(1))
    pose = pack_pose(batch.pose_xy[nb, na, nt], batch.pose_yaw[nb, na, nt])  # [N, 4]
    atype = batch.agent_type[nb, na]

    prev = torch.where(tok_valid, tok, -1)
    prev = torch.cat([prev.new_full((B, A, 1), -1), prev[:, :, :-1]], 2)  # token k-1 of each node
    if prev_hidden is not None:
        prev = prev.masked_fill(prev_hidden.bool(), -1)
    before = torch.cat([prev.new_full((B, A, 1), -1), prev[:, :, :-1]], 2)  # token k-2 (the node before's input)
    before = before.masked_fill(prev == -1, -1)[nb, na, nt]  # a hidden / unknown previous token: no trend either
    prev = prev[nb, na, nt]
    check_tokens(tok, tok_valid, model.type_vocab[batch.agent_type])
    tix = model._token_index(prev.unsqueeze(-1), atype).squeeze(-1)  # [N]
    desired = _node_desired_speed(batch, nb, na)
    x = model.token_table()[tix] + model._agent_static(atype, batch.agent_size[nb, na], desired)
    x = x + model._speed_gap(tix, desired)
    x = x + model._speed_trend(tix, model._token_index(before.unsqueeze(-1), atype).squeeze(-1))

    # temporal window: the node's own steps t-W+1 .. t (oldest first), -1 where absent
    widx = F.pad(nid, (W - 1, 0), value=-1).unfold(2, W, 1)[nb, na, nt]  # [N, W]
    t_ok = widx >= 0
    widx = widx.clamp_min(0)
    # map neighbours (per scene) and agent neighbours (same scene and step, computed on the padded layout)
    m_idx, m_ok = _knn_per_scene(pose[:, :2], n_off, map_pose[:, :2], m_off, c.map_agent_k, c.map_agent_radius_m)
    qa = batch.pose_xy[:, :, :T].transpose(1, 2).reshape(B * T, A, 2)
    a_loc, a_ok = knn(qa, qa, valid.transpose(1, 2).reshape(B * T, A), c.agent_k, c.agent_radius_m, exclude_self=True)
    ka = a_loc.shape[-1]
    a_loc = a_loc.view(B, T, A, ka)[nb, nt, na]  # [N, ka] agent index in the node's scene
    a_ok = a_ok.view(B, T, A, ka)[nb, nt, na]
    a_idx = nid[nb.unsqueeze(1), a_loc, nt.unsqueeze(1)]  # [N, ka] packed node index (-1 = invalid)
    a_ok = a_ok & (a_idx >= 0)
    a_idx = a_idx.clamp_min(0)
    if ka < c.agent_k:  # fewer agents in the batch than k: pad with masked slots, as every slot feature exists
        pad = c.agent_k - ka
        a_idx, a_ok = F.pad(a_idx, (0, pad)), F.pad(a_ok, (0, pad))

    km = c.map_agent_k
    slot = model.slot_feat  # [E, 4]
    slot_bias = model.edge_slot(slot)  # [E, D]

    def rel_enc(src: Tensor, lo: int, hi: int) -> Tensor:  # the relative encodings of edge slots lo..hi-1
        rel = rel_pose_features(src, pose)  # [N, e, 5]
        feat = torch.cat([rel, slot[lo:hi, :1].expand(rel.shape[:-1] + (1,))], -1)
        return model.edge_emb(feat, slot_bias[lo:hi])  # [N, e, D]

    # one embedding call per edge group (not one over all slots, sliced): the same values, and the backward
    # writes each group's gradient directly instead of zero-filling the full [N, E, D] buffer once per slice
    ed = dict(
        rt=rel_enc(pose[widx], 0, W), rm=rel_enc(map_pose[m_idx], W, W + km), ra=rel_enc(pose[a_idx], W + km, W + km + c.agent_k),
        t_mask=t_ok, m_mask=m_ok, a_mask=a_ok, a_idx=a_idx, t_idx=widx,
        m_content=map_feat[m_idx] + model.tl_emb(map_tl[m_idx, nt.unsqueeze(1)]),
    )
    x = model._decode(x, ed, lambda li, xn: xn[widx])  # [N, D]
    rows = nid[out_mask]
    logits = model.head(x[rows])  # [n, V_max]
    rtype = atype[rows]
    small = model.type_vocab[rtype] < c.vocab_max
    if bool(small.any()):  # types with a smaller vocabulary: their ids above it are impossible
        logits = logits.masked_fill(model.head_invalid[rtype] & small.unsqueeze(-1), float("-inf"))
    return logits


def future_logits(model, batch, mask: Tensor, first_step: int) -> Tensor | None:
    """Packed teacher-forced logits ``[n, V_max]`` of the token steps ``first_step .. first_step + F - 1`` where
    ``mask [B, A, F]`` is True, in ``mask.nonzero()`` order (fine-tuning losses over rebuilt rollouts); ``None`` when a
    masked token has no valid start pose (the caller then runs the padded forward, which scores it anyway).

    Equal to ``model(batch)[:, :, first_step:first_step + F][mask]`` up to float rounding; on one CPU thread a GRPO
    update took 56 s instead of 107 s on the same iteration (session 7, one CPU thread beside another job)."""
    F = mask.shape[-1]
    node_ok = batch.pose_valid[:, :, first_step : first_step + F].bool() & batch.agent_mask.bool().unsqueeze(-1)
    if bool((mask & ~node_ok).any()):
        return None
    out_mask = torch.zeros(batch.agent_token.shape, dtype=torch.bool, device=mask.device)
    out_mask[:, :, first_step : first_step + F] = mask
    return model(batch, out_mask=out_mask)  # the module call (forward -> packed_logits), wrappers included


def loss_mask(batch) -> Tensor:
    """``[B, A, 18]`` bool: the tokens the training loss averages over (valid token, real agent, valid start pose)."""
    T = batch.agent_token.shape[2]
    return batch.agent_token_valid.bool() & batch.agent_mask.bool().unsqueeze(-1) & batch.pose_valid[:, :, :T].bool()


def packed_loss(model, batch, label_smoothing: float = 0.1, targets: Tensor | None = None,
                forward=None, prev_hidden: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """:meth:`TrafficPolicy.loss` computed over packed nodes: label-smoothed cross-entropy (fp32) over the
    :func:`loss_mask` tokens. ``forward`` is what to call for the logits (a ``DistributedDataParallel``
    wrapper of ``model``; default ``model``). Returns (mean loss, top-1 accuracy)."""
    valid = loss_mask(batch)
    if targets is not None:  # -1: a label to ignore (e.g. rewritten steps of r1sim_sumo.train.steady_history)
        valid = valid & (targets >= 0)
    target = (batch.agent_token if targets is None else targets)[valid]
    ty = batch.agent_type.unsqueeze(-1).expand_as(valid)[valid]
    logits = (forward or model)(batch, out_mask=valid, prev_hidden=prev_hidden)
    return smoothed_cross_entropy(model, logits, target, ty, label_smoothing)


def smoothed_cross_entropy(model, logits: Tensor, target: Tensor, agent_type: Tensor,
                           label_smoothing: float) -> tuple[Tensor, Tensor]:
    """Label smoothing spread over each row's own type vocabulary; logits ``[n, V_max]`` (-inf outside it).
    Computed in fp32 whatever the logits' dtype (bf16 under autocast), by :class:`SmoothedCrossEntropy`."""
    if target.numel() == 0:
        zero = logits.sum() * 0.0
        return zero, zero.detach()
    vocab = model.type_vocab[agent_type]
    loss = SmoothedCrossEntropy.apply(logits, target, vocab, float(label_smoothing))
    z = logits.detach()  # top-1: the target's logit is the row's largest (amax is ~7x faster than argmax on a CPU)
    acc = (z.gather(-1, target.unsqueeze(-1)).squeeze(-1) >= z.amax(-1)).float().mean()
    return loss, acc.detach()


def _valid_sums(z: Tensor, vocab: Tensor) -> Tensor:
    """Per row the sum of ``z [n, V]`` over the row's first ``vocab[row]`` columns (its type's vocabulary)."""
    sizes = vocab.unique().tolist()  # one value per agent type present
    if len(sizes) == 1:
        return z[:, : sizes[0]].sum(-1)
    out = z.new_empty(z.shape[0])
    for v in sizes:
        rows = vocab == v
        out[rows] = z[rows, :v].sum(-1)
    return out


class SmoothedCrossEntropy(torch.autograd.Function):
    """Mean over rows of ``(1 - eps) * NLL(target) + eps * mean over the row's vocabulary of -log p``, with one
    hand-written backward.

    With ``lse`` the row's log-sum-exp and ``s`` the sum of its logits over its vocabulary of size ``v``, a row's
    loss is ``lse - (1 - eps) z_target - eps s / v`` and its gradient ``softmax(z) - (1 - eps) onehot(target) -
    eps / v`` on the vocabulary (0 outside it, where the logits are -inf). Autograd of the log-softmax form
    materialised and zero-filled several ``[n, V]`` buffers (the gather's backward alone took ~10% of a training
    step); this does three passes forward and three backward. Equal to the log-softmax form up to float rounding
    (``tests/test_fast_training.py``)."""

    @staticmethod
    def forward(ctx, logits: Tensor, target: Tensor, vocab: Tensor, eps: float) -> Tensor:
        z = logits.float() if logits.dtype in (torch.float16, torch.bfloat16) else logits
        lse = torch.logsumexp(z, -1)  # [n]
        z_t = z.gather(-1, target.unsqueeze(-1)).squeeze(-1)
        s = _valid_sums(z, vocab)
        ctx.save_for_backward(z, lse, target, vocab)
        ctx.eps = eps
        return (lse - (1.0 - eps) * z_t - eps * s / vocab).mean()

    @staticmethod
    def backward(ctx, g: Tensor):
        z, lse, target, vocab = ctx.saved_tensors
        eps, n, V = ctx.eps, z.shape[0], z.shape[1]
        grad = torch.sub(z, lse.unsqueeze(-1)).exp_()  # softmax; 0 where the logit is -inf
        grad.sub_((eps / vocab).unsqueeze(-1))
        for v in vocab.unique().tolist():  # outside a row's vocabulary the gradient is 0
            if v < V:
                grad[vocab == v, v:] = 0.0
        grad.scatter_add_(-1, target.unsqueeze(-1), grad.new_full((n, 1), -(1.0 - eps)))
        return grad.mul_(g / n), None, None, None
