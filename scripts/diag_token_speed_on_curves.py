"""Does the tokenization itself slow vehicles down in curves? Per 0.5 s token of exact rolling matching (what the
policy is trained to predict), the token's speed (its end displacement / 0.5 s) against the logged speed over the same
0.5 s (boundary-to-boundary displacement / 0.5 s), binned by how much the logged heading turns in that 0.5 s (the
matched chain moves by exactly its tokens, so this is also the chain's speed); with ``--teacher-forced N`` also, on N windows per
network, what the policy predicts from the logged past (teacher forced, as in training): the speed of its most likely
token (greedy, the drop-in's default) and the expected speed of a top-5 draw (its five likeliest tokens,
renormalised), against the logged token's.

    python scripts/diag_token_speed_on_curves.py data/generated/rings/train [--every 5] [--checkpoint r1sim-nano]
    python scripts/diag_token_speed_on_curves.py data/generated/rings/test --teacher-forced 40

Only moving vehicles (logged speed >= ``--min-speed`` m/s) count. A token slower than the log in curves teaches the
policy to drive curves slower than the drivers it imitates (a free ring at 5.7-5.8 m/s where SUMO's drivers go 7.7-7.9,
docs/training/README.md, session 36).
"""

from __future__ import annotations

import argparse

import numpy as np

from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.matching import match_agents

TURN_BINS_RAD = (0.0, 0.05, 0.15, 0.3, 0.6, np.inf)  # |heading change| over 0.5 s [rad]
STEPS = 5  # 10 Hz states per token
START_BINS_MPS = ((0.0, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, 4.0), (4.0, np.inf))  # logged token speed from standstill


