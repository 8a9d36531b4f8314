"""Pretraining step on REAL batches of the default recipe: the reference step vs the fast path, side by side.

Batches: the first ``N`` batches (batch size 4, epoch order of seed 0, exact matching) of the default recipe's
training split, from the compact token dataset ``data/tokens/default`` (``r1sim tokens build --data
data/generated/default --out data/tokens/default``). Every configuration runs the same batches, interleaved in
rounds (so machine noise hits all alike); a step = forward + loss + backward + AdamW.

Configurations: ``reference`` = the padded forward over the 150 m map crop in fp32 (the step before the fast
path; 2 threads = the old default); ``fast`` = packed forward over real map tokens and valid nodes, maps
cropped to the model's reach, with the attention core in the C kernel (``model/gathered_attention.py``), fp32 (the
default) or bf16 autocast (the attention stays fp32; the linear layers run in bf16, which pays only on CPUs with fast
bf16 matrix units such as AMX: the peaks row of the notes says which this machine is). Reported per configuration: seconds per step,
agent-tokens/s (valid tokens / s), matmul FLOP/s (``torch.utils.flop_counter``, forward + backward) as a fraction
of dense 1024^3 fp32 and bf16 matmul peaks measured in the same process with the same threads, minor page faults
per step, and peak resident memory of a separate 3-step process. Also a loss curve: ``curve_steps`` steps of the
reference (fp32, 2 threads) and of the fast path (fp32, 1 thread) from one initialisation on the same batches (with dropout, the
shipped recipe's lr schedule), plotted to ``reports/training_loss_curve.png``.

The first row, ``issue-time step``, is the step of the code when the throughput issue was filed (revision
``ISSUE_STEP_REV``, the study ``shared/studies/training-throughput.md``): the issue's target is 4x over *that* step on
the same batches. It runs from a detached git worktree of that revision in a child process
(``benchmarks/_issue_step_child.py``), once per round between the in-process rows; without git history the row is
left out and the notes say why. ``speedup_vs_issue_step`` is the ratio the issue asks for.

``python benchmarks/run.py --only training [--quick]``; alone: ``python benchmarks/bench_training.py``.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from r1sim_sumo._memory import keep_freed_memory
from r1sim_sumo.model import PolicyConfig, TrafficPolicy
from r1sim_sumo.model.packed import packed_loss, reach_radius_m
from r1sim_sumo.tokens.batch import collate, crop_map_to_reach
from r1sim_sumo.train.pretrain import EpochBatches, PretrainConfig, autocast, lr_at

ROOT = Path(__file__).resolve().parent.parent
TOKENS = ROOT / "data" / "tokens" / "default"
REPORTS = Path(__file__).resolve().parent / "reports"
MODEL_OVERRIDES = {"agent_k": 8, "map_agent_k": 8, "map_k": 8}  # configs/pretrain.yaml
ISSUE_STEP_REV = "c35897b045414adae3fbc23ed6f1899057a5c7fa"  # the code when the throughput issue was filed (its study)
ISSUE_STEP_NAME = "issue-time step (c35897b) fp32, 2 threads"
CONFIGS = [  # name, fast, precision, threads
    ("reference fp32, 2 threads", False, "fp32", 2),
    ("reference fp32, 1 thread", False, "fp32", 1),
    ("fast fp32, 1 thread", True, "fp32", 1),
    ("fast fp32, 2 threads", True, "fp32", 2),
    ("fast bf16, 1 thread", True, "bf16", 1),  # attention core in fp32 (kernel), linear layers in bf16
    ("fast bf16, 2 threads", True, "bf16", 2),
]


def _model(vocab, seed: int = 0, dropout: float | None = None) -> TrafficPolicy:
    torch.manual_seed(seed)
    over = dict(MODEL_OVERRIDES, **({} if dropout is None else {"dropout": dropout}))
    cfg = PolicyConfig.preset("nano", vocab_sizes=vocab.sizes, **over)
    return TrafficPolicy(cfg, [torch.as_tensor(vocab.traj[t]) for t in range(3)]).train()


def real_batches(n: int, batch_size: int = 4):
    """``(vocab, [(reference_batch, fast_batch, valid_tokens)] * n)`` from the compact default dataset."""
    from r1sim_sumo.tokens.compact import CompactTokenDataset

    if not (TOKENS / "manifest.json").exists():
        raise FileNotFoundError(f"{TOKENS}: no compact token dataset; build it with `r1sim dataset build --out "
                                "data/generated/default` then `r1sim tokens build --data data/generated/default "
                                "--out data/tokens/default`")
    ds = CompactTokenDataset(TOKENS, "train")
    order = EpochBatches(len(ds), batch_size, seed=0)
    reach = reach_radius_m(_model(ds.vocab).config) + 1.0
    out = []
    for s in range(n):
        scenes = [ds[i] for i in order(s)]
        ref = collate(scenes)
        fast = collate([crop_map_to_reach(sc, reach) for sc in scenes])
        out.append((ref, fast, int((ref.agent_token_valid & ref.agent_mask[..., None]).sum())))
    return ds.vocab, out


def _step_fn(model, opt, fast: bool, precision: str):
    dev = torch.device("cpu")

    def step(ref_batch, fast_batch):
        with autocast(dev, precision):
            if fast:
                loss, _ = packed_loss(model, fast_batch, 0.1)
            else:
                loss, _ = model.loss(ref_batch, model(ref_batch), label_smoothing=0.1)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        return float(loss.detach())

    return step


def _flops(model, fast: bool, precision: str, batches) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    total = 0
    for ref, fb, _ in batches[:2]:  # counted on two batches, scaled (FlopCounterMode's dispatch overhead is large)
        with FlopCounterMode(display=False) as fc, autocast(torch.device("cpu"), precision):
            loss = packed_loss(model, fb, 0.1)[0] if fast else model.loss(ref, model(ref))[0]
            loss.backward()
        model.zero_grad(set_to_none=True)
        total += fc.get_total_flops()
    return total * len(batches) / min(2, len(batches))


def _peak(dtype, threads: int, n: int = 1024, reps: int = 5) -> float:
    torch.set_num_threads(threads)
    a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
    a @ b
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        a @ b
        ts.append(time.perf_counter() - t)
    return 2 * n**3 / min(ts)


class IssueStep:
    """The training step of revision :data:`ISSUE_STEP_REV` (the padded forward + ``model.loss`` of the old code,
    fp32, 2 threads, as the old ``r1sim pretrain`` ran it) on the same batches, in a child process whose
    ``r1sim_sumo`` is a detached git worktree of that revision (``benchmarks/_issue_step_child.py``).
    ``available`` is False (with ``why``) where the revision cannot be checked out (no git, shallow clone)."""

    def __init__(self, vocab, batches, tmp: Path) -> None:
        self.tree, self.blob, self.why = tmp / "issue_tree", tmp / "batches.pt", ""
        out = subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(self.tree), ISSUE_STEP_REV],
                             capture_output=True, text=True)
        self.available = out.returncode == 0
        if not self.available:
            self.why = (out.stderr.strip().splitlines() or ["git worktree add failed"])[-1]
            return
        torch.save({"batches": [{k: v for k, v in ref._asdict().items()} for ref, _, _ in batches],
                    "traj": [np.asarray(vocab.traj[t]) for t in range(3)], "vocab_sizes": list(vocab.sizes),
                    "model_overrides": MODEL_OVERRIDES}, self.blob)

    def run(self, passes: int, threads: int = 2, flops: bool = False) -> dict:
        env = dict(os.environ, PYTHONPATH=str(self.tree), OMP_NUM_THREADS=str(threads))
        cmd = [sys.executable, str(Path(__file__).with_name("_issue_step_child.py")), str(self.blob), str(threads), str(passes)]
        out = subprocess.run(cmd + (["--flops"] if flops else []), capture_output=True, text=True, env=env, timeout=1800)
        if out.returncode:
            raise RuntimeError(f"issue-time step child failed:\n{out.stderr[-2000:]}")
        res = json.loads(out.stdout.strip().splitlines()[-1])
        if not Path(res["file"]).resolve().is_relative_to(self.tree.resolve()):
            raise RuntimeError(f"issue-time step child imported {res['file']}, not the worktree {self.tree}")
        return res

    def close(self) -> None:
        if self.available:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(self.tree)], capture_output=True)


def throughput(n_batches: int, rounds: int) -> tuple[list[dict], dict]:
    import tempfile

    keep_freed_memory()
    vocab, batches = real_batches(n_batches)
    tokens = sum(b[2] for b in batches)
    with tempfile.TemporaryDirectory() as tmp:
        issue = IssueStep(vocab, batches, Path(tmp))
        try:
            return _throughput(vocab, batches, tokens, rounds, issue)
        finally:
            issue.close()


def _throughput(vocab, batches, tokens: int, rounds: int, issue: IssueStep) -> tuple[list[dict], dict]:
    n_batches = len(batches)
    runs = []
    for name, fast, precision, threads in CONFIGS:
        model = _model(vocab)
        opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
        torch.set_num_threads(threads)
        flops = _flops(model, fast, precision, batches)  # also the warm-up
        runs.append(dict(name=name, fast=fast, precision=precision, threads=threads, step=_step_fn(model, opt, fast, precision),
                         flops=flops, times=[], faults=[]))
    issue_runs = []
    for rnd in range(rounds):  # interleaved: every configuration runs all batches once per round
        if issue.available:
            issue_runs.append(issue.run(1, flops=rnd == 0))
        for r in runs:
            torch.set_num_threads(r["threads"])
            f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            t = time.perf_counter()
            for ref, fb, _ in batches:
                r["step"](ref, fb)
            r["times"].append(time.perf_counter() - t)
            r["faults"].append((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / len(batches))
    peaks = {t: (_peak(torch.float32, t), _peak(torch.bfloat16, t)) for t in (1, 2)}
    if issue_runs:  # the issue's "today's step": the ratio the acceptance asks for
        runs.insert(0, dict(name=ISSUE_STEP_NAME, threads=2, flops=issue_runs[0]["flops"],
                            times=[x for r in issue_runs for x in r["times"]],
                            faults=[x for r in issue_runs for x in r["faults"]]))
    base = min(runs[0]["times"])
    ref_2t = min(next(r for r in runs if r["name"] == CONFIGS[0][0])["times"])
    rows = []
    for r in runs:
        sec = min(r["times"])  # best round (least disturbed by other processes)
        fp32, bf16 = peaks[r["threads"]]
        achieved = r["flops"] / sec
        rows.append({
            "config": r["name"], "s_per_step": sec / len(batches), "agent_tokens_per_s": tokens / sec,
            "speedup_vs_issue_step": base / sec if issue_runs else None,
            "speedup_vs_reference_2_threads": ref_2t / sec,
            "GFLOP_per_step": r["flops"] / len(batches) / 1e9, "achieved_GFLOP_s": achieved / 1e9,
            "frac_fp32_peak": achieved / fp32, "frac_bf16_peak": achieved / bf16,
            "minor_faults_per_step": float(np.median(r["faults"])),
        })
    meta = {"batches": n_batches, "rounds": rounds, "valid_agent_tokens": tokens,
            "map_tokens_reference": int(sum(b[0].map_mask.sum() for b in batches)),
            "map_tokens_fast": int(sum(b[1].map_mask.sum() for b in batches)),
            "padded_map_tokens_reference": int(sum(b[0].map_mask.numel() for b in batches)),
            "peaks_GFLOP_s": {f"{t} thread(s)": {"fp32": p[0] / 1e9, "bf16": p[1] / 1e9} for t, p in peaks.items()},
            "issue_step": "measured" if issue_runs else f"not measured: {issue.why}"}
    return rows, meta


def peak_memory(name: str, mallopt: bool = True) -> dict:
    """Peak RSS [MB] of a fresh process running 3 steps of configuration ``name`` (and its RSS before stepping)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, __file__, "--memory", name, "1" if mallopt else "0"], capture_output=True,
                         text=True, env=env, timeout=900)
    if out.returncode:
        raise RuntimeError(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def _memory_child(name: str, mallopt: bool) -> None:
    from r1sim_sumo._memory import peak_rss_mb, rss_mb

    if mallopt:
        keep_freed_memory()
    _, fast, precision, threads = next(c for c in CONFIGS if c[0] == name)
    torch.set_num_threads(threads)
    vocab, batches = real_batches(3)
    model = _model(vocab)
    step = _step_fn(model, torch.optim.AdamW(model.parameters(), lr=1e-4), fast, precision)
    before = rss_mb()
    for ref, fb, _ in batches:
        step(ref, fb)
    print(json.dumps({"config": name, "mallopt": mallopt, "rss_before_steps_MB": before, "peak_rss_MB": peak_rss_mb()}))


def loss_curve(steps: int) -> dict:
    """Reference fp32 (2 threads) vs fast fp32 (1 thread, the default) vs fast bf16 (1 thread) from one initialisation
    on the same batches."""
    vocab, batches = real_batches(steps)
    cfg = PretrainConfig(lr=2e-3, warmup_steps=max(1, steps // 10), max_steps=steps, min_lr_ratio=0.1)
    curves = {}
    for name, fast, precision, threads in (CONFIGS[0], CONFIGS[2], CONFIGS[4]):
        torch.set_num_threads(threads)
        model = _model(vocab)
        opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=0.05)
        step = _step_fn(model, opt, fast, precision)
        losses = []
        for s, (ref, fb, _) in enumerate(batches):
            torch.manual_seed(1000 + s)  # same dropout seed per step for both (masks differ: other shapes)
            for g in opt.param_groups:
                g["lr"] = lr_at(s, cfg)
            losses.append(step(ref, fb))
        curves[name] = losses
    return curves


def _plot(curves: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, ls in curves.items():
        ax.plot(np.arange(1, len(ls) + 1), ls, label=name)
    ax.set_xlabel("step (same batches, same initialisation)")
    ax.set_ylabel("training loss [nats, label-smoothed]")
    ax.set_title("Reference step vs fast path on real batches")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _target_note(rows: list[dict], meta: dict) -> str:
    """The issue's target, read against the issue-time step (its "today's step") where it could be measured."""
    if meta["issue_step"] != "measured":
        return (f"target: >= 4x the agent-tokens/s of the issue-time step ({ISSUE_STEP_REV[:7]}): {meta['issue_step']}; "
                "the rows give the ratio to the reference path only")
    parts = []
    for name in ("fast fp32, 1 thread", "fast fp32, 2 threads"):
        r = next((r for r in rows if r["config"] == name), None)
        if r:
            parts.append(f"{name} {r['speedup_vs_issue_step']:.2f}x")
    best = max(r["speedup_vs_issue_step"] for r in rows if r.get("speedup_vs_issue_step"))
    return (f"target: >= 4x the agent-tokens/s of the issue-time step ({ISSUE_STEP_NAME}, the same batches, run from a "
            f"git worktree of that revision in a child process, interleaved with the other rows) -> {', '.join(parts)}; "
            f"best {best:.2f}x ({'met' if best >= 4 else 'NOT met'}). The reference rows are the padded forward of "
            "today's code, which shares the faster layers, so they are not the issue's baseline.")


def run(quick: bool = False) -> dict:
    prev = torch.get_num_threads()
    try:
        rows, meta = throughput(n_batches=3 if quick else 4, rounds=1 if quick else 2)
        mem = [peak_memory(CONFIGS[0][0]), peak_memory(CONFIGS[2][0]), peak_memory(CONFIGS[2][0], mallopt=False)]
        for m in mem:
            rows.append({"config": f"{m['config']} (memory, {'mallopt' if m['mallopt'] else 'glibc default'})",
                         "rss_before_steps_MB": m["rss_before_steps_MB"], "peak_rss_MB": m["peak_rss_MB"]})
        curve_steps = 10 if quick else 24
        curves = loss_curve(curve_steps)
    finally:
        torch.set_num_threads(prev)
    REPORTS.mkdir(parents=True, exist_ok=True)
    (REPORTS / "training_loss_curve.json").write_text(json.dumps(curves, indent=1))
    _plot(curves, REPORTS / "training_loss_curve.png")
    (ref_name, ref_l), (fast_name, fast_l), (bf_name, bf_l) = curves.items()
    k = max(1, curve_steps // 4)
    notes = [
        f"{meta['batches']} real batches of 4 scenes ({meta['valid_agent_tokens']} valid agent-tokens), best of {meta['rounds']} "
        f"interleaved rounds; load average at the end {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs.",
        f"map tokens per step: reference {meta['map_tokens_reference'] / meta['batches']:.0f} real of "
        f"{meta['padded_map_tokens_reference'] / meta['batches']:.0f} padded; fast (reach crop) "
        f"{meta['map_tokens_fast'] / meta['batches']:.0f}.",
        f"dense matmul peaks in this process [GFLOP/s]: {json.dumps(meta['peaks_GFLOP_s'])}.",
        _target_note(rows, meta),
        f"loss curve ({curve_steps} steps, plot training_loss_curve.png): mean of the last {k} losses {ref_name} "
        f"{np.mean(ref_l[-k:]):.4f}, {fast_name} {np.mean(fast_l[-k:]):.4f}; mean |difference| over all steps "
        f"{np.mean(np.abs(np.array(ref_l) - np.array(fast_l))):.4f} (dropout masks differ between the paths); "
        f"{bf_name} {np.mean(bf_l[-k:]):.4f}, mean |difference| to the fast fp32 curve "
        f"{np.mean(np.abs(np.array(bf_l) - np.array(fast_l))):.4f} (same path, same dropout masks).",
    ]
    return {"title": "Pretraining step on real batches: reference vs fast path (CPU)", "rows": rows, "notes": notes}


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--memory":
        _memory_child(sys.argv[2], sys.argv[3] == "1")
    else:
        print(json.dumps(run("--quick" in sys.argv), indent=1))
