"""``r1sim ablate``: the structure of R1Sim's Tables II-IV on a held-out split, with plots.

Models (checkpoint folders; missing ones are fine-tuned from ``--il`` when ``--train-budget-iters N`` is given):
IL (pretrained), SFT (closed-loop SFT, CAT-K), GRPO-standard (advantage / std), GRPO-refined (advantage = r - mean,
reward SPR) and one GRPO-refined fine-tune per other reward design (OR, APR, AHR, SHR; ``reward.kind``).
Samplers: top-K 32 and entropy-guided (16, 80) by default. Every (model, sampler) is evaluated with
:func:`r1sim_sumo.evaluate.evaluate_policy` for every seed (mean ± std over seeds).

Outputs in ``--out``:

- ``ablation.md`` / ``ablation.json``: **Table III** (sampling x optimization: RMM, kinematic / interactive /
  map-based likelihoods, collision and offroad rates, mean ± std), **Table II** (Easy / Hard split: top and bottom
  ``--easy-hard-quantile`` of scenarios by the IL model's RMM under top-K 32, first seed; RMM and the difference
  to GRPO-refined + entropy-guided, "ours"), **Table IV** (reward designs, entropy-guided sampler);
- ``training_curves.png``: reward, collision rate and distance to the reference vs iteration from each fine-tune's
  ``log.csv``;
- ``entropy_before_after.png``: token-entropy distribution of IL vs GRPO-refined under the entropy-guided sampler,
  on all / Easy / Hard scenarios (per-scenario entropies from the rollouts, as the paper's entropy figure).

Full command (the lead's run; ~hours on 2 CPU cores)::

    r1sim ablate --data data/generated/default/test --il runs/pretrain_nano/final \\
        --train-config configs/grpo.yaml --train-budget-iters 200 --train-data data/generated/default/train \\
        --rollouts 32 --seeds 0 1 2 3 4 --max-scenarios 64 --out runs/ablate

Existing fine-tunes can be passed instead of trained: ``--sft DIR --grpo-std DIR --grpo DIR --reward-ckpt or=DIR ...``.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

HELP = "ablation tables (samplers x optimizations, Easy/Hard, reward designs) and training/entropy plots"

OPTIMIZATIONS = ("il", "sft", "grpo-std", "grpo")  # model keys; "grpo" = GRPO-refined with SPR
OPT_LABEL = {"il": "IL", "sft": "SFT", "grpo-std": "GRPO-standard", "grpo": "GRPO-refined"}
REWARDS = ("or", "apr", "ahr", "shr", "spr")
TRAIN = {"sft": ["method=sft"], "grpo-std": ["method=grpo-std"], "grpo": ["method=grpo", "reward.kind=spr"],
         **{f"reward-{k}": ["method=grpo", f"reward.kind={k}"] for k in ("or", "apr", "ahr", "shr")}}
METRICS = [("realism/rmm", "RMM"), ("bucket/kinematic", "kinematic L."), ("bucket/interactive", "interactive L."),
           ("bucket/map_based", "map-based L."), ("realism/collision_rate", "collision rate"),
           ("realism/offroad_rate", "offroad rate")]


def add_arguments(p) -> None:
    p.add_argument("--data", required=True, help="held-out dataset folder (e.g. data/generated/default/test)")
    p.add_argument("--il", default=None, help="pretrained (IL) checkpoint (default: the shipped policy)")
    p.add_argument("--sft", default=None, help="closed-loop SFT checkpoint")
    p.add_argument("--grpo-std", default=None, help="GRPO-standard checkpoint")
    p.add_argument("--grpo", default=None, help="GRPO-refined (SPR reward) checkpoint")
    p.add_argument("--reward-ckpt", nargs="*", default=[], metavar="KIND=DIR",
                   help="GRPO-refined checkpoints per reward design: or=DIR apr=DIR ahr=DIR shr=DIR")
    p.add_argument("--rewards", nargs="*", default=list(REWARDS), help=f"reward designs of Table IV (default {' '.join(REWARDS)})")
    p.add_argument("--train-budget-iters", type=int, default=None,
                   help="fine-tune every missing model from --il for this many iterations (else missing models are skipped)")
    p.add_argument("--train-config", default=None, help="GRPOConfig YAML of the fine-tunes (e.g. configs/grpo.yaml)")
    p.add_argument("--train-data", default=None, help="training dataset of the fine-tunes (default: the config's)")
    p.add_argument("--train-set", nargs="*", default=[], metavar="KEY=VALUE", help="extra GRPOConfig overrides for every fine-tune")
    p.add_argument("--samplers", nargs="+", default=["topk:32", "entropy:16,80"], help="last = entropy-guided ('ours'); topk:32 (else the first) = baseline defining Easy/Hard; "
                        "the paper's Table II: topk:5 topk:32 topk:64 entropy:16,80")
    p.add_argument("--rollouts", type=int, default=32)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--max-scenarios", type=int, default=None, help="evaluate on N evenly spaced scenarios")
    p.add_argument("--batch-scenes", type=int, default=2)
    p.add_argument("--easy-hard-quantile", type=float, default=0.2, help="Easy/Hard = top/bottom fraction by IL RMM (paper: 0.02)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default="runs/ablate")


def _train(key: str, args, out: Path) -> Path:
    """Fine-tune model ``key`` from the IL checkpoint with the small budget; returns its ``final`` folder."""
    from r1sim_sumo.config import load_config
    from r1sim_sumo.train.grpo import GRPOConfig, finetune

    run_dir = out / "train" / key
    sets = [*TRAIN[key], f"max_iters={args.train_budget_iters}", f"out_dir={run_dir}", *args.train_set]
    if args.il:
        sets.append(f"init_checkpoint={args.il}")
    if args.train_data:
        sets.append(f"train_data={args.train_data}")
    if (run_dir / "final" / "checkpoint.json").exists():
        return run_dir / "final"
    cfg = load_config(GRPOConfig, args.train_config, sets)
    return finetune(cfg, resume=(run_dir / "state").exists(), progress=False)


def resolve_models(args, out: Path) -> dict[str, str | None]:
    """Model key -> checkpoint (None = shipped default for IL); trains the missing ones when a budget is given."""
    given = {"il": args.il, "sft": args.sft, "grpo-std": args.grpo_std, "grpo": args.grpo}
    for item in args.reward_ckpt:
        kind, sep, path = item.partition("=")
        if not sep or kind not in REWARDS:
            raise SystemExit(f"r1sim ablate: --reward-ckpt '{item}': expected KIND=DIR with KIND in {REWARDS}")
        given["grpo" if kind == "spr" else f"reward-{kind}"] = path
    wanted = ["sft", "grpo-std", "grpo", *[f"reward-{k}" for k in args.rewards if k != "spr"]]
    models: dict[str, str | None] = {"il": given["il"]}
    for key in wanted:
        if given.get(key):
            models[key] = given[key]
        elif args.train_budget_iters:
            models[key] = str(_train(key, args, out))
    return models


def _fmt(s: dict, key: str) -> str:
    v, sd = s.get(key, math.nan), s.get(key + "/std")
    return f"{v:.4f}" + (f" (±{sd:.4f})" if sd is not None else "")


def table_ablation(summ: dict, samplers: list[str]) -> str:
    """Table III: one row per (sampler, optimization) evaluated."""
    lines = ["| sampling | optimization | " + " | ".join(m[1] for m in METRICS) + " |", "|---" * (len(METRICS) + 2) + "|"]
    for opt in OPTIMIZATIONS:
        for smp in samplers:
            s = summ.get((opt, smp))
            if s is not None:
                lines.append(f"| {smp} | {OPT_LABEL[opt]} | " + " | ".join(_fmt(s, k) for k, _ in METRICS) + " |")
    return "\n".join(lines)


def table_easy_hard(split_summ: dict, samplers: list[str], ours: tuple[str, str]) -> str:
    """Table II: RMM on Easy / Hard and the difference of ours (GRPO-refined + entropy-guided) to each row."""
    lines = ["| category | method | RMM Easy | ΔRMM Easy | RMM Hard | ΔRMM Hard |", "|---|---|---|---|---|---|"]
    rows = [("Sampling", ("il", s), f"{s} (IL)") for s in samplers]
    rows += [("Optimization", (o, samplers[-1]), f"{OPT_LABEL[o]} ({samplers[-1]})") for o in OPTIMIZATIONS]
    o_e, o_h = split_summ["Easy"].get(ours), split_summ["Hard"].get(ours)
    for cat, key, label in rows:
        e, h = split_summ["Easy"].get(key), split_summ["Hard"].get(key)
        if e is None:
            continue
        de = f"{o_e['realism/rmm'] - e['realism/rmm']:+.4f}" if o_e and key != ours else "-"
        dh = f"{o_h['realism/rmm'] - h['realism/rmm']:+.4f}" if o_h and key != ours else "-"
        lines.append(f"| {cat} | {label} | {e['realism/rmm']:.4f} | {de} | {h['realism/rmm']:.4f} | {dh} |")
    return "\n".join(lines)


def table_rewards(summ: dict, rewards: list[str], sampler: str) -> str:
    """Table IV: one row per reward design (GRPO-refined fine-tunes, entropy-guided sampler)."""
    cols = METRICS[:4]
    lines = ["| reward | " + " | ".join(c[1] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for k in rewards:
        s = summ.get(("grpo" if k == "spr" else f"reward-{k}", sampler))
        if s is not None:
            lines.append(f"| {k.upper()} | " + " | ".join(_fmt(s, c) for c, _ in cols) + " |")
    return "\n".join(lines)


def read_log(run_final: str | None) -> list[dict]:
    """Rows of the fine-tune's ``log.csv`` (the folder above its ``final`` checkpoint), [] when absent."""
    if not run_final:
        return []
    p = Path(run_final).parent / "log.csv"
    if not p.exists():
        return []
    with open(p) as f:
        return list(csv.DictReader(f))


