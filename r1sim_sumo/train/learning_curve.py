"""Learning curve of pretraining runs: closed-loop quality of every kept checkpoint on the held-out test split.

``python -m r1sim_sumo.train.learning_curve --run runs/campaign_a --run runs/campaign_b --out docs/training``

For each checkpoint (the ``ckpt-XXXXXX/`` snapshots a run keeps, plus ``--checkpoint`` folders or bundled names;
``--run`` also takes a fine-tuning run of ``r1sim finetune`` with ``keep_every``, plotted from its start checkpoint on):
closed-loop 8 s rollouts (``--rollouts`` per scene, top-K sampling) of ``--per-network`` test scenes of every SUMO
network (the held-out roundabout included): collision rate, offroad rate over the log window (overall and per
network), RMM, and the *copy rate* (share of consecutive future tokens of a vehicle that repeat the previous token;
the log's own rate on the same scenes is reported beside it) and the held-out next-token NLL on the same batches of
the compact val split for every checkpoint, and the free-road speed probes (:mod:`r1sim_sumo.evaluate_free_road`:
does a lone vehicle slowed to 8 / 20 m/s speed back up within 8 s; does the front vehicle of a 10 m/s platoon). Writes ``learning_curve.json``,
``learning_curve.md`` (agent-tokens seen and CPU hours per checkpoint) and ``learning_curve.png`` (each metric
against CPU hours).
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
import torch

from r1sim_sumo.evaluate import evaluate_policy, sumo_scenes_by_network
from r1sim_sumo.evaluate_free_road import free_road_speeds, platoon_speeds
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.kernel import DECODINGS
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.batch import collate, tokenize_scenario
from r1sim_sumo.tokens.constants import CURRENT_POSE

METRICS = ("collision_rate", "offroad_rate_log_window", "rmm", "copy_rate", "val_nll", "free_road_8", "platoon_front")


def cache_key(path: str, decoding: str) -> str:
    """The learning-curve cache's key of a checkpoint evaluated with ``decoding``: the path alone for ``tokens`` (every
    entry before session 12), ``path#decoding`` otherwise."""
    return path if decoding == "tokens" else f"{path}#{decoding}"


def weights_sha256(path: str) -> str | None:
    """The SHA-256 of a checkpoint's weights as its ``checkpoint.json`` records it (a folder or a bundled name);
    ``None`` when not recorded. Nothing is loaded or hashed."""
    from r1sim_sumo.model.checkpoint import BUNDLED_DIR, META_FILE

    for meta in (Path(path) / META_FILE, BUNDLED_DIR / str(path) / META_FILE):
        if meta.is_file():
            return json.loads(meta.read_text()).get("weights", {}).get("sha256")
    return None


def evaluated_twin(evaluated: dict, path: str, decoding: str) -> str | None:
    """The cache key of an entry evaluated with ``decoding`` on the same weights as ``path`` (recorded SHA-256), else
    ``None``: a run's ``final`` is its last ``ckpt-*``, a fine-tune's start is a copy of a pretraining snapshot."""
    sha = weights_sha256(path)
    if sha is None:
        return None
    for key, res in evaluated.items():
        if res.get("weights_sha256") == sha and cache_key(key.split("#")[0], decoding) == key:
            return key
    return None


def repeat_rate(tok: torch.Tensor) -> tuple[int, int]:
    """(repeats, pairs) over consecutive valid tokens ``[A, F]`` (-1 invalid): how often a token repeats the previous one."""
    a, b = tok[:, :-1], tok[:, 1:]
    ok = (a >= 0) & (b >= 0)
    return int(((a == b) & ok).sum()), int(ok.sum())


