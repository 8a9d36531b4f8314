#!/usr/bin/env python3
"""Closed loop: does the policy change lanes where the log does? Per checkpoint and network, on held-out SUMO scenes.

For every policy-driven agent of the model card's closed-loop scenes (the same subset: ``--max-scenes`` drawn with
seed 0 from ``--data``, SUMO scenes only) the logged 8 s future (its matched boundary poses, what the GRPO reward
compares to) and each of ``--rollouts`` closed-loop futures are read by
:func:`r1sim_sumo.metrics.lane_changes.lane_change_direction` (>= 2.5 m sideways with the heading kept, no turn):

* ``recall``: of the agents whose log changes lanes, the share of rollouts that change lanes to the same side;
* ``spurious``: of the agents whose log keeps its lane, the share of rollouts that change lanes.
* ``recall_started`` / ``recall_unstarted``: recall for the changers already moving sideways at the start (their pose
  1 s earlier lies >= ``STARTED_M`` to the side of the start heading line) and for those not yet moving sideways: a
  policy that only carries on what its history shows does the first and not the second.
* ``must-merge``: the agents that start on a lane that ends (a lane with no successor beside one of the same edge
  that has one: motorway_merge's acceleration lane ``merge_0``, lane_drop's ``pre_drop_0``); the share of their logged
  futures and of their rollouts that change lanes (in the drop-in such vehicles are the ones that jam), and their
  mean speed [m/s] over the first token (the start) and the last token of the window, logged and in the rollouts.

Run (needs ``r1sim dataset build --config configs/dataset_eval_splits.yaml --out data/generated/default``):
``python scripts/eval_lane_changes.py start=docs/training/runs/s34_rec_long/final grpo=runs/grpo_lc_s40/iter40
--out docs/training/lane_changes_s40``. Writes ``lane_changes.json`` and ``lane_changes.md``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

import r1sim_sumo
from r1sim_sumo.evaluate import batch_generator
from r1sim_sumo.metrics.lane_changes import lane_change_direction, must_merge_lanes, poses_on_lanes
from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.batch import collate, tokenize_scenario
from r1sim_sumo.tokens.constants import CURRENT_POSE
from r1sim_sumo.train.model_card import _subset

N_COUNTS = 17
STARTED_M = 0.3
"""Sideways offset [m] of the pose 1 s before the start from the start heading line: the lane change has begun."""


def card_scenes(data: str, n: int) -> list:
    """The model card's closed-loop subset (``model_card.closed_loop``: ``n`` drawn with seed 0, SUMO scenes only)."""
    return [s for s in _subset(ScenarioDataset(data), n, 0) if s.metadata.get("source") == "sumo"]