def token_speed_rows(root: str, vocab, every: int, min_speed_mps: float) -> tuple[np.ndarray, dict]:
    """Rows (|turn| [rad], logged speed, token speed [m/s], network index) of every valid vehicle token of every
    ``every``-th window, and the networks by index."""
    ds = ScenarioDataset(root)
    out = []
    nets: dict[str, int] = {}
    for i in range(0, len(ds), every):
        sc = ds[i]
        a = sc.agents
        tok = match_agents(a, vocab)
        T = a.valid.shape[1]
        b = np.arange((T - 1) // STEPS + 1) * STEPS
        veh = np.asarray(a.agent_type) == 0
        net = nets.setdefault(str(sc.metadata.get("network")), len(nets))
        for k in range(len(b) - 1):
            ok = tok.token_valid[:, k] & veh
            if not ok.any():
                continue
            i0, i1 = b[k], b[k + 1]
            d_log = np.hypot(a.x_m[:, i1] - a.x_m[:, i0], a.y_m[:, i1] - a.y_m[:, i0]) / (STEPS * 0.1)
            turn = np.abs(np.angle(np.exp(1j * (a.yaw_rad[:, i1] - a.yaw_rad[:, i0]))))
            t = np.maximum(tok.token[:, k], 0)
            end = vocab.traj[0][t, -1, :2]
            d_tok = np.hypot(end[:, 0], end[:, 1]) / (STEPS * 0.1)
            m = ok & (d_log >= min_speed_mps)
            out.append(np.stack([turn[m], d_log[m], d_tok[m], np.full(int(m.sum()), net)], 1))
    rows = np.concatenate(out) if out else np.zeros((0, 4))
    return rows, {v: k for k, v in nets.items()}


def teacher_forced_rows(root: str, policy, per_network: int) -> tuple[np.ndarray, dict]:
    """Rows (|logged turn| [rad], logged token speed, greedy token speed, top-5 expected speed [m/s], network index,
    the logged previous token's speed [m/s]) of every
    valid vehicle token from the third on (two tokens of logged past at least) of ``per_network`` windows per network."""
    import torch

    from r1sim_sumo.evaluate import sumo_scenes_by_network
    from r1sim_sumo.tokens.batch import collate, tokenize_scenario

    end = torch.as_tensor(policy.vocab.traj[0])[:, -1]  # [V, 3] end pose of each vehicle token (x, y [m], yaw [rad])
    tok_speed = end[:, :2].norm(dim=-1) / (STEPS * 0.1)  # [V] mean speed of each token [m/s]
    ds = ScenarioDataset(root)
    scenes = sumo_scenes_by_network(ds, per_network, every=max(1, len(ds) // (4 * per_network)))
    out, nets = [], {}
    for net, scs in sorted(scenes.items()):
        n = nets.setdefault(net, len(nets))
        for sc in scs:
            b = collate([tokenize_scenario(sc, policy.vocab)])
            veh = (b.agent_type[0] == 0) & b.agent_mask[0].bool()
            ok = b.agent_token_valid[0].bool() & veh[:, None]
            with torch.no_grad():
                logits = policy.model(b)[0]  # [A, F, V] teacher forced
            V = len(end)
            for k in range(2, b.agent_token.shape[-1]):
                m = ok[:, k]
                if not m.any():
                    continue
                g = b.agent_token[0, m, k]
                lg = logits[m, k, :V].float()
                top = lg.topk(5, dim=-1)
                top5 = (top.values.softmax(-1) * tok_speed[top.indices]).sum(-1)
                prev = tok_speed[b.agent_token[0, m, k - 1].clamp_min(0)]  # the logged token before [m/s]
                out.append(torch.stack([end[g, 2].abs(), tok_speed[g], tok_speed[lg.argmax(-1)], top5,
                                        torch.full((int(m.sum()),), float(n)), prev], 1).numpy())
    return (np.concatenate(out) if out else np.zeros((0, 6))), {v: k for k, v in nets.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+", help="dataset split folders (e.g. data/generated/rings/train)")
    ap.add_argument("--every", type=int, default=5, help="look at every n-th window")
    ap.add_argument("--min-speed", type=float, default=2.0, help="only tokens whose logged speed is at least this [m/s]")
    ap.add_argument("--checkpoint", default="r1sim-nano", help="the policy whose vocabulary matches (default r1sim-nano)")
    ap.add_argument("--teacher-forced", type=int, default=0, metavar="N",
                    help="also the policy's teacher-forced token speeds on N windows per network")
    a = ap.parse_args(argv)
    import r1sim_sumo

    policy = r1sim_sumo.load_policy(a.checkpoint)
    vocab = policy.vocab
    for root in a.datasets:
        rows, nets = token_speed_rows(root, vocab, a.every, a.min_speed)
        print(f"{root}: {len(rows)} vehicle tokens (every {a.every}th window, logged speed >= {a.min_speed:g} m/s), "
              f"vocabulary of {a.checkpoint}")
        for n in sorted(nets):
            sel = rows[:, 3] == n
            r = rows[sel]
            print(f"  {nets[n]}: |heading change| per 0.5 s [rad]: tokens | logged speed | token - logged [m/s] (mean, "
                  "and share of tokens slower than the log by > 0.5 m/s)")
            for lo, hi in zip(TURN_BINS_RAD[:-1], TURN_BINS_RAD[1:], strict=True):
                q = r[(r[:, 0] >= lo) & (r[:, 0] < hi)]
                if not len(q):
                    continue
                dt = q[:, 2] - q[:, 1]
                print(f"    {lo:4.2f} .. {hi:4.2f}  {len(q):7d} | {q[:, 1].mean():6.2f} | {dt.mean():+6.3f} "
                      f"({(dt < -0.5).mean():5.1%} slower)")
        if not a.teacher_forced:
            continue
        rows, nets = teacher_forced_rows(root, policy, a.teacher_forced)
        print(f"{root}: teacher forced, {a.checkpoint}, {a.teacher_forced} windows per network, vehicle tokens 3..16")
        for n in sorted(nets):
            r = rows[rows[:, 4] == n]
            print(f"  {nets[n]}: |logged heading change| per 0.5 s [rad]: tokens | logged token speed | greedy - logged "
                  "| top-5 expected - logged [m/s]")
            for lo, hi in zip(TURN_BINS_RAD[:-1], TURN_BINS_RAD[1:], strict=True):
                q = r[(r[:, 0] >= lo) & (r[:, 0] < hi) & (r[:, 1] >= a.min_speed)]
                if len(q):
                    print(f"    {lo:4.2f} .. {hi:4.2f}  {len(q):7d} | {q[:, 1].mean():6.2f} | {(q[:, 2] - q[:, 1]).mean():+6.3f} "
                          f"| {(q[:, 3] - q[:, 1]).mean():+6.3f}")
            print("    starting from a standstill (logged token before < 0.5 m/s), by the logged token's speed [m/s]: "
                  "tokens | greedy - logged | top-5 expected - logged [m/s]")
            still = r[r[:, 5] < 0.5]
            for lo, hi in START_BINS_MPS:
                q = still[(still[:, 1] >= lo) & (still[:, 1] < hi)]
                if len(q):
                    print(f"    {lo:4.1f} .. {hi:4.1f}  {len(q):7d} | {(q[:, 2] - q[:, 1]).mean():+6.3f} | "
                          f"{(q[:, 3] - q[:, 1]).mean():+6.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