def copy_rates(policy, scenes, sampler: str = "topk:5", seed: int = 0) -> tuple[float, float]:
    """(policy, log) copy rate of the vehicles' future tokens over ``scenes`` (one rollout each)."""
    pol, log = np.zeros(2), np.zeros(2)
    for i, sc in enumerate(scenes):
        b = collate([tokenize_scenario(sc, policy.vocab)])
        veh = (b.agent_type[0] == 0) & b.agent_mask[0].bool()
        gt = torch.where(b.agent_token_valid[0].bool(), b.agent_token[0], -1)[:, CURRENT_POSE:]
        log += repeat_rate(gt[veh])
        with torch.no_grad():
            res = rollout(policy.model, policy.vocab, b, 1, parse_sampler(sampler), generator=torch.Generator().manual_seed(seed + i))
        pol += repeat_rate(res.token[0, 0][veh & (gt[:, 0] >= 0)])
    return pol[0] / max(pol[1], 1), log[0] / max(log[1], 1)


def evaluate_checkpoint(policy, by_network: dict, rollouts: int, sampler: str, desired_speed: str = "log",
                        decoding: str = "central") -> dict:
    """Closed-loop metrics over the scenes of ``by_network`` (``{network: [Scenario]}``); ``desired_speed`` and
    ``decoding`` as in :func:`r1sim_sumo.evaluate.evaluate_policy`."""
    out, per = {}, {}
    rows = []
    for net, scs in sorted(by_network.items()):
        res = evaluate_policy(policy, scs, sampler=sampler, num_rollouts=rollouts, progress=False, name=net,
                              desired_speed=desired_speed, decoding=decoding)
        s = res.summary()
        per[net] = {"collision_rate": s["realism/collision_rate"], "offroad_rate_log_window": s["realism/offroad_rate_log_window"],
                    "rmm": s["realism/rmm"]}
        rows += res.rows
    for k, key in (("collision_rate", "realism/collision_rate"), ("offroad_rate_log_window", "realism/offroad_rate_log_window"),
                   ("rmm", "realism/rmm")):
        out[k] = float(np.nanmean([r[key] for r in rows]))
    out["copy_rate"], out["copy_rate_log"] = copy_rates(policy, [s for scs in by_network.values() for s in scs], sampler)
    out["per_network"] = per
    out["num_scenes"] = len(rows)
    return out


def val_nll(policy, tokens: str, batches: int) -> float:
    """Held-out next-token NLL [nats] of future tokens on ``batches`` batches of 4 spread over the compact val split."""
    from r1sim_sumo.tokens.batch import collate
    from r1sim_sumo.tokens.compact import CompactTokenDataset
    from r1sim_sumo.train.pretrain import evaluate_nll

    return float(evaluate_nll(policy.model, CompactTokenDataset(tokens, "val"), collate, 4, batches)["nll"])


def _init_of(run: Path) -> str:
    """The checkpoint a run started from. A bundled name (``r1sim-nano``) is replaced by the run folder's snapshot with
    the same weights when the run recorded their SHA-256 (``init.json``) and the bundled policy has since been
    re-shipped (its weights differ): the sibling runs' ``ckpt-*`` and ``final`` folders and sibling folders holding
    weights directly are searched, then the name's earlier shipped versions in git (``restore_shipped_from_git``).
    When none holds them the start is ``MISSING_START`` (the name would load other weights than the run started from)."""
    cfg = (run / "config.yaml").read_text() if (run / "config.yaml").exists() else ""
    init = next((ln.split(":", 1)[1].strip() for ln in cfg.splitlines() if ln.startswith("init_checkpoint:")), "null")
    from r1sim_sumo.train.pretrain import recorded_init

    sha = recorded_init(run).get("weights_sha256")
    if not sha or Path(init).exists():
        return init
    if weights_sha256(init) == sha:  # the name's weights today (read from its metadata, nothing loaded)
        return init
    candidates = (sorted(run.parent.glob("*/ckpt-*/checkpoint.json")) + sorted(run.parent.glob("*/final/checkpoint.json"))
                  + sorted(run.parent.glob("*/checkpoint.json")))
    for meta in candidates:
        if weights_sha256(str(meta.parent)) == sha:
            return str(meta.parent)
    restored = restore_shipped_from_git(init, sha, RESTORED_DIR)
    if restored is not None:
        return str(restored)
    print(f"[learning_curve] {run}: started from {init!r} with weights sha256 {sha[:8]}, which {init!r} no longer "
          f"holds, nor any folder beside the run or version of {init!r} in git; its start point is left out. Fix: put "
          f"a folder with those weights (model.safetensors + checkpoint.json) beside the run.")
    return MISSING_START