def count_batch(policy, scs: list, rollouts: int, sampler, seed: int, j: int) -> dict[str, np.ndarray]:
    """Per network: [changer rollouts, of them matched, keeper rollouts, of them changing lanes, started-changer
    rollouts, of them matched, unstarted-changer rollouts, of them matched, must-merge rollouts, of them logged
    changing lanes, of them changing lanes]."""
    scenes = [tokenize_scenario(sc, policy.vocab) for sc in scs]
    b = collate(scenes)
    r = rollout(policy.model.eval(), policy.vocab, b, num_rollouts=rollouts, sampler=sampler,
                generator=batch_generator(seed, j))
    F = r.pose_xy.shape[-2] - 1
    fut = slice(CURRENT_POSE + 1, CURRENT_POSE + 1 + F)
    start = (b.pose_xy[:, :, CURRENT_POSE], b.pose_yaw[:, :, CURRENT_POSE], b.pose_valid[:, :, CURRENT_POSE])
    logged = lane_change_direction(b.pose_xy[:, :, fut], b.pose_yaw[:, :, fut], b.pose_valid[:, :, fut], *start)  # [B, A]
    sim = lane_change_direction(r.pose_xy[..., 1:, :], r.pose_yaw[..., 1:], r.valid[..., 1:], *start)  # [G, B, A]
    driven = r.sim_mask.bool() & start[2].bool()
    d0 = b.pose_xy[:, :, 0] - start[0]  # pose 1 s before the start, in the start frame
    side0 = -d0[..., 0] * torch.sin(start[1]) + d0[..., 1] * torch.cos(start[1])
    started = b.pose_valid[:, :, 0].bool() & (side0.abs() >= STARTED_M)
    out: dict[str, np.ndarray] = {}
    for k, sc in enumerate(scs):
        net = sc.metadata.get("network", "?")
        m = driven[k]
        ch = m & (logged[k] != 0)
        ke = m & (logged[k] == 0)
        c = out.setdefault(net, np.zeros(N_COUNTS, np.float64))
        hit = sim[:, k] == logged[k]
        for i, group in ((0, ch), (4, ch & started[k]), (6, ch & ~started[k])):
            c[i] += int(group.sum()) * rollouts
            c[i + 1] += int((hit & group).sum())
        c[2] += int(ke.sum()) * rollouts
        c[3] += int(((sim[:, k] != 0) & ke).sum())
        lanes = must_merge_lanes(sc.map)
        if lanes:
            mm = m & torch.as_tensor(poses_on_lanes(sc.map, lanes, start[0][k].double().numpy(), start[1][k].double().numpy()))
            c[8] += int(mm.sum()) * rollouts
            c[9] += int((mm & (logged[k] != 0)).sum()) * rollouts
            c[10] += int(((sim[:, k] != 0) & mm).sum())
            v0 = torch.linalg.vector_norm(b.pose_xy[k, :, CURRENT_POSE] - b.pose_xy[k, :, CURRENT_POSE - 1], dim=-1) / 0.5
            ok0 = mm & b.pose_valid[k, :, CURRENT_POSE - 1].bool()
            c[11] += float(v0[ok0].sum())
            c[12] += int(ok0.sum())
            end = CURRENT_POSE + F
            v_log = torch.linalg.vector_norm(b.pose_xy[k, :, end] - b.pose_xy[k, :, end - 1], dim=-1) / 0.5
            ok_log = mm & b.pose_valid[k, :, end].bool() & b.pose_valid[k, :, end - 1].bool()
            c[13] += float(v_log[ok_log].sum())
            c[14] += int(ok_log.sum())
            v_sim = torch.linalg.vector_norm(r.pose_xy[:, k, :, -1] - r.pose_xy[:, k, :, -2], dim=-1) / 0.5  # [G, A]
            ok_sim = mm & r.valid[:, k, :, -1].bool() & r.valid[:, k, :, -2].bool()
            c[15] += float(v_sim[ok_sim].sum())
            c[16] += int(ok_sim.sum())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="+", help="NAME=checkpoint folder (or a bundled name)")
    ap.add_argument("--data", default="data/generated/default/test")
    ap.add_argument("--max-scenes", type=int, default=40, help="scenes drawn as the model card draws them (default 40)")
    ap.add_argument("--networks", nargs="*", default=None, help="keep only the drawn scenes of these networks")
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--sampler", default="topk:5")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--batch-scenes", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", required=True, help="output folder (lane_changes.json, lane_changes.md)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    scs = card_scenes(args.data, args.max_scenes)
    if args.networks:
        scs = [s for s in scs if s.metadata.get("network") in args.networks]
    sampler = parse_sampler(args.sampler)
    results: dict[str, dict] = {}
    for spec in args.checkpoints:
        name, _, ck = spec.partition("=")
        if not ck:
            raise SystemExit(f"eval_lane_changes: '{spec}' is not NAME=checkpoint (e.g. start=docs/training/runs/s34_rec_long/final)")
        pol = r1sim_sumo.load_policy(ck)
        tot: dict[str, np.ndarray] = {}
        for j, lo in enumerate(tqdm(range(0, len(scs), args.batch_scenes), desc=name)):
            for net, c in count_batch(pol, scs[lo: lo + args.batch_scenes], args.rollouts, sampler, args.seed, j).items():
                tot[net] = tot.get(net, np.zeros(N_COUNTS, np.float64)) + c
        tot["all"] = sum(tot.values())
        results[name] = {"checkpoint": ck, "per_network": {
            net: {"changer_rollouts": int(c[0]), "recall": float(c[1] / c[0]) if c[0] else None,
                  "keeper_rollouts": int(c[2]), "spurious": float(c[3] / c[2]) if c[2] else None,
                  "started_rollouts": int(c[4]), "recall_started": float(c[5] / c[4]) if c[4] else None,
                  "unstarted_rollouts": int(c[6]), "recall_unstarted": float(c[7] / c[6]) if c[6] else None,
                  "must_merge_rollouts": int(c[8]), "must_merge_logged": float(c[9] / c[8]) if c[8] else None,
                  "must_merge_changed": float(c[10] / c[8]) if c[8] else None,
                  "must_merge_speed_start_mps": float(c[11] / c[12]) if c[12] else None,
                  "must_merge_speed_end_log_mps": float(c[13] / c[14]) if c[14] else None,
                  "must_merge_speed_end_rollouts_mps": float(c[15] / c[16]) if c[16] else None}
            for net, c in sorted(tot.items())}}
        print(name, {n: (v["recall"], v["spurious"], v["recall_started"], v["recall_unstarted"])
                     for n, v in results[name]["per_network"].items()}, flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "lane_changes.json").write_text(json.dumps({"data": args.data, "scenes": len(scs), "rollouts": args.rollouts,
                                                       "sampler": args.sampler, "seed": args.seed, "results": results}, indent=1))
    nets = sorted({n for r in results.values() for n in r["per_network"]})
    lines = [f"Lane changes in closed loop, {len(scs)} held-out SUMO scenes of `{args.data}` x {args.rollouts} rollouts "
             f"({args.sampler}, seed {args.seed}); recall = rollouts changing lanes to the logged side / rollouts of "
             "agents whose log changes lanes; spurious = rollouts changing lanes / rollouts of agents whose log keeps "
             "its lane (`python scripts/eval_lane_changes.py ...`).", "",
             "| checkpoint | " + " | ".join(f"{n} recall (n) | {n} spurious" for n in nets) + " |",
             "|---|" + "---|---|" * len(nets)]
    for name, r in results.items():
        cells = []
        for n in nets:
            v = r["per_network"].get(n)
            if v is None or v["recall"] is None:
                cells += ["-", "-" if v is None or v["spurious"] is None else f"{v['spurious']:.3f}"]
            else:
                cells += [f"{v['recall']:.3f} ({v['changer_rollouts'] // args.rollouts})", f"{v['spurious']:.3f}"]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "Recall by whether the logged lane change had begun at the start (pose 1 s earlier >= "
              f"{STARTED_M} m to the side), all networks:", "",
              "| checkpoint | begun: recall (n) | not begun: recall (n) |", "|---|---|---|"]
    for name, r in results.items():
        a = r["per_network"]["all"]
        fmt = lambda v, n: "-" if v is None else f"{v:.3f} ({n // args.rollouts})"  # noqa: E731
        lines.append(f"| {name} | {fmt(a['recall_started'], a['started_rollouts'])} | "
                     f"{fmt(a['recall_unstarted'], a['unstarted_rollouts'])} |")
    def speed(v: float | None) -> str:
        return "-" if v is None else f"{v:.1f}"

    mm_nets = [n for n in nets if n != "all" and any(r["per_network"].get(n, {}).get("must_merge_rollouts") for r in results.values())]
    lines += ["", "Agents that start on a lane that ends (must merge): share of logged futures / of rollouts that "
              "change lanes:", "", "| checkpoint | " + " | ".join(f"{n} log | {n} rollouts (n) | {n} speed at start -> at 8 s, log / rollouts [m/s]"
                                             for n in mm_nets) + " |",
              "|---|" + "---|---|---|" * len(mm_nets)]
    for name, r in results.items():
        cells = []
        for n in mm_nets:
            v = r["per_network"][n]
            cells += [f"{v['must_merge_logged']:.3f}", f"{v['must_merge_changed']:.3f} ({v['must_merge_rollouts'] // args.rollouts})",
                      " -> ".join(speed(v[k]) for k in ("must_merge_speed_start_mps", "must_merge_speed_end_log_mps"))
                      + f" / {speed(v['must_merge_speed_end_rollouts_mps'])}"]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    (out / "lane_changes.md").write_text("\n".join(lines) + "\n")
    print((out / "lane_changes.md").read_text())


if __name__ == "__main__":
    main()
