"""Offroad and position error of the rolling-matched *reference* (GT tokens rebuilt) on held-out SUMO test scenes, per network.

Run: `python scripts/diag_matched_reconstruction.py runs/vocab/vocab.safetensors` (needs the default dataset).
"""
import numpy as np, torch, sys
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.batch import collate, tokenize_scenario
from r1sim_sumo.tokens.matching import reconstruct_states
from r1sim_sumo.tokens.motion_vocab import MotionVocab
from r1sim_sumo.evaluate import rollouts_to_sim
from r1sim_sumo.metrics.realism import compute_features
torch.set_num_threads(1)
vocab = MotionVocab.load(sys.argv[1])
ds = ScenarioDataset("data/generated/default/test")
idx = np.random.default_rng(0).choice(len(ds), 80, replace=False)
res = {}
for i in idx:
    sc = ds[int(i)]
    if sc.metadata.get("source") != "sumo": continue
    scene = tokenize_scenario(sc, vocab); b = collate([scene]); ci = sc.current_index
    tok = b.agent_token[:, :, 2:]; tv = b.agent_token_valid[:, :, 2:].bool()
    xy10, yaw10 = reconstruct_states(b.pose_xy[:, :, 2], b.pose_yaw[:, :, 2], torch.where(tv, tok, 0), vocab, b.agent_type.long())
    v = b.pose_valid[:, :, 2:].bool()
    v10 = torch.cat([v[..., :1], v[..., 1:].repeat_interleave(5, -1)], -1)
    sim = rollouts_to_sim(xy10, yaw10, v10, scene.agent_index, sc)
    f = compute_features(sc, sim.x_m, sim.y_m, sim.yaw_rad, sim.valid)
    T = sim.x_m.shape[-1]; a = sc.agents
    both = sim.valid[0] & a.valid[:, ci+1:ci+1+T]
    err = np.hypot(sim.x_m[0]-a.x_m[:, ci+1:ci+1+T], sim.y_m[0]-a.y_m[:, ci+1:ci+1+T])[both]
    live = a.valid[:, ci]
    res.setdefault(sc.metadata["network"], []).append((f.offroad.any(-1)[0, live].mean(), err.mean(), err.max()))
for n, r in res.items():
    r = np.array(r); print(n, len(r), "offroad", r[:,0].mean().round(3), "err mean", r[:,1].mean().round(3), "max", r[:,2].max().round(2))