MISSING_START = "missing-start"  # _init_of: the run's recorded start weights are nowhere to be found
RESTORED_DIR = Path("runs") / "_restored"  # earlier shipped policies written out of git (runs/ is not committed)


def restore_shipped_from_git(name: str, sha: str, dest_root: Path) -> Path | None:
    """An earlier shipped version of the bundled policy ``name`` whose weights have SHA-256 ``sha``, written out of the
    git history (``r1sim_sumo/checkpoints/<name>/``) into ``dest_root/<name>-<sha[:8]>/``; ``None`` when git or the
    history is not there or no version has those weights. The written weights are checked against ``sha``."""
    import hashlib
    import subprocess

    from r1sim_sumo.model.checkpoint import BUNDLED_DIR, META_FILE, WEIGHTS_FILE

    dest = dest_root / f"{name}-{sha[:8]}"
    if weights_sha256(str(dest)) == sha:  # restored before
        return dest
    folder = BUNDLED_DIR / name

    def git(*args: str) -> bytes:
        return subprocess.run(["git", "-C", str(BUNDLED_DIR), *args], capture_output=True, check=True).stdout

    try:
        rel = git("rev-parse", "--show-prefix").decode().strip() + name
        commits = git("log", "--format=%H", "--", f"{name}/{META_FILE}").decode().split()
        for c in commits:
            meta = json.loads(git("show", f"{c}:{rel}/{META_FILE}"))
            if meta.get("weights", {}).get("sha256") != sha:
                continue
            weights = git("show", f"{c}:{rel}/{WEIGHTS_FILE}")
            if hashlib.sha256(weights).hexdigest() != sha:
                return None  # stored as something else (e.g. an LFS pointer): not the weights
            dest.mkdir(parents=True, exist_ok=True)
            (dest / WEIGHTS_FILE).write_bytes(weights)
            (dest / META_FILE).write_text(json.dumps(meta, indent=1))
            print(f"[learning_curve] {folder}: the version with weights {sha[:8]} restored from commit {c[:10]} into {dest}")
            return dest
    except (OSError, subprocess.CalledProcessError, json.JSONDecodeError):
        return None
    return None


def checkpoint_counts(path: str, _depth: int = 0) -> dict:
    """Agent-tokens seen and CPU hours of a pretraining snapshot counted from the shipped weights: its own run's
    counts (``checkpoint.json``) plus those of the snapshot its run started from, and so on up the chain (a bundled
    name or a folder without counts ends it). A fine-tuning snapshot (``ckpt-XXXXXX`` or ``final`` of an ``r1sim
    finetune`` run, which records no counts) counts as its run's start plus the run's compute up to it
    (:func:`_finetune_compute`); ``{}`` when ``path`` holds no counts and is not in such a run."""
    p = Path(path)
    if path in ("null", "None", "", MISSING_START) or not (p / "checkpoint.json").exists():
        return {}
    own = dict(json.loads((p / "checkpoint.json").read_text()).get("training", {}).get("train", {}))
    if _depth > 20:
        return own
    if not own:
        return _finetune_snapshot_counts(p, _depth)
    base = checkpoint_counts(_init_of(p.parent), _depth + 1)
    for k in ("agent_tokens_seen", "cpu_hours"):
        if own.get(k) is not None and base.get(k) is not None:
            own[k] = own[k] + base[k]
    return own


