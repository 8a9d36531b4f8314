"""Closed-loop evaluation: policy rollouts (and baselines) scored by the WOSAC-style realism metrics.

``evaluate_policy`` tokenizes scenarios, rolls out ``num_rollouts`` futures per scenario in batches
(:func:`r1sim_sumo.rollout.engine.rollout`; batches can be sharded over a :mod:`r1sim_sumo.workers` pool, each
seeded from ``(seed, batch index)`` so the sharded report equals the single-process one), maps them back to the scenario's agents and scores them with
:func:`r1sim_sumo.metrics.realism.compute_realism`. Baselines on the same scenarios: log replay (upper
reference) and constant velocity (heading and speed held from the current state). Reports: per-scenario rows,
aggregates, entropy / K_t statistics, an Easy/Hard split by RMM quantile, JSON + markdown + plots.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from r1sim_sumo.evaluate_sumo_again import has_states, sumo_again_sim
from r1sim_sumo.metrics.realism import compute_realism, metric_config
from r1sim_sumo.metrics.types import SimTrajectories
from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.kernel import DECODINGS
from r1sim_sumo.rollout.samplers import Sampler, parse_sampler
from r1sim_sumo.scenario import N_FUTURE_10HZ, Scenario
from r1sim_sumo.sumo_launch import sumo_close
from r1sim_sumo.tokens.batch import collate, tokenize_scenario
from r1sim_sumo.tokens.matching import reconstruct_states
from r1sim_sumo.viz import save_scenario_png


def rollouts_to_sim(xy_10hz: torch.Tensor, yaw_10hz: torch.Tensor, valid_10hz: torch.Tensor, agent_index: np.ndarray,
                    scenario: Scenario) -> SimTrajectories:
    """Rollout states of one scene ``[G, A_tok, 81, ...]`` (index 0 = now) -> scenario-ordered future ``[G, A, 80]``.

    Scenario agents that were not tokenized (no valid boundary pose) are invalid in every rollout.
    """
    G, n = xy_10hz.shape[0], len(agent_index)
    A = scenario.agents.num_agents
    T = min(N_FUTURE_10HZ, scenario.num_steps - scenario.current_index - 1)
    x = np.zeros((G, A, T))
    y = np.zeros((G, A, T))
    yaw = np.zeros((G, A, T))
    v = np.zeros((G, A, T), bool)
    x[:, agent_index] = xy_10hz[:, :n, 1 : T + 1, 0].double().numpy()
    y[:, agent_index] = xy_10hz[:, :n, 1 : T + 1, 1].double().numpy()
    yaw[:, agent_index] = yaw_10hz[:, :n, 1 : T + 1].double().numpy()
    v[:, agent_index] = valid_10hz[:, :n, 1 : T + 1].numpy()
    return SimTrajectories(x_m=x, y_m=y, yaw_rad=yaw, valid=v)


def constant_velocity_sim(scenario: Scenario) -> SimTrajectories:
    """Constant-velocity baseline: every agent keeps its current velocity vector and heading for 8 s."""
    a, ci = scenario.agents, scenario.current_index
    T = min(N_FUTURE_10HZ, scenario.num_steps - ci - 1)
    t = (np.arange(1, T + 1) * scenario.dt_s)[None]  # [1, T]
    x = a.x_m[:, ci, None] + a.vx_mps[:, ci, None] * t
    y = a.y_m[:, ci, None] + a.vy_mps[:, ci, None] * t
    yaw = np.repeat(a.yaw_rad[:, ci, None], T, 1)
    v = np.repeat(a.valid[:, ci, None], T, 1)
    return SimTrajectories(x_m=x[None], y_m=y[None], yaw_rad=yaw[None], valid=v[None])


def sumo_scenes_by_network(dataset, per_network: int, every: int = 7) -> dict[str, list[Scenario]]:
    """Up to ``per_network`` SUMO scenes per network from every ``every``-th scene of ``dataset`` (a fixed, spread
    sample for per-network diagnostics), in dataset order."""
    out: dict[str, list[Scenario]] = {}
    for i in range(0, len(dataset), every):
        sc = dataset[i]
        if sc.metadata.get("source") == "sumo":
            scs = out.setdefault(sc.metadata["network"], [])
            if len(scs) < per_network:
                scs.append(sc)
    return out


def matched_reference_sim(scenario: Scenario, vocab, scene=None) -> SimTrajectories:
    """The logged future rebuilt from its rolling-matched tokens (open loop, ``[1, A, 80]``): the best a policy over
    this vocabulary can do, so its offroad and collision rates are the floor the tokenization alone sets.

    :param scene: the scenario's :class:`~r1sim_sumo.tokens.batch.TokenizedScene` if already built.
    """
    scene = scene if scene is not None else tokenize_scenario(scenario, vocab)
    b = collate([scene])
    tok, ok = b.agent_token[:, :, 2:], b.agent_token_valid[:, :, 2:].bool()  # future tokens from "now" (pose 2)
    xy10, yaw10 = reconstruct_states(b.pose_xy[:, :, 2], b.pose_yaw[:, :, 2], torch.where(ok, tok, 0), vocab,
                                     b.agent_type.long())  # [1, A, 81, 2]
    v = b.pose_valid[:, :, 2:].bool()  # [1, A, 17] boundary poses now .. +8 s
    v10 = torch.cat([v[..., :1], v[..., 1:].repeat_interleave(5, -1)], -1)  # a token's 5 states valid with its end
    return rollouts_to_sim(xy10, yaw10, v10, scene.agent_index, scenario)


@dataclass
class EvalResult:
    name: str
    rows: list[dict] = field(default_factory=list)  # per scenario: id + metrics
    entropy: list[float] = field(default_factory=list)  # sampled per-agent-step entropies [nats]
    k_by_step: list[list[float]] = field(default_factory=list)  # mean K_t per future step, per batch
    wall_s: float = 0.0

    def summary(self, subset: set[int] | None = None) -> dict:
        rows = [r for i, r in enumerate(self.rows) if subset is None or i in subset]
        keys = [k for k in rows[0] if k not in ("scenario",)] if rows else []
        return {k: float(np.nanmean([r[k] for r in rows])) for k in keys} | {"num_scenarios": len(rows)}


def _row(sid: str, res) -> dict:
    d = res.to_dict()
    d["scenario"] = sid
    return d


def _sid(sc: Scenario, i: int) -> str:
    m = sc.metadata
    return str(m.get("scenario_id") or f"{m.get('network', m.get('source', 'scn'))}/s{m.get('seed', '?')}/w{m.get('window_index', m.get('start_step', i))}")


@dataclass
class EvalBatchTask:
    """One batch of scenes to roll out and score: a pool task of :func:`evaluate_policy`.

    The sampling generator is seeded from ``(seed, batch_index)`` only, so the result of a batch does not
    depend on which worker runs it or on what ran before.
    """

    batch_index: int
    first_index: int  # index of scenarios[0] in the evaluated list (for scenario ids)
    scenarios: list
    sampler: Sampler
    num_rollouts: int
    seed: int
    threads: int | None = None  # torch threads in the worker (None: leave as is)
    metric: str = "wosac"  # realism computation: wosac (official) or legacy (r1sim_sumo.metrics.realism.metric_config)
    desired_speed: str = "log"  # desired-speed input of policies that take one: "log" (hindsight over the log window) or "unknown"
    decoding: str = "central"  # 10 Hz states between token boundaries (r1sim_sumo.rollout.kernel.DECODINGS)

    def describe(self) -> str:
        last = self.first_index + len(self.scenarios) - 1
        return f"evaluation batch {self.batch_index} (scenarios {self.first_index}..{last}, {self.sampler.spec}, seed {self.seed})"


def batch_generator(seed: int, batch_index: int) -> torch.Generator:
    """The sampling generator of batch ``batch_index``: ``manual_seed(seed * 1_000_003 + batch_index)``."""
    return torch.Generator().manual_seed(int(seed) * 1_000_003 + int(batch_index))


def evaluate_batch(task: EvalBatchTask, policy) -> dict:
    """Roll out and score one batch (runs in a worker): ``{"rows", "entropy", "k_by_step"}``."""
    if task.threads is not None:
        torch.set_num_threads(task.threads)
    model, vocab = policy.model.eval(), policy.vocab
    scs = task.scenarios
    scenes = [tokenize_scenario(sc, vocab) for sc in scs]
    batch = collate(scenes)
    if task.desired_speed == "unknown":  # the policy gets no desired speed (NaN): nothing from the logged future
        batch = batch._replace(agent_desired_speed=torch.full_like(batch.agent_desired_speed, float("nan")))
    r = rollout(model, vocab, batch, num_rollouts=task.num_rollouts, sampler=task.sampler,
                generator=batch_generator(task.seed, task.batch_index), decoding=task.decoding)
    v10 = r.valid_10hz()
    sim_m = r.sim_mask.expand_as(r.entropy[..., 0])  # [G, B, A]
    rows = []
    for b, (sc, scene) in enumerate(zip(scs, scenes, strict=True)):
        sim = rollouts_to_sim(r.xy_10hz[:, b], r.yaw_10hz[:, b], v10[:, b], scene.agent_index, sc)
        rows.append(_row(_sid(sc, task.first_index + b), compute_realism(sc, sim, config=metric_config(task.metric))))
    return {"rows": rows, "entropy": r.entropy[sim_m].flatten().tolist()[:20000],
            "k_by_step": [float(r.k[..., s][sim_m].float().mean()) for s in range(r.k.shape[-1])]}


def evaluate_policy(policy, scenarios, sampler: Sampler | str = "topk:32", num_rollouts: int = 32, seed: int = 0,
                    batch_scenes: int = 2, progress: bool = True, name: str | None = None, pool=None,
                    worker_threads: int | None = None, metric: str = "wosac", desired_speed: str = "log",
                    decoding: str = "central") -> EvalResult:
    """Roll out and score every scenario of ``scenarios`` (a list or ScenarioDataset).

    Scenes are rolled out ``batch_scenes`` at a time; batch ``j`` samples with
    :func:`batch_generator` ``(seed, j)``, so a run sharded over a worker pool gives the same report as a
    single-process run.

    :param pool: a :mod:`r1sim_sumo.workers` pool to shard the batches over (``None``: this process).
    :param worker_threads: torch threads each worker uses (``None``: unchanged).
    :param metric: ``wosac`` (the official realism computation) or ``legacy`` (the one before issue 16).
    :param desired_speed: for policies with the desired-speed input: ``log`` gives each agent the hindsight estimate
        of its logged window (its fastest 0.5 s, future included: a driver attribute taken from the log, as SUMO's
        speedFactor is known to the drop-in), ``unknown`` gives none.
    :param decoding: the rollouts' 10 Hz states between token boundaries (:func:`r1sim_sumo.rollout.kernel.decode_frames`).
    """
    metric_config(metric)  # a bad name fails here, not in a worker
    if decoding not in DECODINGS:
        raise ValueError(f"evaluate_policy: decoding {decoding!r} must be one of {DECODINGS}")
    if desired_speed not in ("log", "unknown"):
        raise ValueError(f"evaluate_policy: desired_speed {desired_speed!r} must be 'log' or 'unknown'")
    sampler = parse_sampler(sampler) if isinstance(sampler, str) else sampler
    out = EvalResult(name or sampler.spec)
    t0 = time.time()
    n = len(scenarios)
    tasks = [EvalBatchTask(j, lo, [scenarios[i] for i in range(lo, min(n, lo + batch_scenes))], sampler,
                           num_rollouts, seed, worker_threads if pool is not None else None, metric, desired_speed,
                           decoding)
             for j, lo in enumerate(range(0, n, batch_scenes))]
    bar = tqdm(total=n, desc=f"evaluate {out.name}", disable=not progress, dynamic_ncols=True)
    if pool is None:
        parts = []
        for t in tasks:
            parts.append(evaluate_batch(t, policy))
            bar.update(len(t.scenarios))
    else:
        parts = pool.map(evaluate_batch, tasks, shared=policy, on_result=lambda i, _: bar.update(len(tasks[i].scenarios)))
    bar.close()
    for part in parts:  # task order = scenario order
        out.rows.extend(part["rows"])
        out.entropy.extend(part["entropy"])
        out.k_by_step.append(part["k_by_step"])
    out.wall_s = time.time() - t0
    return out


def _baseline_rows(task: tuple) -> dict[str, list[dict]]:
    """Pool task of :func:`evaluate_baselines`: ``(first_index, scenarios, num_rollouts[, state_root[, redraw[, metric]]])`` ->
    rows per baseline; with a ``state_root`` (not None) also ``sumo_again`` (:mod:`r1sim_sumo.evaluate_sumo_again`,
    ``redraw``: new desired-speed factors as well as a new seed)."""
    first, scs, num_rollouts = task[:3]
    state_root = task[3] if len(task) > 3 else None
    redraw = bool(task[4]) if len(task) > 4 else False
    cfg = metric_config(task[5] if len(task) > 5 else "wosac")
    out: dict[str, list[dict]] = {"log_replay": [], "constant_velocity": []}
    if state_root is not None:
        out["sumo_again"] = []
    for k, sc in enumerate(scs):
        sid = _sid(sc, first + k)
        out["log_replay"].append(_row(sid, compute_realism(sc, SimTrajectories.log_replay(sc, num_rollouts), config=cfg)))
        out["constant_velocity"].append(_row(sid, compute_realism(sc, constant_velocity_sim(sc), config=cfg)))
        if state_root is not None:
            again = sumo_again_sim(sc, state_root, num_rollouts, redraw_speed_factor=redraw)
            out["sumo_again"].append(_row(sid, compute_realism(sc, again, config=cfg)))
    if state_root is not None:
        sumo_close()
    return out


def evaluate_baselines(scenarios, num_rollouts: int = 32, progress: bool = True, pool=None,
                       chunk: int = 4, sumo_again: bool | str = False, state_root=None,
                       metric: str = "wosac") -> dict[str, EvalResult]:
    """Log replay (the reference itself, ``num_rollouts`` copies) and constant velocity on the same scenarios.

    :param pool: a :mod:`r1sim_sumo.workers` pool to shard ``chunk`` scenarios per task (``None``: here).
    :param sumo_again: also SUMO rerun from each scenario's saved state with ``num_rollouts`` other seeds
        (:mod:`r1sim_sumo.evaluate_sumo_again`); every scenario needs a ``state_file`` under ``state_root``
        (default: ``scenarios.root`` of a ScenarioDataset). ``"redraw"`` also redraws every vehicle's desired-speed
        factor (a new seed alone moves the 8 s futures by centimetres: Krauss dawdling is corrected every step).
    """
    res = {"log_replay": EvalResult("log replay"), "constant_velocity": EvalResult("constant velocity")}
    n = len(scenarios)
    root = None
    if sumo_again:
        root = state_root if state_root is not None else getattr(scenarios, "root", None)
        if not has_states(scenarios, root):
            raise ValueError(f"evaluate_baselines(sumo_again=True): not every scenario has a 'state_file' under {root}; "
                             "generate the data with `r1sim generate sumo --save-states` and pass state_root")
        res["sumo_again"] = EvalResult("SUMO again" + (" (speed factors redrawn)" if sumo_again == "redraw" else ""))
        root = str(root)
    redraw = sumo_again == "redraw"
    metric_config(metric)
    tasks = [(lo, [scenarios[i] for i in range(lo, min(n, lo + chunk))], num_rollouts, root, redraw, metric)
             for lo in range(0, n, chunk)]
    bar = tqdm(total=n, desc="baselines", disable=not progress, dynamic_ncols=True)
    if pool is None:
        parts = []
        for t in tasks:
            parts.append(_baseline_rows(t))
            bar.update(len(t[1]))
    else:
        parts = pool.map(_baseline_rows, tasks, on_result=lambda i, _: bar.update(len(tasks[i][1])))
    bar.close()
    for part in parts:
        for k, rows in part.items():
            res[k].rows.extend(rows)
    return res


def summarize_runs(runs: list[EvalResult], subset: set[int] | None = None) -> dict:
    """Mean over runs (seeds) of each run's per-scenario mean; ``<key>/std`` across runs when there are several."""
    per = [r.summary(subset) for r in runs]
    keys = [k for k in per[0] if k != "num_scenarios"]
    out = {k: float(np.nanmean([p[k] for p in per])) for k in keys}
    if len(per) > 1:
        out.update({f"{k}/std": float(np.nanstd([p[k] for p in per], ddof=1)) for k in keys})
    out["num_scenarios"] = per[0]["num_scenarios"]
    out["num_seeds"] = len(per)
    return out


