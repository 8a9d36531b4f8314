"""Model card of a checkpoint: held-out next-token metrics vs baselines, and closed-loop safety.

``python -m r1sim_sumo.train.model_card CHECKPOINT --train DIR --heldout DIR --closed-loop DIR`` computes

* next-token top-1 accuracy and NLL [nats] on the held-out split's future tokens for the policy, the unigram
  baseline and the constant-velocity token baseline (both fitted on the training split);
* closed-loop 8 s rollouts on held-out SUMO scenarios: collision rate and offroad rate of the policy vs the
  constant-velocity baseline, overall and per network;

and writes ``MODEL_CARD.md`` + ``model_card.json`` into the checkpoint folder.
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.evaluate import evaluate_baselines, evaluate_policy
from r1sim_sumo.model.policy import token_nll_and_correct
from r1sim_sumo.rollout.kernel import DECODINGS
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.batch import collate, tokenize_scenario
from r1sim_sumo.train.baselines import ConstantVelocityBaseline, UnigramBaseline


def _subset(ds, n: int | None, seed: int = 0):
    idx = np.arange(len(ds)) if n is None or n >= len(ds) else np.sort(np.random.default_rng(seed).choice(len(ds), n, replace=False))
    return [ds[int(i)] for i in idx]


def token_metrics(policy, train_dir: str, heldout_dir: str, max_train: int = 2000, max_heldout: int = 600, batch: int = 8) -> dict:
    vocab = policy.vocab
    train = [tokenize_scenario(s, vocab) for s in _subset(ScenarioDataset(train_dir), max_train)]
    held = [tokenize_scenario(s, vocab) for s in _subset(ScenarioDataset(heldout_dir), max_heldout)]
    uni = UnigramBaseline(vocab).fit(train).score(held)
    cv = ConstantVelocityBaseline(vocab).fit(train).score(held)
    nll, ok, n = 0.0, 0, 0
    policy.model.eval()
    with torch.no_grad():
        for i in range(0, len(held), batch):
            b = collate(held[i : i + batch])
            a, c, m = token_nll_and_correct(b, policy.model(b))
            nll, ok, n = nll + a, ok + c, n + m
    return {"policy": {"nll": nll / max(n, 1), "top1": ok / max(n, 1), "tokens": n}, "unigram": uni, "constant_velocity": cv,
            "heldout_scenarios": len(held), "train_scenarios_for_baselines": len(train)}


def closed_loop(policy, data_dir: str, max_scenarios: int = 60, rollouts: int = 8, sampler: str = "topk:5", seed: int = 0,
                metric: str = "wosac", decoding: str = "central") -> dict:
    scs = [s for s in _subset(ScenarioDataset(data_dir), max_scenarios, seed) if s.metadata.get("source") == "sumo"]
    pol = evaluate_policy(policy, scs, sampler, rollouts, seed, batch_scenes=2, progress=True, metric=metric,
                          decoding=decoding)
    base = evaluate_baselines(scs, rollouts, progress=True, metric=metric)
    out = {"sampler": sampler, "rollouts": rollouts, "decoding": decoding, "num_scenarios": len(scs), "overall": {},
           "per_network": {}}
    keys = ["realism/collision_rate", "realism/offroad_rate", "realism/offroad_rate_log_window", "realism/rmm", "realism/min_ade"]
    runs = {"policy": pol, "constant_velocity": base["constant_velocity"], "log_replay": base["log_replay"]}
    for name, r in runs.items():
        out["overall"][name] = {k: r.summary()[k] for k in keys}
    nets = sorted({s.metadata.get("network") for s in scs})
    for net in nets:
        idx = {i for i, s in enumerate(scs) if s.metadata.get("network") == net}
        out["per_network"][net] = {name: {k: r.summary(idx)[k] for k in keys} for name, r in runs.items()}
    return out


METRIC_TEXT = {"wosac": "the official Waymo Open Sim Agents computation (`r1sim_sumo/metrics/realism.py`, `RealismConfig`)",
               "legacy": "the legacy computation from before the WOSAC correction (`--metric legacy`)"}


def kept_from_previous_card(ckpt: Path) -> dict:
    """What a person wrote into the checkpoint's previous ``model_card.json`` and a rerun must not lose: the
    ``notes`` (Limitations) and the ``machine`` the weights were trained on. Empty when there is no previous card."""
    path = ckpt / "model_card.json"
    if not path.exists():
        return {}
    try:
        old = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc}); fix or delete it before regenerating the card") from exc
    return {k: old[k] for k in ("notes", "machine") if k in old}


def _steps_line(tr: dict, extra: dict) -> str:
    """The card's training-effort line: wall time when the checkpoint records it, else CPU hours, plus the number
    of runs in a shipped checkpoint's lineage (``r1sim_sumo.train.ship``)."""
    line = f"- Steps: {tr['steps']}" if "steps" in tr else f"- Fine-tuning iterations ({tr.get('method', '?')}): {tr.get('iters', '?')}"
    if tr.get("device_name"):  # trained on a GPU: the card's machine is not the one that trained
        line += f" (last run); trained on {tr['device_name']}"
    elif tr.get("wall_s"):
        line += f"; wall time {tr['wall_s'] / 60:.1f} min on {extra.get('machine', 'CPU')}"
    elif tr.get("cpu_hours") is not None:
        line += f" (last run); {tr['cpu_hours']:.2f} CPU h on {extra.get('machine', 'CPU')}"
    if tr.get("lineage"):
        from r1sim_sumo.train.ship import flat_runs

        runs = flat_runs(tr["lineage"])
        line += (f"; shipped from `{tr.get('shipped_from', '?')}` after {len(runs)} runs on top of the earlier shipped policy"
                 + (f" ({tr['cpu_hours_recorded_total']:.2f} CPU h recorded)" if tr.get("cpu_hours_recorded_total") else "")
                 + "; the lineage with every run's config is in `checkpoint.json`")
    return line + "."


