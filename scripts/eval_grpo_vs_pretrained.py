"""GRPO checkpoint vs the pretrained one on held-out SUMO test scenes (8 scenes, 16 rollouts, entropy:16,80, 5 seeds).

Needs the default dataset (`r1sim dataset build --out data/generated/default`). Run: `python scripts/eval_grpo_vs_pretrained.py`.
"""
import json, numpy as np, torch, r1sim_sumo
torch.set_num_threads(2)
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.evaluate import evaluate_policy, summarize_runs
ds = ScenarioDataset("data/generated/default/test")
idx = np.random.default_rng(1).choice(len(ds), 80, replace=False)
scs = [s for s in (ds[int(i)] for i in idx) if s.metadata.get("source") == "sumo"][:8]
out = {}
for name, ck in [("r1sim-nano (pretrained)", None), ("r1sim-grpo", "r1sim-grpo")]:
    pol = r1sim_sumo.load_policy(ck)
    for samp in ["entropy:16,80"]:
        runs = [evaluate_policy(pol, scs, samp, 16, seed, batch_scenes=2, progress=False) for seed in range(5)]
        s = summarize_runs(runs)
        out[f"{name} / {samp}"] = s
        keys = ["realism/rmm", "realism/collision_rate", "realism/offroad_rate"]
        print(name, samp, {k.split("/")[1]: f"{s[k]:.4f} +- {s[k + '/std']:.4f}" for k in keys}, flush=True)
json.dump({"scenes": [str(s.metadata) for s in scs], "results": out}, open("eval_grpo_vs_pretrained.json", "w"), indent=1, default=str)
