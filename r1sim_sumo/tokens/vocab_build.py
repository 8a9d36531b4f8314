"""Building a motion vocabulary from a scenario dataset and reporting how well it reconstructs held-out tracks.

:func:`build_vocab_from_dataset` extracts 0.5 s segments of the training part of a dataset and clusters them
(:func:`r1sim_sumo.tokens.motion_vocab.build_vocab`); :func:`reconstruction_report` measures the position [m] and
heading [deg] error of rolling-matched (:mod:`r1sim_sumo.tokens.matching`) held-out tracks. Kept apart from
:mod:`~r1sim_sumo.tokens.motion_vocab` because the report needs the matching, which needs the vocabulary.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
import torch
from tqdm import tqdm

from r1sim_sumo.geometry import wrap_angle
from r1sim_sumo.scenario import AGENT_TYPES, DT_S, AgentTracks
from r1sim_sumo.tokens.constants import FRAMES_PER_TOKEN as FRAMES
from r1sim_sumo.tokens.matching import match_agents, reconstruct_states
from r1sim_sumo.tokens.motion_vocab import (
    STEPS,
    TYPES,
    MotionVocab,
    VocabBuildConfig,
    VocabError,
    build_vocab,
    extract_segments,
)

FAST_SPEED_MPS = 15.0  # [m/s] agents at least this fast get their own line in the reconstruction report


def _scenario_split(n: int, heldout_fraction: float) -> tuple[range, range]:
    n_held = int(round(n * heldout_fraction)) if n > 1 else 0
    if heldout_fraction > 0 and n > 1:
        n_held = max(n_held, 1)
    return range(0, n - n_held), range(n - n_held, n)


def build_vocab_from_dataset(
    scenarios: Sequence | Iterable,
    cfg: VocabBuildConfig | None = None,
    progress: bool = False,
    max_report_scenarios: int = 200,
) -> tuple[MotionVocab, dict]:
    """Build a vocabulary from a ScenarioDataset (or a list of Scenarios) and report its reconstruction error.

    The trailing ``cfg.heldout_fraction`` of the scenarios is held out (datasets are written in run order,
    so the tail shares fewer overlapping windows with the rest than a random split would); segments come
    from the others. Returns ``(vocab, report)``; the report is also stored in ``vocab.meta["report"]``.
    """
    cfg = cfg or VocabBuildConfig()
    scenarios = scenarios if hasattr(scenarios, "__getitem__") else list(scenarios)
    train_idx, held_idx = _scenario_split(len(scenarios), cfg.heldout_fraction)
    rng = np.random.default_rng(cfg.seed)
    pools: dict[int, list[np.ndarray]] = {t: [] for t in TYPES}
    counts = dict.fromkeys(TYPES, 0)
    it: Iterable = train_idx
    if progress:
        it = tqdm(train_idx, desc="segments", unit="scn")
    for i in it:
        tracks = scenarios[i].agents
        for t in TYPES:
            seg = extract_segments(tracks, t)
            if len(seg):
                pools[t].append(seg)
                counts[t] += len(seg)
            if counts[t] > 4 * cfg.max_segments:  # bound memory: subsample what we hold so far
                allseg = np.concatenate(pools[t])
                pools[t] = [allseg[rng.choice(len(allseg), 2 * cfg.max_segments, replace=False)]]
                counts[t] = 2 * cfg.max_segments
    segments = {t: np.concatenate(pools[t]) if pools[t] else np.zeros((0, FRAMES, 3), np.float32) for t in TYPES}
    vocab = build_vocab(segments, cfg, progress=progress)
    vocab.meta["n_train_scenarios"] = len(train_idx)
    held = [scenarios[i].agents for i in list(held_idx)[:max_report_scenarios]]
    report = reconstruction_report(vocab, held) if held else {"note": "no held-out scenarios"}
    vocab.meta["report"] = report
    return vocab, report


def reconstruction_report(vocab: MotionVocab, tracks_list: Iterable[AgentTracks], current_index: int = 10) -> dict:
    """Reconstruction error of rolling-matched tracks over the future (states ``current_index..T-1``, 8 s
    for standard 91-state windows).

    For every agent valid at all states from ``current_index`` on, tokens are matched
    by rolling matching over the whole window, and 10 Hz states are rebuilt from the matched current pose
    with the matched future tokens (:func:`reconstruct_states`). Errors against the ground truth:
    position (box centre, [m]) and heading ([deg]), mean and max over all states and agents, and the mean
    at the last state. Keys ``<type>/...`` per agent type present, ``all/...``, and ``fast/...`` for agents
    whose mean future speed is at least :data:`FAST_SPEED_MPS`.
    """
    if current_index % STEPS:
        raise VocabError(f"reconstruction_report: current_index {current_index} is not a token boundary (multiple of {STEPS})")
    k0 = current_index // STEPS
    pos_err, yaw_err, types, speeds = [], [], [], []
    for tracks in tracks_list:
        T = tracks.num_steps
        n_tok = (T - 1) // STEPS
        if n_tok <= k0:
            continue
        end = n_tok * STEPS + 1
        ok = tracks.valid[:, current_index:end].all(1)
        if not ok.any():
            continue
        tk = match_agents(tracks.select(ok).slice_steps(0, end), vocab)
        xy, yaw = reconstruct_states(
            torch.from_numpy(tk.pose_xy[:, k0]).double(), torch.from_numpy(tk.pose_yaw[:, k0]).double(),
            torch.from_numpy(tk.token[:, k0:]), vocab, torch.from_numpy(tk.agent_type))
        gx, gy = tracks.x_m[ok, current_index:end], tracks.y_m[ok, current_index:end]
        gyaw = tracks.yaw_rad[ok, current_index:end]
        xy, yaw = xy.numpy(), yaw.numpy()
        pos_err.append(np.hypot(xy[..., 0] - gx, xy[..., 1] - gy))  # [a, n]
        yaw_err.append(np.degrees(np.abs(wrap_angle(yaw - gyaw))))
        types.append(tk.agent_type)
        speeds.append(np.hypot(np.diff(gx, axis=1), np.diff(gy, axis=1)).mean(1) / DT_S)  # [a] mean speed [m/s]
    if not pos_err:
        return {"n_agents": 0, "note": "no held-out agent valid over the whole future"}
    pos, yawd, typ = np.concatenate(pos_err), np.concatenate(yaw_err), np.concatenate(types)
    fast = np.concatenate(speeds) >= FAST_SPEED_MPS

    def stats(m):
        return {"n_agents": int(m.sum()), "pos_err_mean_m": float(pos[m].mean()), "pos_err_max_m": float(pos[m].max()),
                "pos_err_final_mean_m": float(pos[m, -1].mean()), "yaw_err_mean_deg": float(yawd[m].mean()),
                "yaw_err_max_deg": float(yawd[m].max()), "horizon_s": round((pos.shape[1] - 1) * DT_S, 3)}

    report = {f"all/{k}": v for k, v in stats(np.ones(len(typ), bool)).items()}
    for t in TYPES:
        if (typ == t).any():
            report.update({f"{AGENT_TYPES[t]}/{k}": v for k, v in stats(typ == t).items()})
    if fast.any():  # motorway speeds, where a sparse vocabulary shows first
        report.update({f"fast/{k}": v for k, v in stats(fast).items()})
    return report


def format_report(report: dict) -> str:
    """One line per key, numbers rounded, for printing."""
    lines = []
    for k, v in report.items():
        lines.append(f"  {k:32s} {v:.4f}" if isinstance(v, float) and not math.isnan(v) else f"  {k:32s} {v}")
    return "\n".join(lines)