def easy_hard_split(reference: EvalResult, quantile: float = 0.2) -> tuple[set[int], set[int]]:
    """Indices of the top (Easy) and bottom (Hard) ``quantile`` of scenarios by the reference run's RMM."""
    rmm = np.array([r["realism/rmm"] for r in reference.rows])
    k = max(1, int(round(len(rmm) * quantile)))
    order = np.argsort(rmm)
    return set(order[-k:].tolist()), set(order[:k].tolist())


COLUMNS = [("realism/rmm", "RMM"), ("bucket/kinematic", "kinematic"), ("bucket/interactive", "interactive"),
           ("bucket/map_based", "map-based"), ("realism/collision_rate", "collision rate"),
           ("realism/offroad_rate", "offroad rate"), ("realism/offroad_rate_log_window", "offroad (log window)"),
           ("realism/min_ade", "minADE [m]"), ("realism/diversity", "diversity [m]")]


def markdown_table(summaries: dict[str, dict], columns=COLUMNS) -> str:
    cols = [c for c in columns if any(c[0] in s for s in summaries.values())]
    lines = ["| model / sampler | " + " | ".join(c[1] for c in cols) + " | scenarios |", "|---" * (len(cols) + 2) + "|"]
    for name, s in summaries.items():
        vals = []
        for key, _ in cols:
            v = s.get(key, math.nan)
            sd = s.get(key + "/std")
            vals.append(f"{v:.4f}" + (f" ± {sd:.4f}" if sd is not None else ""))
        lines.append(f"| {name} | " + " | ".join(vals) + f" | {int(s.get('num_scenarios', 0))} |")
    return "\n".join(lines)