VERSUS_KEYS = (("RMM", "realism/rmm"), ("collision rate", "realism/collision_rate"), ("offroad rate", "realism/offroad_rate"))


def load_versus(path: str | Path) -> dict:
    """A comparison written by ``scripts/eval_grpo_vs_pretrained.py`` (``results``: ``"<model> / <sampler>"`` ->
    summarised metrics with ``/std``), checked so that a wrong file fails here and not half-way through the card."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"--versus {path}: cannot read it as JSON ({exc}); give a file written by "
                         "scripts/eval_grpo_vs_pretrained.py --out") from exc
    res = d.get("results")
    if not isinstance(res, dict) or not res:
        raise ValueError(f"--versus {path}: no 'results' field; give a file written by scripts/eval_grpo_vs_pretrained.py --out")
    for label, v in res.items():
        missing = [k for _, k in VERSUS_KEYS if k not in v]
        if " / " not in label or missing:
            lacks = missing or "the ' / <sampler>' suffix"
            raise ValueError(f"--versus {path}: result '{label}' lacks {lacks}; "
                             "rerun scripts/eval_grpo_vs_pretrained.py")
    return {"file": str(path), **{k: d.get(k) for k in ("metric", "pretrained", "grpo", "command")},
            "num_scenes": len(d.get("scenes", [])), "results": res}


def versus_section(versus: list[dict]) -> list[str]:
    """Card lines: the checkpoint against its starting point, same scenes and seeds, one row per (sampler, model),
    with the relative change of the collision rate."""
    L = ["", "## Against its starting point (same scenes and seeds)", ""]
    for v in versus:
        L += [f"`{v['file']}`: {v['num_scenes']} held-out SUMO test scenes, mean ± std over seeds, metric {v.get('metric') or '?'}; "
              f"start `{v.get('pretrained')}`, fine-tune `{v.get('grpo')}`"
              + (f"; produced by `{v['command']}`" if v.get("command") else "") + ".", "",
              "| sampler | model | " + " | ".join(n for n, _ in VERSUS_KEYS) + " | collision vs start |",
              "|---|---|" + "---|" * len(VERSUS_KEYS) + "---|"]
        by_sampler: dict[str, list[tuple[str, dict]]] = {}
        for label, r in v["results"].items():
            model, sampler = label.rsplit(" / ", 1)
            by_sampler.setdefault(sampler, []).append((model, r))
        for sampler, rows in by_sampler.items():
            base = rows[0][1]["realism/collision_rate"]
            for i, (model, r) in enumerate(rows):
                cells = [f"{r[k]:.4f} ± {r.get(k + '/std', float('nan')):.4f}" for _, k in VERSUS_KEYS]
                change = "start" if i == 0 else (f"{(r['realism/collision_rate'] - base) / base:+.0%}" if base > 0 else "n/a")
                L.append(f"| {sampler if i == 0 else ''} | {model} | " + " | ".join(cells) + f" | {change} |")
        L.append("")
    return L


def _preset_name(tr: dict, meta: dict) -> str:
    """The model preset: as the pretraining config names it, else (a fine-tune's config names none) the preset whose
    settings the checkpoint's ``model_config`` has; ``custom`` when none matches."""
    from r1sim_sumo.model.config import PRESETS

    if tr.get("config", {}).get("model"):
        return str(tr["config"]["model"])
    mc = meta.get("model_config", {})
    return next((n for n, kv in PRESETS.items() if all(mc.get(k) == v for k, v in kv.items())), "custom")


def write_card(ckpt: Path, tok: dict, cl: dict, extra: dict) -> None:
    meta = json.loads((ckpt / "checkpoint.json").read_text())
    tr = meta.get("training", {})
    tr = tr.get("train") or tr.get("finetune") or tr  # pretraining stores its info under "train", fine-tuning under "finetune"
    L = [f"# Model card: `{ckpt.name}`", "",
         f"- Parameters: {meta['num_parameters']:,}; preset: {_preset_name(tr, meta)}; vocabulary sizes {meta['vocab_sizes']} "
         f"(fingerprint `{meta['vocab_fingerprint']}`); package {meta['package_version']}.",
         f"- Training data: `{tr.get('config', {}).get('train_data', '?')}` ({extra.get('train_desc', '')}).",
         _steps_line(tr, extra),
         "", "## Held-out next-token prediction (future tokens, no label smoothing)", "",
         "| predictor | top-1 accuracy | NLL [nats] |", "|---|---|---|"]
    for k in ("policy", "unigram", "constant_velocity"):
        L.append(f"| {k} | {tok[k]['top1']:.4f} | {tok[k]['nll']:.3f} |")
    L += ["", f"{tok['policy']['tokens']:,} tokens from {tok['heldout_scenarios']} held-out scenarios; baselines fitted on "
          f"{tok['train_scenarios_for_baselines']} training scenarios.", "",
          f"## Closed-loop 8 s rollouts on held-out SUMO scenarios ({cl['num_scenarios']} scenarios, {cl['rollouts']} rollouts each, sampler `{cl['sampler']}`, "
          f"decoding `{cl.get('decoding', 'tokens')}`)", "",
          f"Realism metric: {METRIC_TEXT.get(cl.get('metric', 'wosac'), cl.get('metric'))}.", "",
          "| model | collision rate | offroad rate | offroad (log window) | RMM | minADE [m] |", "|---|---|---|---|---|---|"]
    nan = float("nan")
    for name, v in cl["overall"].items():
        L.append(f"| {name} | {v['realism/collision_rate']:.4f} | {v['realism/offroad_rate']:.4f} | "
                 f"{v.get('realism/offroad_rate_log_window', nan):.4f} | {v['realism/rmm']:.4f} | {v['realism/min_ade']:.2f} |")
    ov = cl["overall"]
    if {"policy", "constant_velocity", "log_replay"} <= set(ov):
        cv, lr = ov["constant_velocity"]["realism/rmm"], ov["log_replay"]["realism/rmm"]
        L += ["", f"RMM closes {(ov['policy']['realism/rmm'] - cv) / (lr - cv):.0%} of the gap from constant velocity to log replay."]
    L += ["", "Per network (collision / offroad / offroad over the log window):", "", "| network | policy | constant velocity | log replay |", "|---|---|---|---|"]
    for net, d in cl["per_network"].items():
        cells = [f"{d[n]['realism/collision_rate']:.3f} / {d[n]['realism/offroad_rate']:.3f} / {d[n].get('realism/offroad_rate_log_window', nan):.3f}"
                 for n in ("policy", "constant_velocity", "log_replay")]
        L.append(f"| {net} | " + " | ".join(cells) + " |")
    L += ["", "Rates are fractions of (rollout, agent) pairs with any collision / offroad event during the 8 s (SAT box "
          "overlap; offroad = a box corner outside the union of lane polygons). The log-window offroad counts only the "
          "steps at which the logged agent exists (an agent whose log ends where it leaves the finite network keeps driving "
          "in simulation, off the map). Log replay is the reference data itself.", "",
          f"Produced by `{extra.get('command', '')}`."]
    if extra.get("versus"):
        L += versus_section(extra["versus"])
    if extra.get("notes"):
        L += ["", "## Limitations", ""] + [f"- {n}" for n in extra["notes"]]
    (ckpt / "MODEL_CARD.md").write_text("\n".join(L) + "\n")
    (ckpt / "model_card.json").write_text(json.dumps({"token_metrics": tok, "closed_loop": cl, **extra}, indent=1))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint")
    ap.add_argument("--train", required=True)
    ap.add_argument("--heldout", required=True, help="split for token metrics (e.g. val)")
    ap.add_argument("--closed-loop", required=True, help="split for closed-loop rollouts (e.g. test)")
    ap.add_argument("--max-heldout", type=int, default=600)
    ap.add_argument("--max-closed-loop", type=int, default=60)
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--sampler", default="topk:5")
    ap.add_argument("--train-desc", default="")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--metric", choices=["wosac", "legacy"], default="wosac", help="realism computation of the closed-loop table")
    ap.add_argument("--decoding", choices=list(DECODINGS), default="central",
                    help="10 Hz states between the rollouts' token boundaries (rollout.kernel.decode_frames)")
    ap.add_argument("--versus", nargs="+", default=[], metavar="JSON",
                    help="comparisons with the starting point written by scripts/eval_grpo_vs_pretrained.py --out "
                         "(a fine-tune's card shows them as a table)")
    args = ap.parse_args(argv)
    versus = [load_versus(f) for f in args.versus]  # fail before the rollouts, not after
    torch.set_num_threads(args.threads)
    t0 = time.time()
    policy = r1sim_sumo.load_policy(args.checkpoint)
    tok = token_metrics(policy, args.train, args.heldout, max_heldout=args.max_heldout)
    print(json.dumps(tok, indent=1))
    cl = closed_loop(policy, args.closed_loop, args.max_closed_loop, args.rollouts, args.sampler, metric=args.metric,
                     decoding=args.decoding)
    cl["metric"] = args.metric
    print(json.dumps(cl["overall"], indent=1))
    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), platform.processor())
    ckpt = Path(policy.path) if hasattr(policy, "path") else Path(args.checkpoint)
    extra = {"train_desc": args.train_desc, "machine": f"{cpu}, {args.threads} threads",
             "command": "python -m r1sim_sumo.train.model_card " + shlex.join(sys.argv[1:] if argv is None else argv),
             "card_machine": f"{cpu}, {args.threads} threads", "card_wall_s": time.time() - t0}
    extra.update(kept_from_previous_card(ckpt))  # the Limitations and training machine a person wrote stay
    if versus:
        extra["versus"] = versus
    write_card(ckpt, tok, cl, extra)
    print(f"[model card] wrote {Path(args.checkpoint) / 'MODEL_CARD.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