def plot_training(models: dict, path: Path) -> list[str]:
    """Reward, collision rate and distance to the reference vs iteration of every fine-tune with a ``log.csv``
    (SFT logs no reward: only its distance ``sft_dist_m``); returns the runs plotted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(13, 3.5))
    plotted = []
    for key, ck in models.items():
        rows = read_log(ck)
        if not rows or "iter" not in rows[0]:  # no fine-tune log (e.g. the IL model's pretraining log counts steps)
            continue
        it = [int(r["iter"]) for r in rows]
        for a, field in zip(ax, ("reward", "collision_rate", "distance_m"), strict=True):
            col = field if rows[0].get(field) not in ("", None) else ("sft_dist_m" if field == "distance_m" else None)
            if col and rows[0].get(col) not in ("", None):
                a.plot(it, [float(r[col]) for r in rows], marker="o", label=key)
        plotted.append(key)
    for a, lab in zip(ax, ("mean token reward", "collision rate (token steps)", "distance to reference [m]"), strict=True):
        a.set_xlabel("iteration")
        a.set_ylabel(lab)
        if a.lines:
            a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return plotted


def scene_entropies(policy, scenarios, sampler: str, num_rollouts: int, seed: int, batch_scenes: int) -> list[list[float]]:
    """Per scenario, the token entropies [nats] of its policy-driven agents over its rollouts (one list per scene)."""
    import torch

    from r1sim_sumo.rollout.engine import rollout
    from r1sim_sumo.rollout.samplers import parse_sampler
    from r1sim_sumo.tokens.batch import collate, tokenize_scenario

    gen, out = torch.Generator().manual_seed(seed), []
    for lo in range(0, len(scenarios), batch_scenes):
        scs = [scenarios[i] for i in range(lo, min(len(scenarios), lo + batch_scenes))]
        r = rollout(policy.model.eval(), policy.vocab, collate([tokenize_scenario(s, policy.vocab) for s in scs]),
                    num_rollouts, parse_sampler(sampler), generator=gen)
        act = r.sim_mask[None, :, :, None] & (r.token >= 0)  # [G, B, A, F]
        for b in range(len(scs)):
            out.append(r.entropy[:, b][act[:, b]].tolist())
    return out


def plot_entropy(before: list[list[float]], after: list[list[float]], easy: set[int], hard: set[int], path: Path) -> dict:
    """Entropy histograms IL vs GRPO-refined on all / Easy / Hard scenes; returns the mean entropies."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(1, 3, figsize=(12, 3.3), sharey=True)
    means = {}
    for a, (name, sub) in zip(ax, (("all", None), ("Easy", easy), ("Hard", hard)), strict=True):
        for label, per in (("IL", before), ("GRPO-refined", after)):
            vals = np.concatenate([np.asarray(v, float) for i, v in enumerate(per) if sub is None or i in sub] or [np.zeros(0)])
            means[f"{label}/{name}"] = float(vals.mean()) if vals.size else math.nan
            if vals.size:
                a.hist(vals, bins=40, alpha=0.5, density=True, label=f"{label} (mean {vals.mean():.2f})")
        a.set_title(f"{name} scenes")
        a.set_xlabel("token entropy H_t [nats]")
        a.legend(fontsize=7)
    ax[0].set_ylabel("density")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return means


