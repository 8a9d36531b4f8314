"""After a steady vehicle's first speed-up in the log, does the next 0.5 s speed up again or step back?

For every vehicle of a scenario dataset split and every 0.5 s boundary, the mean speed over each 0.5 s token (boundary
displacement / 0.5 s). A "first speed-up" is a token at least ``--gain`` m/s faster than the one before, after two
tokens within 0.2 m/s of each other (a steady past), at >= ``--min-speed`` m/s and at least 2 m/s below the vehicle's
desired speed (where the data records it). Prints how the next token goes: faster again by >= ``--gain``
(a sustained acceleration), back by <= -0.2 m/s (a fluctuation that reverts) or neither, per network.

    python scripts/speed_up_runs.py data/generated/desired/train [--max-scenes 400]
"""

from __future__ import annotations

import argparse
import collections

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("split", help="a scenario dataset split folder (r1sim dataset build ... /train)")
    ap.add_argument("--max-scenes", type=int, default=400, help="scenes read, spread evenly over the split")
    ap.add_argument("--gain", type=float, default=0.4, help="[m/s] a token this much faster than the one before")
    ap.add_argument("--min-speed", type=float, default=8.0, help="[m/s] only vehicles at least this fast")
    a = ap.parse_args(argv)

    from r1sim_sumo.scenario import ScenarioDataset

    ds = ScenarioDataset(a.split)
    count: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for i in range(0, len(ds), max(1, len(ds) // a.max_scenes)):
        sc = ds[i]
        ag = sc.agents
        net = str(sc.metadata.get("network", sc.metadata.get("source", "?")))
        b = np.arange(0, ag.num_steps, 5)  # token boundaries (10 Hz states)
        x, y, ok = ag.x_m[:, b], ag.y_m[:, b], ag.valid[:, b]
        v = np.hypot(np.diff(x, axis=1), np.diff(y, axis=1)) / 0.5  # [A, K] mean speed per token [m/s]
        vok = ok[:, 1:] & ok[:, :-1]
        desired = ag.desired_speed_mps if ag.desired_speed_mps is not None else np.full(ag.num_agents, np.nan)
        for k in range(2, v.shape[1] - 1):
            sel = (vok[:, k - 2] & vok[:, k - 1] & vok[:, k] & vok[:, k + 1] & (ag.agent_type == 0)
                   & (np.abs(v[:, k - 1] - v[:, k - 2]) < 0.2) & (v[:, k] - v[:, k - 1] >= a.gain)
                   & (v[:, k - 1] >= a.min_speed) & ~(desired - v[:, k - 1] < 2.0))
            for j in np.flatnonzero(sel):
                d = v[j, k + 1] - v[j, k]
                count[net]["again" if d >= a.gain else "back" if d <= -0.2 else "level"] += 1
    for net, c in sorted(count.items()):
        n = sum(c.values())
        print(f"{net}: {n} first speed-ups after a steady second; next token faster again {c['again'] / n:.0%}, "
              f"back {c['back'] / n:.0%}, level {c['level'] / n:.0%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
