"""Short GRPO fine-tunes with the full-softmax vs the truncated (top-K_t) ratio, scored on the same scenes.

For each ``logp_kind`` and seed: fine-tune the policy for ``--iters`` iterations on ``--data`` (entropy-guided
sampler, the paper's default), then roll out ``--eval-rollouts`` futures of every scene with a fixed generator and
report the GRPO objective's ingredients: mean token reward, collision rate, distance to the log [m], and the last
iterations' KL and clip fraction. The initial policy is scored the same way.

    nice -n 19 python scripts/compare_grpo_logp_kind.py --data /path/to/tiny --iters 6 --out docs/grpo_logp_kind.json
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
import time
from pathlib import Path

import torch

from r1sim_sumo import load_policy
from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.batch import TokenizedDataset, collate
from r1sim_sumo.train.grpo import GRPOConfig, TensorSource, finetune
from r1sim_sumo.train.rewards import RewardConfig, compute_rewards


class _Pol:
    def __init__(self, model, vocab):
        self.model, self.vocab = model, vocab


def score(model, vocab, batch, rollouts: int, sampler: str, num_steps: int, seed: int) -> dict:
    """Mean token reward (SPR), collision rate per agent-step and distance to the log [m] of fresh rollouts."""
    with torch.no_grad():
        res = rollout(model, vocab, batch, rollouts, parse_sampler(sampler), generator=torch.Generator().manual_seed(seed),
                      num_steps=num_steps)
        rw = compute_rewards(res, batch, RewardConfig())
    m = rw.mask
    n = m.sum().clamp(min=1)
    return {"reward": float(rw.reward[m].sum() / n), "collision_rate": float(rw.collision[m].float().sum() / n),
            "distance_m": float(rw.distance_m[m].sum() / n)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--checkpoint", default=None, help="policy to fine-tune (default: the shipped one)")
    ap.add_argument("--iters", type=int, default=6)
    ap.add_argument("--scenes", type=int, default=6, help="first N scenes of --data (train and score on them)")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--num-rollouts", type=int, default=8)
    ap.add_argument("--num-steps", type=int, default=8)
    ap.add_argument("--eval-rollouts", type=int, default=16)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(2)
    pol = load_policy(args.checkpoint)
    with tempfile.TemporaryDirectory() as tmp:
        ds = TokenizedDataset(ScenarioDataset(args.data), pol.vocab, cache_dir=Path(tmp) / "cache")
        batch = collate([ds[i] for i in range(min(args.scenes, len(ds)))])
        sampler = "entropy:16,80"
        print("scoring the initial policy", flush=True)
        out = {"command": "scripts/compare_grpo_logp_kind.py " + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items()),
               "scenes": int(batch.agent_mask.shape[0]), "initial": score(pol.model.float(), pol.vocab, batch, args.eval_rollouts, sampler,
                                                   args.num_steps, 123), "runs": []}
        for seed in [int(s) for s in args.seeds.split(",")]:
            for kind in ("full", "truncated"):
                cfg = GRPOConfig(method="grpo", logp_kind=kind, num_rollouts=args.num_rollouts, batch_scenes=2,
                                 sampler=sampler, num_steps=args.num_steps, lr=args.lr, max_iters=args.iters, seed=seed,
                                 ckpt_every=10_000, out_dir=str(Path(tmp) / f"{kind}_{seed}"), threads=2)
                t0 = time.time()
                final = finetune(cfg, progress=False, policy=pol, source=TensorSource(batch))
                tuned = load_policy(str(final))
                rows = list(csv.DictReader(open(Path(cfg.out_dir) / "log.csv")))
                last = rows[-max(1, len(rows) // 3):]
                r = {"logp_kind": kind, "seed": seed, "wall_s": time.time() - t0,
                     "train_kl_last": sum(float(x["kl"]) for x in last) / len(last),
                     "train_clip_frac_last": sum(float(x["clip_frac"]) for x in last) / len(last),
                     **score(tuned.model.float(), tuned.vocab, batch, args.eval_rollouts, sampler, args.num_steps, 123)}
                print(json.dumps(r), flush=True)
                out["runs"].append(r)
    for kind in ("full", "truncated"):
        rs = [r for r in out["runs"] if r["logp_kind"] == kind]
        out[f"mean_{kind}"] = {k: sum(r[k] for r in rs) / len(rs) for k in ("reward", "collision_rate", "distance_m",
                                                                           "train_kl_last", "train_clip_frac_last")}
    print(json.dumps({k: v for k, v in out.items() if k != "runs"}, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
