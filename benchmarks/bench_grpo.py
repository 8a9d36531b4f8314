"""GRPO iteration throughput: scenes x rollouts per second of one fine-tuning iteration, measured side by side.

Rows (same policy, same synthetic scenes, same run): the in-model GRPO iteration (rollout + rewards + ``ppo_epochs``
x ``num_minibatches`` teacher-forced updates), its rollout phase alone, the closed-loop SFT baseline iteration, and,
when SUMO is installed, the SUMO-in-the-loop rollout source (:mod:`r1sim_sumo.train.sumo_inloop`) on a bundled
network. Policy: the ``nano`` preset with the default vocabulary sizes (2048 / 512 / 512) and random weights (speed
does not depend on the weights). Scenes: :func:`r1sim_sumo.model.synthetic.synthetic_batch`.

In-model vs SUMO-in-the-loop (:mod:`r1sim_sumo.train.sumo_inloop`) on the *same* scenes: a short ``motorway_merge``
run generated with state files into a temporary folder; both sources run a full GRPO iteration (rollouts + rewards +
updates) with the same learner settings; the SUMO source uses 2 worker processes (one libsumo each) and is timed
after a warm-up iteration (process start, policy load).

Run: ``python benchmarks/run.py --only grpo [--quick]``.
"""

from __future__ import annotations

import copy
import time

import torch


def _setup(num_agents: int, num_scenes: int):
    from r1sim_sumo.model.config import PolicyConfig
    from r1sim_sumo.model.policy import TrafficPolicy
    from r1sim_sumo.model.synthetic import synthetic_batch, synthetic_vocab
    from r1sim_sumo.tokens.motion_vocab import MotionVocab

    torch.manual_seed(0)
    tr = synthetic_vocab((2048, 512, 512))
    vocab = MotionVocab.from_traj({i: t.numpy() for i, t in enumerate(tr)})
    model = TrafficPolicy(PolicyConfig.preset("nano", vocab_sizes=vocab.sizes), [torch.as_tensor(vocab.traj[i]) for i in range(3)]).eval()
    batch = synthetic_batch(tr, num_scenes=num_scenes, num_agents=num_agents, num_map_tokens=400, seed=1)
    return vocab, model, batch


def run(quick: bool = False) -> dict:
    from r1sim_sumo.train.grpo import GRPOConfig, GRPOLearner

    G, A, B, F, reps = (8, 16, 1, 4, 1) if quick else (32, 32, 2, 16, 2)
    vocab, model, batch = _setup(A, B)
    rows = []
    base = dict(num_rollouts=G, batch_scenes=B, num_steps=F, sampler="entropy:16,80", ppo_epochs=2, num_minibatches=4)
    for method in ("grpo", "sft"):
        learner = GRPOLearner(copy.deepcopy(model), copy.deepcopy(model), vocab, GRPOConfig(method=method, **base))
        learner.iteration(batch, torch.Generator().manual_seed(0))  # warm-up
        ts, st = [], {}
        for r in range(reps):
            t0 = time.perf_counter()
            st = learner.iteration(batch, torch.Generator().manual_seed(r + 1))
            ts.append(time.perf_counter() - t0)
        dt = sum(ts) / len(ts)
        n = B * (G if method == "grpo" else 1)
        rows.append({"source": f"in-model {method}", "rollouts_per_iter": n, "iter_s": dt, "scene_rollouts_per_s": n / dt,
                     "rollout_s": st.get("rollout_s", 0.0), "update_s": st.get("update_s", 0.0)})
    rows.append({"source": "in-model grpo: rollout phase only", "rollouts_per_iter": B * G, "iter_s": rows[0]["rollout_s"],
                 "scene_rollouts_per_s": B * G / max(rows[0]["rollout_s"], 1e-9)})
    notes = [f"G={G} rollouts x B={B} scenes, A={A} agents, {F} token steps (0.5 s each), nano policy, "
             f"torch threads {torch.get_num_threads()}; update = 2 epochs x 4 minibatches of teacher-forced forward+backward "
             "plus one reference forward."]
    try:
        rows += benchmark_sumo_source(model, vocab, num_rollouts=4 if quick else 8, num_steps=F, num_scenes=1 if quick else 2)
    except Exception as exc:  # SUMO missing or failing must not hide the in-model rows
        notes.append(f"SUMO-in-the-loop rows skipped: {type(exc).__name__}: {exc}")
    else:
        notes.append("SUMO scenes: motorway_merge windows (real agent counts, see rows); in-model and SUMO rows on the same "
                     "scenes share G, F and the learner settings; 'vs_in_model_same_scenes' compares those two.")
    ref = rows[0]["scene_rollouts_per_s"]
    for r in rows:
        r["vs_in_model_grpo"] = r["scene_rollouts_per_s"] / ref
    return {"title": "GRPO fine-tuning iteration throughput (scene x rollouts per second)", "rows": rows, "notes": notes}


