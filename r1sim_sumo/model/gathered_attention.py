"""Edge attention with the neighbours' content gathered on the fly: a small C kernel for CPU training.

:class:`~r1sim_sumo.model.layers.RelAttentionBlock` attends over edge features ``e = [src[idx], rel]`` (the
neighbour's normalised features, ``Dc`` wide, then the pair's relative encoding, ``Dr`` wide). The plain path
materialises ``e`` (``[N, E, Dc + Dr]``, a gather and a concatenation per block and layer) and runs the attention as
batched products of tiny matrices (4 heads x 8 edges per query), which on a CPU are bound by memory traffic and
per-batch overhead, forward and backward. :func:`gathered_edge_attention` computes the same values in one pass over the
edges per direction (``gathered_attention.c``): the source rows are read through ``idx`` (the source table, a few
MB, stays in cache) and nothing per edge is written in the forward but the weights ``[N, H, E]``.

The kernel is compiled at first use with the system C compiler (``cc``, ``-O3 -march=native -fopenmp``; without
``-march=native``, then without OpenMP where those fail) into
``~/.cache/r1sim_sumo/kernels/`` (``R1SIM_KERNEL_CACHE`` overrides it), keyed by the source, the flags and the CPU,
and loaded with ``ctypes``; where no compiler is found or the build fails, :func:`available` is False and callers
use the plain path (same values up to float rounding: ``tests/test_gathered_attention.py``). ``R1SIM_FUSED_ATTENTION=0``
turns it off (the build: :mod:`r1sim_sumo.model.c_kernels`). CPU only (CUDA keeps the plain path); under bf16
autocast the queries, outputs and bf16 edge features are read and written as bf16 and the arithmetic is fp32.
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from r1sim_sumo.model.c_kernels import CKernel
from r1sim_sumo.model.c_kernels import pointer as _p


def _declare(dll: ctypes.CDLL) -> None:
    i64, ptr, c_int = ctypes.c_int64, ctypes.c_void_p, ctypes.c_int
    dll.gea_forward.argtypes = [ptr] * 7 + [i64] * 5 + [c_int, c_int]
    dll.gea_backward.argtypes = [ptr] * 10 + [i64] * 6 + [c_int, c_int]
    dll.gea_forward.restype = dll.gea_backward.restype = None


KERNEL = CKernel("gathered_attention.c", _declare, "R1SIM_FUSED_ATTENTION")
_BF16_QE, _BF16_SRC, _BF16_REL = 1, 2, 4  # the kernel's dtype flags: which of qe (and out), src, rel are bf16


def _library() -> ctypes.CDLL | None:
    return KERNEL.library()


def available() -> bool:
    """True when the kernel is built (or builds now) and not turned off by ``R1SIM_FUSED_ATTENTION=0``."""
    return KERNEL.available()


def unavailable_reason() -> str | None:
    """Why :func:`available` is False (``None`` when it is True)."""
    return KERNEL.unavailable_reason()


def usable(*tensors: Tensor) -> bool:
    """The kernel applies: CPU tensors in fp32 or bf16 (under bf16 autocast the edge-space queries, the aggregated
    features and the linear layers' outputs among the edge features are bf16; the kernel's arithmetic stays fp32)
    and the kernel is available."""
    return all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.bfloat16) for t in tensors) and available()


def _flags(qe: Tensor, src: Tensor, rel: Tensor) -> int:
    bf = torch.bfloat16
    return (_BF16_QE * (qe.dtype == bf)) | (_BF16_SRC * (src.dtype == bf)) | (_BF16_REL * (rel.dtype == bf))


class GatheredEdgeAttention(torch.autograd.Function):
    """``out [H, N, Dc+Dr]`` of :func:`gathered_edge_attention`, with the kernel's backward. ``qe`` (and so ``out``),
    ``src`` and ``rel`` may each be fp32 or bf16 (their gradients come in the same dtype, read and written by the
    kernel without a cast copy); the arithmetic is fp32."""

    @staticmethod
    def forward(ctx, qe: Tensor, src: Tensor, idx: Tensor | None, rel: Tensor, mask: Tensor) -> Tensor:
        qe, src, rel, mask = qe.contiguous(), src.contiguous(), rel.contiguous(), mask.contiguous()
        idx = None if idx is None else idx.contiguous()
        H, N, De = qe.shape
        E, Dc, Dr = mask.shape[1], src.shape[1], rel.shape[2]
        out = torch.empty_like(qe)
        w = torch.empty(N, H, E, dtype=torch.float32)  # the softmax weights, fp32 whatever the inputs
        _library().gea_forward(_p(qe), _p(src), _p(idx), _p(rel), _p(mask), _p(out), _p(w), N, H, E, Dc, Dr,
                               torch.get_num_threads(), _flags(qe, src, rel))
        ctx.save_for_backward(qe, src, idx, rel, mask, w)
        return out

    @staticmethod
    def backward(ctx, g_out: Tensor):
        qe, src, idx, rel, mask, w = ctx.saved_tensors
        g_out = g_out.to(qe.dtype).contiguous()
        H, N, De = qe.shape
        E, Dc, Dr = mask.shape[1], src.shape[1], rel.shape[2]
        g_qe = torch.empty_like(qe)
        # fp32 scatter: accumulated in place (zeros); bf16 scatter: summed in the kernel's fp32 buffers, every row
        # stored; identity: every row written
        g_src = torch.zeros_like(src) if idx is not None and src.dtype == torch.float32 else torch.empty_like(src)
        g_rel = torch.empty_like(rel)
        _library().gea_backward(_p(qe), _p(src), _p(idx), _p(rel), _p(mask), _p(w), _p(g_out), _p(g_qe), _p(g_src),
                                _p(g_rel), N, src.shape[0], H, E, Dc, Dr, torch.get_num_threads(),
                                _flags(qe, src, rel))
        return g_qe, g_src, None, g_rel, None


def gathered_edge_attention(qe: Tensor, src: Tensor, idx: Tensor | None, rel: Tensor, mask: Tensor) -> Tensor:
    """Attention of each query over its edges ``k(n, e) = [src[idx[n, e]], rel[n, e]]``.

    :param qe: ``[H, N, Dc + Dr]`` queries mapped into edge space, head-major (scale included); fp32, or bf16 under
        autocast (the output then is bf16 too; the arithmetic is fp32 either way).
    :param src: ``[Ns, Dc]`` source table (e.g. the layer's normalised node features); fp32 or bf16.
    :param idx: ``[N, E]`` int64 rows of ``src``, read only where ``mask`` is True; ``None``: row ``n * E + e``
        (per-edge content, ``src`` ``[N * E, Dc]``).
    :param rel: ``[N, E, Dr]`` per-edge features (relative encodings); fp32 or bf16.
    :param mask: ``[N, E]`` bool, True = real neighbour; a query without one gets zeros.
    :return: ``[H, N, Dc + Dr]`` attention-weighted edge features, as
        :func:`r1sim_sumo.model.layers.edge_attention` of ``cat([src[idx], rel], -1)`` (head-major).
    """
    if qe.dtype not in (torch.float32, torch.bfloat16):
        qe = qe.float()
    if idx is None and src.shape[0] != mask.numel():
        raise ValueError(f"gathered_edge_attention: identity rows need src [N * E, Dc], got {tuple(src.shape)} for "
                         f"{tuple(mask.shape)} edges")
    if src.dtype not in (torch.float32, torch.bfloat16):
        src = src.float()
    if rel.dtype not in (torch.float32, torch.bfloat16):
        rel = rel.float()
    return GatheredEdgeAttention.apply(qe, src, idx, rel, mask.to(torch.bool))
