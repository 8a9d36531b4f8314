"""Scaling out: 1 vs 2 workers (process backend) for SUMO reference runs and for closed-loop evaluation, the
learner's cost per training step, and a written estimate for 64 workers built from these measurements.

Run alone: ``python benchmarks/run.py --only scaling [--quick]``.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

EVAL_DATA = Path(__file__).resolve().parent.parent / "data" / "generated" / "default" / "test"


def _gen_jobs(quick: bool):
    from r1sim_sumo.data.sumo_reference import SumoGenConfig

    dur, warm, n = (60.0, 10.0, 4) if quick else (180.0, 30.0, 4)
    nets = ["motorway_merge", "lane_drop"]
    return [SumoGenConfig(network=nets[i % 2], seed=i, duration_s=dur, warmup_s=warm) for i in range(n)]


def _generation_row(jobs, workers: int) -> dict:
    from r1sim_sumo.data.dataset import execute_jobs

    with tempfile.TemporaryDirectory(prefix="bench_scaling_") as tmp:
        t0 = time.perf_counter()
        res = execute_jobs(jobs, Path(tmp), workers=workers, progress=False, backend="process")
        wall = time.perf_counter() - t0
    sim_s = sum(j.sim_seconds for j in jobs)
    return {"case": f"SUMO reference runs, {workers} worker(s)", "tasks": len(jobs), "wall_s": wall,
            "sim_s_per_wall_s": sim_s / wall, "vehicle_states_per_s": sum(r.vehicle_states for r in res) / wall,
            "per_task_s": sum(r.wall_s for r in res) / len(res)}


def _scenarios(quick: bool, tmp: Path) -> tuple[list, str]:
    """Held-out SUMO test scenes when the default dataset is built, else a short SUMO run generated here."""
    import numpy as np

    from r1sim_sumo.scenario import ScenarioDataset

    n = 4 if quick else 8
    if (EVAL_DATA / "manifest.json").exists():
        ds, src = ScenarioDataset(EVAL_DATA), str(EVAL_DATA)
    else:
        from r1sim_sumo.data.dataset import generate_sumo_dataset
        from r1sim_sumo.data.sumo_reference import SumoGenConfig

        cfgs = [SumoGenConfig(network="motorway_merge", seed=0, duration_s=30.0, warmup_s=20.0, stride_steps=5)]
        ds, src = ScenarioDataset(generate_sumo_dataset(cfgs, tmp / "scenes", workers=1, progress=False)), "generated"
    idx = np.linspace(0, len(ds) - 1, min(n, len(ds))).round().astype(int)
    return [ds[int(i)] for i in idx], src


def _eval_row(policy, scs, rollouts: int, workers: int | None) -> tuple[dict, object]:
    from r1sim_sumo.evaluate import evaluate_policy
    from r1sim_sumo.workers import make_pool

    t0 = time.perf_counter()
    if workers is None:
        res = evaluate_policy(policy, scs, "topk:5", rollouts, seed=0, batch_scenes=1, progress=False)
        case = "evaluation, in this process (1 thread)"
    else:
        with make_pool("process", workers, threads_per_worker=1) as pool:
            res = evaluate_policy(policy, scs, "topk:5", rollouts, seed=0, batch_scenes=1, progress=False, pool=pool,
                                  worker_threads=1)
        case = f"evaluation, {workers} worker process(es)"
    wall = time.perf_counter() - t0
    return {"case": case, "tasks": len(scs), "wall_s": wall, "scene_rollouts_per_s": len(scs) * rollouts / wall}, res


def _learner_row(policy, scs, batch: int = 4, reps: int = 3) -> dict:
    """One teacher-forced forward + backward + AdamW step of the policy on ``batch`` scenes (1 thread)."""
    import torch

    from r1sim_sumo.tokens.batch import collate, tokenize_scenario

    model = policy.model.train()
    scenes = [tokenize_scenario(sc, policy.vocab) for sc in scs[:batch]]
    b = collate(scenes)
    opt = torch.optim.AdamW(model.parameters(), lr=0.0)  # lr 0: timing only, the shipped weights stay as they are
    times = []
    for _ in range(reps + 1):
        t0 = time.perf_counter()
        loss, _ = model.loss(b, model(b))
        opt.zero_grad()
        loss.backward()
        opt.step()
        times.append(time.perf_counter() - t0)
    model.eval()
    step = sorted(times[1:])[len(times[1:]) // 2]  # median, first (warm-up) call dropped
    return {"case": f"learner step (fwd+bwd+AdamW), {len(scenes)} scenes, 1 thread", "tasks": len(scenes),
            "wall_s": step, "per_task_s": step / len(scenes)}


def run(quick: bool) -> dict:
    import os

    import torch

    import r1sim_sumo

    torch.set_num_threads(1)
    load_before = os.getloadavg()[0]
    jobs = _gen_jobs(quick)
    g1, g2 = _generation_row(jobs, 1), _generation_row(jobs, 2)
    g2["speedup_vs_1_worker"], g1["speedup_vs_1_worker"] = g1["wall_s"] / g2["wall_s"], 1.0
    policy = r1sim_sumo.load_policy()
    rollouts = 8 if quick else 16
    with tempfile.TemporaryDirectory(prefix="bench_scaling_scenes_") as tmp:
        scs, src = _scenarios(quick, Path(tmp))
    e0, ref = _eval_row(policy, scs, rollouts, None)
    e1, _ = _eval_row(policy, scs, rollouts, 1)
    e2, res2 = _eval_row(policy, scs, rollouts, 2)
    for r in (e0, e1, e2):
        r["speedup_vs_1_worker"] = e1["wall_s"] / r["wall_s"]
    same = [a["realism/rmm"] for a in ref.rows] == [b["realism/rmm"] for b in res2.rows]
    learner = _learner_row(policy, scs)
    load_after = os.getloadavg()[0]

    # ---- 64-worker estimate from the measured per-worker rates (see notes for the assumptions)
    per_worker_rollout_s = e0["wall_s"] / (len(scs) * rollouts)  # one scene-rollout of 8 s, one core
    per_worker_sumo = g1["sim_s_per_wall_s"]  # simulated s per wall s, one SUMO per core
    learner_per_scene_s = learner["per_task_s"]
    group = 32  # GRPO rollouts per scene (paper)
    scenes_per_iter = 64
    rollout_time_64 = scenes_per_iter * group * per_worker_rollout_s / 64
    learner_time = scenes_per_iter * group * learner_per_scene_s  # the update re-scores every rollout once
    estimate = [
        f"per worker (1 core, measured here): {1 / per_worker_rollout_s:.2f} scene-rollouts/s (8 s horizon, "
        f"{sum(sc.agents.num_agents for sc in scs) / len(scs):.0f} agents/scene), {per_worker_sumo:.0f} simulated s/s of SUMO "
        "reference generation",
        f"64 workers, ideal: {64 / per_worker_rollout_s:.0f} scene-rollouts/s and {64 * per_worker_sumo:.0f} SUMO "
        "simulated s/s; the measured 2-worker efficiency on this 2-core shared machine is "
        f"{e2['speedup_vs_1_worker'] / 2:.0%} (evaluation) and {g2['speedup_vs_1_worker'] / 2:.0%} (generation)",
        f"GRPO iteration of {scenes_per_iter} scenes x {group} rollouts: the rollouts take {rollout_time_64:.1f} s on "
        f"64 workers; re-scoring them with gradients (fwd+bwd, {learner_per_scene_s * 1000:.0f} ms per scene-rollout "
        f"measured on one contended core) takes {learner_time:.0f} s on one learner process, i.e. the learner costs "
        f"{learner_time / max(rollout_time_64 * 64, 1e-9):.1f}x one worker's rollout time per sample: keeping 64 rollout "
        f"workers busy needs ~{learner_time / max(rollout_time_64, 1e-9):.0f} learner cores (torchrun/DDP ranks) or GPUs, "
        "or fewer gradient samples per rollout (e.g. sub-sampling time steps)",
        "assumptions: one core per worker and no oversubscription; per-task start-up (process spawn + torch "
        "import, ~2-4 s here) amortised over long tasks; policy weights (4.7 MB for nano) sent once per worker "
        "per iteration through Ray's object store (64 x 4.7 MB = 0.3 GB per iteration, < 0.5 s on 10 Gb/s); "
        "results returned are small (metric rows / token sequences)",
    ]
    return {
        "title": "Scaling out: 1 vs 2 workers (process backend) and a 64-worker estimate",
        "rows": [g1, g2, e0, e1, e2, learner],
        "notes": [
            f"SUMO jobs: {[(j.network, j.seed, j.duration_s) for j in jobs]}, warm-up {jobs[0].warmup_s} s, one "
            "spawned process per worker; wall includes process start and shard writing",
            f"evaluation: shipped policy, {len(scs)} scenes from {src}, {rollouts} rollouts, top-K 5, one scene per "
            "task, 1 torch thread per worker; worker rows include spawning workers and importing torch",
            f"sharded evaluation equals the in-process run (same per-scene RMM): {same}",
            f"the machine has {os.cpu_count()} cores shared with other jobs (1-min load average {load_before:.1f} at the "
            f"start, {load_after:.1f} at the end): a second worker only helps when a core is idle, so compare rows "
            "of this run only and read the speedups as lower bounds",
            *estimate,
        ],
    }
