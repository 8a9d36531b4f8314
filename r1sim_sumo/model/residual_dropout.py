"""``x + dropout(u)`` in one pass, with the dropout mask hashed from a seed instead of drawn and stored.

The residual branches of :mod:`r1sim_sumo.model.layers` end in ``x + F.dropout(u, p)``. On a CPU ``F.dropout``
draws a Bernoulli tensor element by element (about 6 ns an element: ~5% of a pretraining step of the nano model) and
keeps the mask for the backward. :func:`residual_dropout` computes ``y = x + keep * u / (1 - p)`` in a small C kernel
(``residual_dropout.c``, built by :mod:`r1sim_sumo.model.c_kernels`) where ``keep`` for element ``i`` is a hash of
``(seed, i)``: one 64-bit hash decides four elements, nothing is stored, and the backward recomputes the mask. The seed
is drawn from PyTorch's default generator, so ``torch.manual_seed`` and a resumed run's saved RNG state fix the masks
as they fix ``F.dropout``'s. The drop probability is ``p`` rounded to a multiple of 1/65536, and ``scale`` is
``1 / (1 - that)``: the branch's expectation is unchanged. It is the same Bernoulli dropout, with other random draws
than ``F.dropout``'s.

Applies to CPU tensors with ``x`` fp32 and ``u`` fp32 or bf16 (bf16 autocast's linear outputs; ``u``'s gradient
then is bf16 too). Elsewhere (CUDA, other dtypes, no compiler, ``R1SIM_FUSED_DROPOUT=0``) it is ``x +
F.dropout(u, p)``.
"""

from __future__ import annotations

import ctypes

import torch
import torch.nn.functional as F
from torch import Tensor

from r1sim_sumo.model.c_kernels import CKernel
from r1sim_sumo.model.c_kernels import pointer as _p


def _declare(dll: ctypes.CDLL) -> None:
    i64, u64, u32, f32, ptr, c_int = ctypes.c_int64, ctypes.c_uint64, ctypes.c_uint32, ctypes.c_float, ctypes.c_void_p, ctypes.c_int
    dll.rdrop_forward.argtypes = [ptr, ptr, ptr, i64, u64, u32, f32, c_int, c_int]
    dll.rdrop_backward.argtypes = [ptr, ptr, i64, u64, u32, f32, c_int, c_int]
    dll.rdrop_forward.restype = dll.rdrop_backward.restype = None


KERNEL = CKernel("residual_dropout.c", _declare, "R1SIM_FUSED_DROPOUT")


def threshold(p: float) -> tuple[int, float]:
    """``(thr, scale)``: an element is dropped when its 16-bit hash lane is ``< thr = round(p * 65536)``, and kept
    elements are multiplied by ``scale = 1 / (1 - thr / 65536)``."""
    thr = min(65535, max(0, round(p * 65536)))
    return thr, 1.0 / (1.0 - thr / 65536.0)


class ResidualDropout(torch.autograd.Function):
    """``x + keep(seed) * u * scale`` with the kernel's forward and backward (``dy/dx = 1``)."""

    @staticmethod
    def forward(ctx, x: Tensor, u: Tensor, p: float, seed: int) -> Tensor:
        x, u = x.contiguous(), u.contiguous()
        thr, scale = threshold(p)
        y = torch.empty_like(x)
        KERNEL.library().rdrop_forward(_p(x), _p(u), _p(y), x.numel(), seed, thr, scale, int(u.dtype == torch.bfloat16),
                                       torch.get_num_threads())
        ctx.seed, ctx.thr, ctx.scale, ctx.u_dtype = seed, thr, scale, u.dtype
        return y

    @staticmethod
    def backward(ctx, g: Tensor):
        g = g.float().contiguous()
        g_u = torch.empty(g.shape, dtype=ctx.u_dtype)
        KERNEL.library().rdrop_backward(_p(g), _p(g_u), g.numel(), ctx.seed, ctx.thr, ctx.scale,
                                        int(ctx.u_dtype == torch.bfloat16), torch.get_num_threads())
        return g, g_u, None, None


def _fused(x: Tensor, u: Tensor) -> bool:
    return (x.device.type == "cpu" and u.device.type == "cpu" and x.dtype == torch.float32
            and u.dtype in (torch.float32, torch.bfloat16) and x.shape == u.shape and KERNEL.available())


def residual_dropout(x: Tensor, u: Tensor, p: float, training: bool) -> Tensor:
    """``x + dropout(u, p)`` (``x + u`` when not ``training`` or ``p == 0``); ``x`` and ``u`` of one shape.

    :param x: the residual stream (fp32 on the fused path).
    :param u: the branch's output (fp32 or bf16 on the fused path).
    """
    if not training or p <= 0.0:
        return x + u
    if not _fused(x, u):
        return x + F.dropout(u, p, True)
    seed = int(torch.randint(0, 2**62, (), dtype=torch.int64))  # from the default generator: seeded runs repeat
    return ResidualDropout.apply(x, u, p, seed)