def run_ablation(args) -> Path:
    """Evaluate every (model, sampler) for every seed, write the tables and plots; returns the output folder."""
    import torch

    import r1sim_sumo
    from r1sim_sumo.commands.evaluate import _subset
    from r1sim_sumo.evaluate import easy_hard_split, evaluate_policy, summarize_runs
    from r1sim_sumo.scenario import ScenarioDataset

    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scenarios = _subset(ScenarioDataset(args.data), args.max_scenarios)
    models = resolve_models(args, out)
    samplers = list(args.samplers)
    topk = "topk:32" if "topk:32" in samplers else samplers[0]  # the paper's baseline sampler (Easy/Hard reference)
    ent = samplers[-1]
    runs, policies = {}, {}
    for key, ck in models.items():
        policies[key] = r1sim_sumo.load_policy(ck)
        # optimizations under every sampler; reward designs under the entropy-guided one only
        for smp in (samplers if key in OPTIMIZATIONS else [ent]):
            runs[(key, smp)] = [evaluate_policy(policies[key], scenarios, smp, args.rollouts, seed, args.batch_scenes,
                                                progress=False, name=f"{key} {smp}") for seed in args.seeds]
    summ = {k: summarize_runs(v) for k, v in runs.items()}
    easy, hard = easy_hard_split(runs[("il", topk)][0], args.easy_hard_quantile)
    split = {lab: {k: summarize_runs(v, sub) for k, v in runs.items()} for lab, sub in (("Easy", easy), ("Hard", hard))}
    ours = ("grpo", ent) if ("grpo", ent) in runs else ("il", ent)
    payload = {"models": models, "samplers": samplers, "seeds": args.seeds, "num_scenarios": len(scenarios),
               "summary": {f"{k[0]}|{k[1]}": v for k, v in summ.items()},
               "easy_hard": {lab: {f"{k[0]}|{k[1]}": v for k, v in d.items()} for lab, d in split.items()},
               "easy": sorted(easy), "hard": sorted(hard), "entropy_means": {}}
    (out / "ablation.json").write_text(json.dumps(payload, indent=1, default=float))  # the evaluations, before any plot
    md = [
        "# Ablation (structure of R1Sim Tables II-IV)", "",
        f"Data: `{args.data}` ({len(scenarios)} scenarios); rollouts {args.rollouts}; seeds {args.seeds}; "
        f"models: " + ", ".join(f"{k} = `{v or 'shipped default'}`" for k, v in models.items()) + ".", "",
        "## Table III: sampling x optimization (mean (± std over seeds))", "", table_ablation(summ, samplers), "",
        f"## Table II: Easy / Hard (top / bottom {args.easy_hard_quantile:g} by IL RMM under {topk}; "
        f"{len(easy)} / {len(hard)} scenarios; Δ = {OPT_LABEL[ours[0]]} + {ours[1]} minus the row)", "",
        table_easy_hard(split, samplers, ours), "",
        f"## Table IV: reward designs (GRPO-refined, {ent})", "", table_rewards(summ, list(args.rewards), ent), "",
    ]
    curves = plot_training(models, out / "training_curves.png")
    md += ["## Fine-tuning curves", "", f"Runs with a log.csv: {', '.join(curves) or 'none'}.", "",
           "![reward and collision rate vs iteration](training_curves.png)", ""]
    ent_means = {}
    if "grpo" in policies:
        before = scene_entropies(policies["il"], scenarios, ent, args.rollouts, args.seeds[0], args.batch_scenes)
        after = scene_entropies(policies["grpo"], scenarios, ent, args.rollouts, args.seeds[0], args.batch_scenes)
        ent_means = plot_entropy(before, after, easy, hard, out / "entropy_before_after.png")
        md += ["## Token entropy before / after GRPO", "",
               "| scenes | IL | GRPO-refined |", "|---|---|---|"]
        md += [f"| {s} | {ent_means[f'IL/{s}']:.3f} | {ent_means[f'GRPO-refined/{s}']:.3f} |" for s in ("all", "Easy", "Hard")]
        md += ["", "![entropy before/after](entropy_before_after.png)", ""]
    (out / "ablation.md").write_text("\n".join(md))
    payload["entropy_means"] = ent_means
    (out / "ablation.json").write_text(json.dumps(payload, indent=1, default=float))
    return out


def run(args) -> int:
    out = run_ablation(args)
    print(f"[ablate] tables and plots written to {out}/ablation.md")
    return 0