def _run_points(run: Path) -> list[dict]:
    """Snapshots of a run: ``ckpt-XXXXXX`` folders with their step, tokens seen and wall time from ``log.csv``."""
    log = list(csv.DictReader(open(run / "log.csv"))) if (run / "log.csv").exists() else []
    pts = []
    init = _init_of(run)
    if log and "iter" in log[0]:  # a fine-tuning run (r1sim finetune): placed after the compute of its start
        return _finetune_points(run, log, init)
    # a run continuing a snapshot of another run is placed after that snapshot's tokens and CPU hours (the shipped
    # weights, a bundled name, count as 0: the campaigns' counts start there)
    start = checkpoint_counts(init)
    tok0, cpu0 = start.get("agent_tokens_seen") or 0, start.get("cpu_hours") or 0.0
    if init not in ("null", "None", "", MISSING_START):  # the run's starting point: step 0, nothing seen yet in this run
        pts.append({"name": f"{run.name}@0", "path": init, "run": run.name, "step": 0, "agent_tokens": tok0,
                    "cpu_hours": cpu0, "val_nll": None})
    for d in sorted(run.glob("ckpt-*")):
        step = int(d.name.split("-")[1])
        rows = [r for r in log if int(r["step"]) <= step]
        val = [r for r in rows if r.get("val_nll")]
        info = json.loads((d / "checkpoint.json").read_text()).get("training", {}).get("train", {})
        pts.append({"name": f"{run.name}@{step}", "path": str(d), "run": run.name, "step": step,
                    "agent_tokens": None if info.get("agent_tokens_seen") is None else tok0 + info["agent_tokens_seen"],
                    "cpu_hours": None if info.get("cpu_hours") is None else cpu0 + info["cpu_hours"],
                    "val_nll": float(val[-1]["val_nll"]) if val and int(val[-1]["step"]) == step else None})
    return pts


def _finetune_compute(run: Path, log: list[dict]) -> dict[int, float]:
    """CPU hours a fine-tuning run spent up to each logged iteration: the summed ``rollout_s + update_s`` of its
    iterations (``log.csv``, exact across resumes) x its torch threads (config ``threads``). A run that logs every
    n-th iteration (``log_every``) logs one iteration's times per row: each row counts for the iterations since the
    previous one."""
    cfg = (run / "config.yaml").read_text() if (run / "config.yaml").exists() else ""
    threads = int(next((ln.split(":", 1)[1] for ln in cfg.splitlines() if ln.startswith("threads:")), "1"))
    spent, total, prev = {}, 0.0, 0
    for r in sorted(log, key=lambda r: int(r["iter"])):
        it = int(r["iter"])
        total += (it - prev) * (float(r.get("rollout_s") or 0.0) + float(r.get("update_s") or 0.0))
        spent[it], prev = total * threads / 3600.0, it
    return spent


def _finetune_snapshot_counts(ckpt: Path, _depth: int) -> dict:
    """Counts of a snapshot of a fine-tuning run (``ckpt-XXXXXX`` = iteration, or ``final`` = its last logged
    iteration): the run start's agent-tokens, and its CPU hours plus the run's compute up to that iteration; ``{}``
    when the folder is not in a fine-tuning run or its start has no counts."""
    run = ckpt.parent
    log = list(csv.DictReader(open(run / "log.csv"))) if (run / "log.csv").exists() else []
    if not log or "iter" not in log[0]:
        return {}
    spent = _finetune_compute(run, log)
    it = int(ckpt.name.split("-")[1]) if ckpt.name.startswith("ckpt-") else max(spent)
    start = checkpoint_counts(_init_of(run), _depth + 1)
    if start.get("cpu_hours") is None or it not in spent:
        return {}
    return {"agent_tokens_seen": start.get("agent_tokens_seen"), "cpu_hours": start["cpu_hours"] + spent[it]}