def write_report(out_dir: str | Path, results: dict[str, EvalResult], meta: dict, example=None) -> Path:
    """Write ``report.json``, ``report.md`` and plots (entropy histogram, K_t over time, likelihood bars)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runs = {k: (v if isinstance(v, list) else [v]) for k, v in results.items()}  # name -> one run per seed
    results = {k: v[0] for k, v in runs.items()}
    summaries = {k: summarize_runs(v) for k, v in runs.items()}
    payload = {"meta": meta, "summary": summaries, "per_scenario": {k: [r.rows for r in v] for k, v in runs.items()}}
    policy_runs = [k for k, r in results.items() if r.entropy]
    md = ["# Evaluation report", "", f"Data: `{meta.get('data')}`; checkpoint: `{meta.get('checkpoint')}`; "
          f"rollouts per scenario: {meta.get('rollouts')}; seed: {meta.get('seed')}.", "", "## All scenarios", "",
          markdown_table(summaries)]
    if policy_runs:
        easy, hard = easy_hard_split(results[policy_runs[0]], meta.get("easy_hard_quantile", 0.2))
        for label, sub in (("Easy", easy), ("Hard", hard)):
            subs = {k: summarize_runs(v, sub) for k, v in runs.items()}
            payload[f"summary_{label.lower()}"] = subs
            md += ["", f"## {label} (by {policy_runs[0]} RMM, {len(sub)} scenarios)", "", markdown_table(subs)]
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
        for k in policy_runs:
            ax[0].hist(sum((r.entropy for r in runs[k]), []), bins=50, alpha=0.5, density=True, label=k)
            ks = np.array(sum((r.k_by_step for r in runs[k]), []))
            if ks.size:
                ax[1].plot(np.arange(ks.shape[1]) * 0.5 + 0.5, ks.mean(0), marker="o", label=k)
        ax[0].set_xlabel("token entropy H_t [nats]")
        ax[0].set_ylabel("density")
        ax[1].set_xlabel("time [s]")
        ax[1].set_ylabel("mean K_t")
        ax[0].legend(fontsize=7)
        ax[1].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "entropy_and_k.png", dpi=110)
        plt.close(fig)
        md += ["", "![entropy and K_t](entropy_and_k.png)"]
        for k in policy_runs:
            payload.setdefault("entropy", {})[k] = {"mean": float(np.mean(results[k].entropy)), "p90": float(np.percentile(results[k].entropy, 90))}
    like_keys = sorted({key for s in summaries.values() for key in s if key.startswith("likelihood/")})
    if like_keys:
        fig, ax = plt.subplots(figsize=(10, 3.5))
        w = 0.8 / max(len(summaries), 1)
        for j, (k, s) in enumerate(summaries.items()):
            ax.bar(np.arange(len(like_keys)) + j * w, [s.get(key, 0) for key in like_keys], w, label=k)
        ax.set_xticks(np.arange(len(like_keys)) + 0.4 - w / 2)
        ax.set_xticklabels([key.split("/", 1)[1] for key in like_keys], rotation=30, ha="right", fontsize=8)
        ax.set_ylabel("likelihood")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "likelihoods.png", dpi=110)
        plt.close(fig)
        md += ["", "![per-feature likelihoods](likelihoods.png)"]
    if example is not None:
        sc, rollouts_xy = example
        save_scenario_png(sc, out / "example_rollouts.png", rollouts=rollouts_xy)
        md += ["", "![example scene with rollouts](example_rollouts.png)"]
    (out / "report.json").write_text(json.dumps(payload, indent=1, default=float))
    (out / "report.md").write_text("\n".join(md) + "\n")
    return out
