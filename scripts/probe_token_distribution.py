"""Where the policy's probability goes for a lone car with a steady past: mass on speeding-up tokens vs what top-K keeps.

The acceleration map (``python -m r1sim_sumo.evaluate_free_road CKPT --accel``) drives a lone vehicle on motorway_merge's
main line from a steady 1.1 s history at ``v0`` with a desired speed ``v0 + gap``. This looks at the first decision of
that probe: the full softmax over the vehicle tokens, each token's mean acceleration over its 0.5 s (its speed over the
last 0.1 s minus ``v0``, over 0.45 s; tokens are placed at the current pose), and prints per (v0, gap): the expected
acceleration under the full distribution and under top-K (K = 5, renormalised), the probability mass on tokens that
speed up by >= 1 m/s^2 and on those that brake by >= 2 m/s^2, and the five likeliest tokens with their accelerations [m/s^2].

    python scripts/probe_token_distribution.py CHECKPOINT [--k 5] [--decision 2 --seeds 8]

``--history-accel A`` gives the vehicle a past that speeds up at ``A`` m/s^2 to reach ``v0`` now instead of a steady
one. ``--decision N`` looks at the N-th decision instead, after the vehicle drove its first N - 1 tokens as drawn by top-5
(``--seeds`` runs, averaged): accelerations are then relative to its speed at that decision, and the likeliest tokens
are those of the first run.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--k", type=int, default=5)
    ap.add_argument("--decision", type=int, default=1, help="which decision to look at (1 = the first)")
    ap.add_argument("--seeds", type=int, default=1, help="runs averaged (the tokens before --decision are drawn)")
    ap.add_argument("--history-accel", type=float, default=0.0,
                    help="[m/s^2] the 1.1 s history speeds up at this rate to reach v0 now (0: steady, the map's probe)")
    a = ap.parse_args(argv)

    import r1sim_sumo.evaluate_free_road as efr
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.rollout.kernel import token_frames
    from r1sim_sumo.scenario import N_HISTORY_10HZ
    from r1sim_sumo.sim.policy_driver import PolicyDriver

    torch.set_num_threads(1)
    pol = load_policy(a.checkpoint)
    road, p0, u, yaw0, _ = efr.lane_axis()
    captured = {}

    class Capture:  # stands in for the sampler: keeps the logits, then draws as the real one
        def __init__(self, inner):
            self.inner = inner

        def draw(self, logits, generator=None):
            captured["logits"] = logits.detach().clone()
            return self.inner.draw(logits, generator)

    V = pol.vocab.size(0)
    below = []  # top-K expected acceleration of the rows below the desired speed (gap > 0)
    for v0 in efr.ACCEL_V0_MPS:
        for gap in efr.ACCEL_GAPS_MPS:
            rows = []
            for seed in range(a.seeds):
                drv = PolicyDriver(pol, road, sampler="topk:5", seed=seed, memory=True)
                drv.sampler = Capture(drv.sampler)
                t = (np.arange(N_HISTORY_10HZ) - (N_HISTORY_10HZ - 1)) * 0.1  # [s] -1.0 .. 0
                s = efr.START_M + v0 * t + 0.5 * a.history_accel * t * t  # speed v0 + accel * t, v0 now
                xy = list(p0 + s[:, None] * u)
                yaw = [yaw0] * N_HISTORY_10HZ
                for _ in range(a.decision):
                    v_now = float(np.linalg.norm(np.asarray(xy[-1]) - np.asarray(xy[-2]))) / 0.1  # [m/s]
                    plan = drv.plan(efr._history(np.array(xy[-N_HISTORY_10HZ:]), np.array(yaw[-N_HISTORY_10HZ:]), v0 + gap))
                    xy += list(plan.xy_m[0, 1:].astype(np.float64))
                    yaw += list(plan.yaw_rad[0, 1:].astype(np.float64))
                logp = torch.log_softmax(captured["logits"][0, 0, :V].double(), -1)  # [V] vehicle tokens
                tok = torch.arange(V)
                fxy, _ = token_frames(torch.zeros(V, 2), torch.zeros(V), tok, pol.vocab, torch.zeros(V, dtype=torch.long))
                f = fxy.double().numpy()  # [V, 6, 2] token paths from the origin
                v_end = np.linalg.norm(f[:, -1] - f[:, -2], axis=-1) / 0.1  # [V] speed over the token's last 0.1 s
                acc = (v_end - v_now) / 0.45  # [m/s^2] the token's mean acceleration from the speed now
                p = logp.exp().numpy()
                top = np.argsort(-p)[: a.k]
                pk = p[top] / p[top].sum()
                rows.append((v_now, float(p @ acc), float(pk @ acc[top]), p[acc >= 1.0].sum(), p[top][acc[top] >= 1.0].sum(),
                             p[acc <= -2.0].sum(), ", ".join(f"{p[t]:.2f}@{acc[t]:+.1f}" for t in top)))
            m = [float(np.mean([r[i] for r in rows])) for i in range(6)]
            print(f"v0 {v0:4.1f} + {gap:4.1f} (decision {a.decision}, now {m[0]:.1f} m/s): E[accel] full {m[1]:+.2f}, "
                  f"top-{a.k} {m[2]:+.2f}; mass on >= 1 m/s^2 {m[3]:.2f} (top-{a.k} keeps {m[4]:.2f}), on <= -2 m/s^2 "
                  f"{m[5]:.2f}; likeliest: {rows[0][6]}")
            if gap > 0:
                below.append(m[2])
    print(f"mean top-{a.k} E[accel] below the desired speed (gap > 0, {len(below)} rows): {np.mean(below):+.2f} m/s^2")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