def _finetune_points(run: Path, log: list[dict], init: str) -> list[dict]:
    """Its start checkpoint (``<run>@0``) and snapshots ``ckpt-XXXXXX`` (``XXXXXX`` = iteration) of a fine-tuning
    run. Agent-tokens are those the start checkpoint was pretrained on (fine-tuning labels its own rollouts); CPU hours
    = the start's (a fine-tuning snapshot's included: :func:`checkpoint_counts`) plus the run's compute
    (:func:`_finetune_compute`)."""
    start = checkpoint_counts(init)
    spent = _finetune_compute(run, log)
    base_cpu = start.get("cpu_hours")
    pts = [{"name": f"{run.name}@0", "path": init, "run": run.name, "step": 0, "agent_tokens": start.get("agent_tokens_seen"),
            "cpu_hours": base_cpu, "val_nll": None}] if init not in ("null", "None", "", MISSING_START) else []
    for d in sorted(run.glob("ckpt-*")):
        it = int(d.name.split("-")[1])
        cpu = base_cpu + spent[it] if base_cpu is not None and it in spent else None
        pts.append({"name": f"{run.name}@{it}", "path": str(d), "run": run.name, "step": it,
                    "agent_tokens": start.get("agent_tokens_seen"), "cpu_hours": cpu, "val_nll": None})
    return pts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", action="append", default=[], help="a pretraining or fine-tuning run folder (its ckpt-* snapshots)")
    ap.add_argument("--checkpoint", action="append", default=[], help="a checkpoint folder or bundled name (e.g. r1sim-nano)")
    ap.add_argument("--data", default="data/generated/default/test")
    ap.add_argument("--per-network", type=int, default=6)
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--sampler", default="topk:5")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--decoding", choices=list(DECODINGS), default="central",
                    help="10 Hz states between the rollouts' token boundaries (rollout.kernel.decode_frames); the "
                         "curve committed before session 12 used 'tokens'")
    ap.add_argument("--out", default="docs/training")
    ap.add_argument("--val-tokens", default="data/tokens/default",
                    help="compact token dataset whose val split gives the held-out NLL of every checkpoint ('' = none)")
    ap.add_argument("--val-batches", type=int, default=24, help="batches of 4 val scenes, spread over the split")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    by_net = sumo_scenes_by_network(ScenarioDataset(a.data), a.per_network)
    points = [{"name": c, "path": c, "run": "checkpoint", "step": None, "agent_tokens": None, "cpu_hours": None,
               "val_nll": None} for c in a.checkpoint]
    for r in a.run:
        points += _run_points(Path(r))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = out / "learning_curve.json"
    evaluated = {}  # checkpoint path -> closed-loop metrics; kept across reruns, which add only new checkpoints
    if cache.exists():
        evaluated = json.loads(cache.read_text()).get("evaluated", {})
    for p in points:
        key = cache_key(p["path"], a.decoding)
        twin = None if key in evaluated else evaluated_twin(evaluated, p["path"], a.decoding)
        if twin is not None:  # the same weights under another path (a copy, a final = last ckpt)
            print(f"{p['name']}: same weights as {twin}, its results reused", flush=True)
            evaluated[key] = dict(evaluated[twin])
        if key not in evaluated:
            pol = load_policy(p["path"])
            tr = pol.info.get("training", {}).get("train", {})
            res = evaluate_checkpoint(pol, by_net, a.rollouts, a.sampler, decoding=a.decoding)
            res.update(agent_tokens_seen=tr.get("agent_tokens_seen"), cpu_hours=tr.get("cpu_hours"),
                       weights_sha256=weights_sha256(p["path"]))
            evaluated[key] = res
            print(f"{p['name']}: collision {res['collision_rate']:.3f} offroad(log window) {res['offroad_rate_log_window']:.3f} "
                  f"RMM {res['rmm']:.3f} copy {res['copy_rate']:.2f} (log {res['copy_rate_log']:.2f})", flush=True)
            cache.write_text(json.dumps({"settings": vars(a), "evaluated": evaluated, "points": points}, indent=1))
        res = evaluated[key]
        if res.get("weights_sha256") is None:  # entries written before the hash was recorded
            res["weights_sha256"] = weights_sha256(p["path"])
        if a.val_tokens and res.get("val_nll_eval") is None:  # the same batches for every checkpoint
            res["val_nll_eval"] = val_nll(load_policy(p["path"]), a.val_tokens, a.val_batches)
        if res.get("free_road") is None:  # speed after 8 s alone on a free motorway lane, from 8 and 20 m/s
            res["free_road"] = {f"{v0:g}": v for v0, v in free_road_speeds(load_policy(p["path"])).items()}
            cache.write_text(json.dumps({"settings": vars(a), "evaluated": evaluated, "points": points}, indent=1))
        if res.get("no_desired") is None:
            pol = load_policy(p["path"])
            if pol.config.desired_speed_input:
                # the same rollouts without the desired-speed input: what the model does with nothing from the log's future
                nd = evaluate_checkpoint(pol, by_net, a.rollouts, a.sampler, desired_speed="unknown", decoding=a.decoding)
                res["no_desired"] = {k: nd[k] for k in ("collision_rate", "offroad_rate_log_window", "rmm", "per_network")}
                cache.write_text(json.dumps({"settings": vars(a), "evaluated": evaluated, "points": points}, indent=1))
        if res.get("platoon") is None:  # the front vehicle of 5 at 10 m/s on a free lane: does it lead the speed-up?
            res["platoon"] = platoon_speeds(load_policy(p["path"]))
            cache.write_text(json.dumps({"settings": vars(a), "evaluated": evaluated, "points": points}, indent=1))
        p["free_road_8"], p["free_road_20"] = res["free_road"]["8"], res["free_road"]["20"]
        p["platoon_front"] = res["platoon"]["front"]
        p.update({k: v for k, v in res.items() if k not in ("agent_tokens_seen", "cpu_hours", "val_nll_eval")})
        p["val_nll"] = res.get("val_nll_eval", p["val_nll"])
        p["agent_tokens"] = p["agent_tokens"] if p["agent_tokens"] is not None else res.get("agent_tokens_seen")
        p["cpu_hours"] = p["cpu_hours"] if p["cpu_hours"] is not None else res.get("cpu_hours")
    cache.write_text(json.dumps({"settings": vars(a), "evaluated": evaluated, "points": points}, indent=1))
    write_report(points, out, a)
    return 0