def benchmark_sumo_source(model, vocab, num_rollouts: int = 8, num_steps: int = 16, num_scenes: int = 2,
                          workers: int = 2, reps: int = 1) -> list[dict]:
    """GRPO iteration throughput, in-model vs SUMO-in-the-loop, on the same freshly generated SUMO scenes."""
    import tempfile
    from pathlib import Path

    from r1sim_sumo.data.sumo_reference import SumoGenConfig, generate_sumo_scenarios
    from r1sim_sumo.model.checkpoint import save_checkpoint
    from r1sim_sumo.scenario import ScenarioDataset, write_dataset
    from r1sim_sumo.tokens.batch import collate, tokenize_scenario
    from r1sim_sumo.train.grpo import GRPOConfig, GRPOLearner
    from r1sim_sumo.train.sumo_inloop import PolicyRef, SumoRolloutSource

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_grpo_sumo_") as tmp:
        root = Path(tmp) / "data"
        cfg_gen = SumoGenConfig(network="motorway_merge", seed=0, duration_s=9.1 + 2.5 * num_scenes, warmup_s=60.0,
                                stride_steps=25, save_states=True)
        write_dataset(root, generate_sumo_scenarios(cfg_gen, state_root=root))
        ds = ScenarioDataset(root)
        idx = list(range(min(num_scenes, len(ds))))
        scenes = [tokenize_scenario(ds[i], vocab) for i in idx]
        batch = collate(scenes)
        ck = save_checkpoint(Path(tmp) / "policy", model, vocab)
        cfg = GRPOConfig(num_rollouts=num_rollouts, batch_scenes=len(idx), num_steps=num_steps, sampler="entropy:16,80",
                         ppo_epochs=2, num_minibatches=4)
        A = int(batch.agent_mask.sum(1).float().mean())
        n = len(idx) * num_rollouts
        learner = GRPOLearner(copy.deepcopy(model), copy.deepcopy(model), vocab, cfg)
        learner.iteration(batch, torch.Generator().manual_seed(0))  # warm-up
        ts, st = [], {}
        for r in range(reps):
            t0 = time.perf_counter()
            st = learner.iteration(batch, torch.Generator().manual_seed(r + 1))
            ts.append(time.perf_counter() - t0)
        dt_model = sum(ts) / len(ts)
        rows.append({"source": f"in-model grpo, SUMO scenes (A~{A})", "rollouts_per_iter": n, "iter_s": dt_model,
                     "scene_rollouts_per_s": n / dt_model, "rollout_s": st["rollout_s"], "update_s": st["update_s"],
                     "collision_rate": st["collision_rate"]})
        learner = GRPOLearner(copy.deepcopy(model), copy.deepcopy(model), vocab, cfg)
        with SumoRolloutSource(ds, workers=workers) as src:
            ref = PolicyRef(str(ck))
            src.rollout(ref, idx, scenes, num_rollouts, cfg.sampler, torch.Generator().manual_seed(0), num_steps)  # warm-up
            ts, tr = [], []
            for r in range(reps):
                t0 = time.perf_counter()
                res, extra = src.rollout(ref, idx, scenes, num_rollouts, cfg.sampler, torch.Generator().manual_seed(r + 1),
                                         num_steps)
                tr.append(time.perf_counter() - t0)
                st = learner.grpo_iteration(batch, torch.Generator().manual_seed(r + 1), result=res, extra_collision=extra)
                ts.append(time.perf_counter() - t0)
        dt = sum(ts) / len(ts)
        rows.append({"source": f"SUMO-in-the-loop grpo, {workers} workers (A~{A})", "rollouts_per_iter": n, "iter_s": dt,
                     "scene_rollouts_per_s": n / dt, "rollout_s": sum(tr) / len(tr), "update_s": st["update_s"],
                     "collision_rate": st["collision_rate"], "vs_in_model_same_scenes": dt_model / dt,
                     "rollout_phase_vs_in_model": rows[-1]["rollout_s"] / max(sum(tr) / len(tr), 1e-9)})
    return rows


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick=True), indent=2))
