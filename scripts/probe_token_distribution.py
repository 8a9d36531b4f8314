"""Where the policy's probability goes for a lone car with a steady past: mass on speeding-up tokens vs what top-K keeps.

The acceleration map (``python -m r1sim_sumo.evaluate_free_road CKPT --accel``) drives a lone vehicle on motorway_merge's
main line from a steady 1.1 s history at ``v0`` with a desired speed ``v0 + gap``. This looks at the first decision of
that probe: the full softmax over the vehicle tokens, each token's mean acceleration over its 0.5 s (its speed over the
last 0.1 s minus ``v0``, over 0.45 s; tokens are placed at the current pose), and prints per (v0, gap): the expected
acceleration under the full distribution and under top-K (K = 5, renormalised), the probability mass on tokens that
speed up by >= 1 m/s^2 and on those that brake by >= 2 m/s^2, and the five likeliest tokens with their accelerations [m/s^2].

    python scripts/probe_token_distribution.py CHECKPOINT [--k 5]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--k", type=int, default=5)
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
    for v0 in efr.ACCEL_V0_MPS:
        for gap in efr.ACCEL_GAPS_MPS:
            drv = PolicyDriver(pol, road, sampler="topk:5", seed=0, memory=True)
            drv.sampler = Capture(drv.sampler)
            s = efr.START_M + np.arange(N_HISTORY_10HZ) * 0.1 * v0
            xy = p0 + s[:, None] * u
            drv.plan(efr._history(xy, np.full(N_HISTORY_10HZ, yaw0), v0 + gap))
            logp = torch.log_softmax(captured["logits"][0, 0, :V].double(), -1)  # [V] vehicle tokens
            tok = torch.arange(V)
            fxy, _ = token_frames(torch.zeros(V, 2), torch.zeros(V), tok, pol.vocab, torch.zeros(V, dtype=torch.long))
            f = fxy.double().numpy()  # [V, 6, 2] token paths from the origin
            v_end = np.linalg.norm(f[:, -1] - f[:, -2], axis=-1) / 0.1  # [V] speed over the token's last 0.1 s
            acc = (v_end - v0) / 0.45  # [m/s^2] the token's mean acceleration from a steady v0
            p = logp.exp().numpy()
            top = np.argsort(-p)[: a.k]
            pk = p[top] / p[top].sum()
            print(f"v0 {v0:4.1f} + {gap:4.1f}: E[accel] full {float(p @ acc):+.2f}, top-{a.k} {float(pk @ acc[top]):+.2f}; "
                  f"mass on >= 1 m/s^2 {p[acc >= 1.0].sum():.2f} (top-{a.k} keeps {p[top][acc[top] >= 1.0].sum():.2f}), "
                  f"on <= -2 m/s^2 {p[acc <= -2.0].sum():.2f}; "
                  "likeliest: " + ", ".join(f"{p[t]:.2f}@{acc[t]:+.1f}" for t in top))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