def _no_desired(p: dict) -> str:
    nd = p.get("no_desired")
    return "" if not nd else f"{nd['collision_rate']:.3f} / {nd['offroad_rate_log_window']:.3f} / {nd['rmm']:.3f}"


def plot_series(points: list[dict], metric: str) -> list[tuple[str, list[float], list[float]]]:
    """``(run, x, y)`` per run for one panel of the plot. x: CPU hours of training where every point knows them
    (fine-tuning runs continue to the right of their start checkpoint); else (checkpoints given one by one, fine-tunes
    that record no hours) each point's position in ``points``, the order given on the command line."""
    by_order = any(p.get("cpu_hours") is None for p in points)
    order = {id(p): i for i, p in enumerate(points)}
    x = (lambda p: float(order[id(p)])) if by_order else (lambda p: p["cpu_hours"])
    out = []
    for run in sorted({p["run"] for p in points}):
        ps = sorted((p for p in points if p["run"] == run and p.get(metric) is not None), key=x)
        if ps:
            out.append((run, [x(p) for p in ps], [p[metric] for p in ps]))
    return out


def _short_name(name: str) -> str:
    """A checkpoint's axis label: ``runs/grpo_x/ckpt-000030`` -> ``grpo_x@30``, ``runs/r/final`` -> ``r/final``."""
    parts = Path(name).parts
    if len(parts) >= 2 and parts[-1].startswith("ckpt-"):
        return f"{parts[-2]}@{int(parts[-1][5:])}" if parts[-1][5:].isdigit() else f"{parts[-2]}/{parts[-1]}"
    return "/".join(parts[-2:]) if len(parts) >= 2 else name


