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
turns it off. CPU only (CUDA keeps the plain path); under bf16 autocast the queries and outputs are stored in bf16 and
the arithmetic is fp32.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import torch
from torch import Tensor

_SOURCE = Path(__file__).with_name("gathered_attention.c")
_FLAGS = ["-O3", "-march=native", "-fopenmp", "-fPIC", "-shared", "-std=c99"]
_FALLBACK_FLAGS = (["-O3", "-fopenmp", "-fPIC", "-shared", "-std=c99"],  # compilers without -march=native
                   ["-O3", "-fPIC", "-shared", "-std=c99"])  # without OpenMP: one thread, same values
_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_error: str | None = None


def _cpu_key() -> str:
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        return next((ln for ln in lines if ln.startswith("flags")), "") + next((ln for ln in lines if ln.startswith("model name")), "")
    except OSError:
        return platform.processor()


def _build() -> ctypes.CDLL:
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        raise RuntimeError("no C compiler (cc / gcc) on PATH")
    src = _SOURCE.read_bytes()
    cache = Path(os.environ.get("R1SIM_KERNEL_CACHE") or Path.home() / ".cache" / "r1sim_sumo" / "kernels")
    errors = []
    for flags in (_FLAGS, *_FALLBACK_FLAGS):
        key = hashlib.sha256(src + " ".join(flags).encode() + cc.encode() + _cpu_key().encode()).hexdigest()[:16]
        lib = cache / f"gathered_attention_{key}.so"
        if lib.exists():
            break
        cache.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=cache) as tmp:  # build aside, then move: no half-written library
            out = Path(tmp) / lib.name
            res = subprocess.run([cc, *flags, str(_SOURCE), "-o", str(out), "-lm"], capture_output=True, text=True)
            if res.returncode == 0:
                os.replace(out, lib)
                break
            errors.append(f"{cc} {' '.join(flags)}: {res.stderr.strip()[-300:]}")
    else:
        raise RuntimeError(f"could not build {_SOURCE.name}: " + " | ".join(errors))
    dll = ctypes.CDLL(str(lib))
    i64, ptr, c_int = ctypes.c_int64, ctypes.c_void_p, ctypes.c_int
    dll.gea_forward.argtypes = [ptr] * 7 + [i64] * 5 + [c_int, c_int]
    dll.gea_backward.argtypes = [ptr] * 10 + [i64] * 6 + [c_int, c_int]
    dll.gea_forward.restype = dll.gea_backward.restype = None
    return dll


def _library() -> ctypes.CDLL | None:
    global _lib, _error
    if _lib is None and _error is None:
        with _lock:
            if _lib is None and _error is None:
                try:
                    _lib = _build()
                except (OSError, RuntimeError) as exc:
                    _error = str(exc)
    return _lib


def available() -> bool:
    """True when the kernel is built (or builds now) and not turned off by ``R1SIM_FUSED_ATTENTION=0``."""
    if os.environ.get("R1SIM_FUSED_ATTENTION", "1") == "0":
        return False
    return _library() is not None


def unavailable_reason() -> str | None:
    """Why :func:`available` is False (``None`` when it is True)."""
    if os.environ.get("R1SIM_FUSED_ATTENTION", "1") == "0":
        return "turned off by R1SIM_FUSED_ATTENTION=0"
    _library()
    return _error


def usable(*tensors: Tensor) -> bool:
    """The kernel applies: CPU tensors in fp32 or bf16 (under bf16 autocast the edge-space queries and the
    aggregated features are bf16 tensors, the kernel's arithmetic stays fp32) and the kernel is available."""
    return all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.bfloat16) for t in tensors) and available()


def _p(t: Tensor | None) -> ctypes.c_void_p:
    return ctypes.c_void_p(None if t is None else t.data_ptr())


class GatheredEdgeAttention(torch.autograd.Function):
    """``out [H, N, Dc+Dr]`` of :func:`gathered_edge_attention`, with the kernel's backward. ``qe`` (and so ``out``,
    and the gradients of both) may be fp32 or bf16; ``src`` and ``rel`` are fp32; the arithmetic is fp32."""

    @staticmethod
    def forward(ctx, qe: Tensor, src: Tensor, idx: Tensor | None, rel: Tensor, mask: Tensor) -> Tensor:
        qe, src, rel, mask = qe.contiguous(), src.contiguous(), rel.contiguous(), mask.contiguous()
        idx = None if idx is None else idx.contiguous()
        H, N, De = qe.shape
        E, Dc, Dr = mask.shape[1], src.shape[1], rel.shape[2]
        out = torch.empty_like(qe)
        w = src.new_empty(N, H, E)
        _library().gea_forward(_p(qe), _p(src), _p(idx), _p(rel), _p(mask), _p(out), _p(w), N, H, E, Dc, Dr,
                               torch.get_num_threads(), int(qe.dtype == torch.bfloat16))
        ctx.save_for_backward(qe, src, idx, rel, mask, w)
        return out

    @staticmethod
    def backward(ctx, g_out: Tensor):
        qe, src, idx, rel, mask, w = ctx.saved_tensors
        g_out = g_out.to(qe.dtype).contiguous()
        H, N, De = qe.shape
        E, Dc, Dr = mask.shape[1], src.shape[1], rel.shape[2]
        g_qe = torch.empty_like(qe)
        g_src = torch.zeros_like(src) if idx is not None else torch.empty_like(src)  # identity: every row written
        g_rel = torch.empty_like(rel)
        _library().gea_backward(_p(qe), _p(src), _p(idx), _p(rel), _p(mask), _p(w), _p(g_out), _p(g_qe), _p(g_src),
                                _p(g_rel), N, src.shape[0], H, E, Dc, Dr, torch.get_num_threads(),
                                int(qe.dtype == torch.bfloat16))
        return g_qe, g_src, None, g_rel, None


def gathered_edge_attention(qe: Tensor, src: Tensor, idx: Tensor | None, rel: Tensor, mask: Tensor) -> Tensor:
    """Attention of each query over its edges ``k(n, e) = [src[idx[n, e]], rel[n, e]]``.

    :param qe: ``[H, N, Dc + Dr]`` queries mapped into edge space, head-major (scale included); fp32, or bf16 under
        autocast (the output then is bf16 too; the arithmetic is fp32 either way).
    :param src: ``[Ns, Dc]`` source table (e.g. the layer's normalised node features).
    :param idx: ``[N, E]`` int64 rows of ``src``, read only where ``mask`` is True; ``None``: row ``n * E + e``
        (per-edge content, ``src`` ``[N * E, Dc]``).
    :param rel: ``[N, E, Dr]`` per-edge features (relative encodings).
    :param mask: ``[N, E]`` bool, True = real neighbour; a query without one gets zeros.
    :return: ``[H, N, Dc + Dr]`` attention-weighted edge features, as
        :func:`r1sim_sumo.model.layers.edge_attention` of ``cat([src[idx], rel], -1)`` (head-major).
    """
    if qe.dtype not in (torch.float32, torch.bfloat16):
        qe = qe.float()
    if idx is None and src.shape[0] != mask.numel():
        raise ValueError(f"gathered_edge_attention: identity rows need src [N * E, Dc], got {tuple(src.shape)} for "
                         f"{tuple(mask.shape)} edges")
    return GatheredEdgeAttention.apply(qe, src.float(), idx, rel.float(), mask.to(torch.bool))
