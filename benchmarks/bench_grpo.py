"""GRPO iteration throughput: scenes x rollouts per second of one fine-tuning iteration, measured side by side.

Rows (same policy, same synthetic scenes, same run): the in-model GRPO iteration (rollout + rewards + ``ppo_epochs``
x ``num_minibatches`` teacher-forced updates), its rollout phase alone, the closed-loop SFT baseline iteration, and,
when SUMO is installed, the SUMO-in-the-loop rollout source (:mod:`r1sim_sumo.train.sumo_rollouts`) on a bundled
network. Policy: the ``nano`` preset with the default vocabulary sizes (2048 / 512 / 512) and random weights (speed
does not depend on the weights). Scenes: :func:`r1sim_sumo.model.synthetic.synthetic_batch`.

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
        from r1sim_sumo.train.sumo_rollouts import benchmark_sumo_source
    except ImportError:
        notes.append("SUMO-in-the-loop source not available")
    else:
        try:
            row = benchmark_sumo_source(model, vocab, num_rollouts=min(G, 4) if quick else 8, num_steps=F)
            rows.append(row)
        except Exception as exc:  # SUMO missing or failing must not hide the in-model rows
            notes.append(f"SUMO-in-the-loop row skipped: {type(exc).__name__}: {exc}")
    ref = rows[0]["scene_rollouts_per_s"]
    for r in rows:
        r["vs_in_model_grpo"] = r["scene_rollouts_per_s"] / ref
    return {"title": "GRPO fine-tuning iteration throughput (scene x rollouts per second)", "rows": rows, "notes": notes}


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick=True), indent=2))