def write_report(points: list[dict], out: Path, a) -> None:
    nets = sorted({n for p in points for n in p.get("per_network", {})})
    head = ["checkpoint", "agent-tokens", "CPU h", "val NLL", "collision", "offroad (log window)", "RMM", "copy rate (log)",
            "free road 8 -> [m/s]", "free road 20 -> [m/s]", "platoon front 10 -> [m/s]",
            "no desired speed: collision / offroad / RMM"]
    lines = [f"# Learning curve\n\n{a.per_network} test scenes per SUMO network x {a.rollouts} rollouts, {a.sampler}, "
             f"decoding `{getattr(a, 'decoding', 'tokens')}`; `python -m r1sim_sumo.train.learning_curve` (settings in learning_curve.json). Free road: speed after "
             "8 s of a vehicle alone on a free motorway lane (limit 33.3 m/s) starting at 8 / 20 m/s "
             "(`r1sim_sumo.evaluate_free_road`; SUMO's Krauss driver is back near the limit within seconds). Platoon "
             "front: speed after 8 s of the front one of 5 vehicles started at 10 m/s with 1.5 s headways in one free "
             "lane, all driven by the policy (`--platoon`): nothing is ahead of it either. Policies with the desired-speed "
             "input get each agent's fastest 0.5 s of its logged window (a driver attribute from the log, future "
             "included); the last column runs the same rollouts with no desired speed given.\n",
             "| " + " | ".join(head + [f"offroad {n}" for n in nets]) + " |", "|" + "---|" * (len(head) + len(nets))]
    f = lambda v, fmt="{:.3f}": "" if v is None else fmt.format(v)  # noqa: E731
    for p in points:
        lines.append("| " + " | ".join([p["name"], f(p.get("agent_tokens"), "{:,.0f}"), f(p.get("cpu_hours"), "{:.2f}"),
                                         f(p.get("val_nll")), f(p["collision_rate"]), f(p["offroad_rate_log_window"]),
                                         f(p["rmm"]), f"{p['copy_rate']:.2f} ({p['copy_rate_log']:.2f})",
                                         f(p.get("free_road_8"), "{:.1f}"), f(p.get("free_road_20"), "{:.1f}"),
                                         f(p.get("platoon_front"), "{:.1f}"), _no_desired(p)]
                                        + [f(p["per_network"].get(n, {}).get("offroad_rate_log_window")) for n in nets]) + " |")
    (out / "learning_curve.md").write_text("\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(METRICS), figsize=(4 * len(METRICS) + 3, 3.6))
    runs = sorted({p["run"] for p in points})
    colours = plt.cm.tab20(np.linspace(0, 1, max(len(runs), 2)))  # one colour per run (tab10 repeats after ten)
    by_order = any(p.get("cpu_hours") is None for p in points)
    for ax, m in zip(axes, METRICS, strict=True):
        for run, xs, ys in plot_series(points, m):
            i = runs.index(run)
            ax.plot(xs, ys, "o-" if i % 2 == 0 else "s--", ms=3, color=colours[i], label=run)
        ax.set_title(m)
        if by_order:
            ax.set_xticks(range(len(points)))
            ax.set_xticklabels([_short_name(p["name"]) for p in points], rotation=90, fontsize=6)
            ax.set_xlabel("checkpoint (in the order given)")
        else:
            ax.set_xlabel("CPU hours of training")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="center left", bbox_to_anchor=(0.9, 0.5), ncol=2, fontsize=7)
    fig.tight_layout(rect=(0, 0, 0.9, 1))
    fig.savefig(out / "learning_curve.png", dpi=100, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
