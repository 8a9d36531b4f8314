"""Closed-loop rollout cost: 32 rollouts x all agents of a typical scene x 16 token steps (8 s), nano model.

Side by side in one run: all 32 rollouts batched into one policy step per token (the engine's default) vs the
same 32 rollouts run one at a time. Uses a held-out scene of the default dataset when it exists (the shipped
checkpoint when it exists), else a synthetic scene with 50 agents and an untrained nano model. Target: <= 2 s per
scenario on 2 CPU threads.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def _setup():
    from r1sim_sumo.model.checkpoint import Policy
    from r1sim_sumo.model.config import PolicyConfig
    from r1sim_sumo.model.policy import TrafficPolicy
    from r1sim_sumo.model.synthetic import synthetic_batch, synthetic_vocab
    from r1sim_sumo.tokens.motion_vocab import MotionVocab

    try:
        import r1sim_sumo
        from r1sim_sumo.scenario import ScenarioDataset
        from r1sim_sumo.tokens.batch import collate, tokenize_scenario

        policy = r1sim_sumo.load_policy()
        ds = ScenarioDataset(REPO / "data/generated/default/test")
        sc = next(ds[i] for i in range(len(ds) - 1, 0, -7) if ds[i].metadata.get("source") == "sumo" and 30 <= ds[i].agents.num_agents <= 60)
        return policy, collate([tokenize_scenario(sc, policy.vocab)]), f"{sc.metadata['network']} test scene, shipped checkpoint"
    except Exception:  # no dataset / checkpoint: synthetic stand-in
        tr = synthetic_vocab((2048, 512, 512))
        vocab = MotionVocab.from_traj({i: t.numpy() for i, t in enumerate(tr)})
        model = TrafficPolicy(PolicyConfig.preset("nano", vocab_sizes=vocab.sizes), [torch.as_tensor(vocab.traj[i]) for i in range(3)])
        b = synthetic_batch(tr, num_scenes=1, num_agents=50, num_map_tokens=2000)
        return Policy(model=model.eval(), vocab=vocab, config=model.config), b, "synthetic 50-agent scene, untrained nano"


def run(quick: bool = False) -> dict:
    from r1sim_sumo.rollout.engine import rollout
    from r1sim_sumo.rollout.samplers import parse_sampler

    torch.set_num_threads(2)
    policy, batch, what = _setup()
    A = int(batch.agent_mask.sum())
    G = 8 if quick else 32
    samp = parse_sampler("entropy:16,80")
    rollout(policy.model, policy.vocab, batch, 2, samp, generator=torch.Generator().manual_seed(0))  # warm-up
    reps = 1 if quick else 3
    t = []
    for r in range(reps):
        t0 = time.perf_counter()
        rollout(policy.model, policy.vocab, batch, G, samp, generator=torch.Generator().manual_seed(r))
        t.append(time.perf_counter() - t0)
    batched = min(t)
    t0 = time.perf_counter()
    for g in range(G):
        rollout(policy.model, policy.vocab, batch, 1, samp, generator=torch.Generator().manual_seed(g))
    sequential = time.perf_counter() - t0
    rows = [
        {"case": f"{G} rollouts batched", "agents": A, "seconds_per_scenario": batched, "agent_steps_per_s": G * A * 16 / batched},
        {"case": f"{G} rollouts one at a time", "agents": A, "seconds_per_scenario": sequential, "agent_steps_per_s": G * A * 16 / sequential},
    ]
    return {"title": "Closed-loop rollout (16 token steps = 8 s, nano, 2 threads)", "rows": rows,
            "notes": [f"scene: {what}", f"batched speed-up: {sequential / batched:.1f}x", "target: <= 2 s per scenario for 32 rollouts"]}


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick=True), indent=1))
