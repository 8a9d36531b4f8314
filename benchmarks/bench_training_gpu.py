"""Pretraining step on REAL batches of the default recipe on a CUDA GPU (rows are skipped on a machine without one).

The same batches as ``bench_training`` (the first batches of the default recipe's training split from the compact
token dataset ``data/tokens/default``, epoch order of seed 0, exact matching), moved to the GPU before timing: the
rows time the model step alone (forward + loss + backward + AdamW), not the CPU work that builds a batch (noised
matching, map crop, collate: ~30 ms of CPU per scene, which ``loader_workers`` processes do ahead of the step in a
training run). Configurations: the reference (padded) step and the fast (packed) step in fp32 and bf16 autocast at
batch 4, and the fast bf16 step at batch 32 (the lent-GPU training recipe). Reported: seconds per step,
agent-tokens/s, matmul FLOP/s (``torch.utils.flop_counter``) as a fraction of dense 4096^3 fp32 (TF32 off) and bf16
matmul peaks measured in the same process, peak GPU memory.

``python benchmarks/run.py --only training_gpu --out benchmarks/reports/gpu`` on a machine with a GPU.
"""

from __future__ import annotations

import time

import torch

from r1sim_sumo.model.packed import packed_loss
from r1sim_sumo.train.pretrain import autocast

CONFIGS = [  # name, fast, precision, batch size
    ("reference fp32, batch 4", False, "fp32", 4),
    ("fast fp32, batch 4", True, "fp32", 4),
    ("fast bf16, batch 4", True, "bf16", 4),
    ("fast bf16, batch 32", True, "bf16", 32),
]


def _peak(dtype, dev, n: int = 4096, reps: int = 10) -> float:
    a, b = torch.randn(n, n, dtype=dtype, device=dev), torch.randn(n, n, dtype=dtype, device=dev)
    for _ in range(3):
        a @ b
    torch.cuda.synchronize(dev)
    t = time.perf_counter()
    for _ in range(reps):
        a @ b
    torch.cuda.synchronize(dev)
    return 2 * n**3 * reps / (time.perf_counter() - t)


def _loss(model, ref, fb, fast: bool):
    if fast:
        return packed_loss(model, fb, 0.1)[0]
    return model.loss(ref, model(ref), label_smoothing=0.1)[0]


def _flops(model, ref, fb, fast: bool, precision: str, dev) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as fc, autocast(dev, precision):
        _loss(model, ref, fb, fast).backward()
    model.zero_grad(set_to_none=True)
    return fc.get_total_flops()


def run(quick: bool = False) -> dict:
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_training import _model, real_batches

    title = "Pretraining step on real batches on a CUDA GPU (model step only)"
    if not torch.cuda.is_available():
        return {"title": title, "rows": [], "notes": ["skipped: torch sees no CUDA device on this machine"]}
    dev = torch.device("cuda")
    torch.backends.cuda.matmul.allow_tf32 = False
    peaks = {"fp32": _peak(torch.float32, dev), "bf16": _peak(torch.bfloat16, dev)}
    n_steps = 4 if quick else 12
    rows = []
    for name, fast, precision, bs in CONFIGS:
        vocab, batches = real_batches(n_steps, batch_size=bs)
        batches = [(r.to(dev), f.to(dev), n) for r, f, n in batches]
        model = _model(vocab).to(dev)
        opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
        flops = _flops(model, batches[0][0], batches[0][1], fast, precision, dev) * len(batches)  # also a warm-up
        for ref, fb, _ in batches[:2]:  # warm-up (allocator, kernels)
            with autocast(dev, precision):
                loss = _loss(model, ref, fb, fast)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        torch.cuda.synchronize(dev)
        torch.cuda.reset_peak_memory_stats(dev)
        t = time.perf_counter()
        for ref, fb, _ in batches:
            with autocast(dev, precision):
                loss = _loss(model, ref, fb, fast)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
        torch.cuda.synchronize(dev)
        sec = time.perf_counter() - t
        tokens = sum(n for _, _, n in batches)
        rows.append({
            "config": name, "s_per_step": sec / len(batches), "agent_tokens_per_s": tokens / sec,
            "GFLOP_per_step": flops / len(batches) / 1e9, "achieved_TFLOP_s": flops / sec / 1e12,
            "frac_fp32_peak": flops / sec / peaks["fp32"], "frac_bf16_peak": flops / sec / peaks["bf16"],
            "peak_gpu_memory_MB": torch.cuda.max_memory_allocated(dev) / 2**20,
        })
    notes = [
        f"device {torch.cuda.get_device_name(dev)}, torch {torch.__version__}; dense 4096^3 matmul peaks in this process "
        f"[TFLOP/s]: fp32 (TF32 off) {peaks['fp32'] / 1e12:.1f}, bf16 {peaks['bf16'] / 1e12:.1f}.",
        f"{n_steps} real batches per configuration, timed after 2 warm-up steps; the CPU rows of the same batches are "
        "in the `training` benchmark. The small model (nano, hidden 64) leaves the GPU launch-bound: the fractions of "
        "peak are low by design, and a training run's pace is set by how fast its loader_workers build batches.",
    ]
    return {"title": title, "rows": rows, "notes": notes}
