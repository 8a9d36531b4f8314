"""How often SUMO's own drivers, cruising steadily below their desired speed with the road ahead free, speed up: the
state the policy meets after every slow-down in the drop-in, and copies its steady past in (session 49).

Records each network for ``--duration`` s after a 120 s warm-up (the reference generator, windows every 2 s), with and
without the desired-speed steps of :mod:`r1sim_sumo.data.desired_steps`, and counts, at each window's current index,
the agent-states that are

- alone: no other agent within ``--ahead`` m ahead and ``--half-width`` m to either side (8 m: any lane; 1.8 m: own lane),
- steady: speed changed by less than 0.5 m/s over the last 1 s, faster than 5 m/s,
- below: desired speed (SUMO's lane limit x speedFactor, the recorded input) more than 3 m/s above the speed,

and how many of those speed up by more than 0.8 m/s^2 over the next 2 s.

    python scripts/steady_below_desired_share.py --networks motorway_merge lane_drop --rate 90
"""

from __future__ import annotations

import argparse

import numpy as np

from r1sim_sumo.data.sumo_reference import RunStats, SumoGenConfig, iter_sumo_scenarios

STEADY_MPS, BELOW_MPS, MIN_SPEED_MPS, SPEEDING_UP_MPS2 = 0.5, 3.0, 5.0, 0.8


def others_in_own_frame(a, t0: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lon, lat, other)`` ``[A, A]`` at step ``t0``: agent j's box centre in agent i's frame, metres ahead along
    i's heading and to its left, and whether j is a valid agent other than i."""
    x, y, h, v = a.x_m[:, t0], a.y_m[:, t0], a.yaw_rad[:, t0], a.valid[:, t0]
    dx, dy = x[None, :] - x[:, None], y[None, :] - y[:, None]
    lon = np.cos(h)[:, None] * dx + np.sin(h)[:, None] * dy
    lat = -np.sin(h)[:, None] * dx + np.cos(h)[:, None] * dy
    other = np.repeat(v[None, :], len(v), 0)
    np.fill_diagonal(other, False)
    return lon, lat, other


def alone(a, t0: int, ahead_m: float, half_width_m: float) -> np.ndarray:
    """``[A]`` bool: no other valid agent within ``ahead_m`` ahead (box centres, along the agent's heading) and
    ``half_width_m`` to either side at step ``t0``."""
    lon, lat, other = others_in_own_frame(a, t0)
    return ~((lon > 0.5) & (lon < ahead_m) & (np.abs(lat) < half_width_m) & other).any(1)


def count(network: str, seed: int, duration_s: float, rate: float, ahead_m: float, half_width_m: float) -> dict:
    st = RunStats()
    cfg = SumoGenConfig(network=network, seed=seed, duration_s=duration_s, warmup_s=120.0,
                        desired_steps_per_vehicle_hour=rate)
    n = n_alone = n_state = n_up = 0
    for sc in iter_sumo_scenarios(cfg, stats=st):
        a, t0 = sc.agents, 10  # the current index of a window
        if a.desired_speed_mps is None:
            continue
        ok = a.valid[:, t0] & a.valid[:, t0 - 10] & a.valid[:, t0 + 20]
        free = ok & alone(a, t0, ahead_m, half_width_m)
        v0, v_past, v_next = a.speed_mps[:, t0], a.speed_mps[:, t0 - 10], a.speed_mps[:, t0 + 20]
        state = free & (np.abs(v0 - v_past) < STEADY_MPS) & (v0 > MIN_SPEED_MPS) & (a.desired_speed_mps - v0 > BELOW_MPS)
        n, n_alone, n_state = n + int(ok.sum()), n_alone + int(free.sum()), n_state + int(state.sum())
        n_up += int((state & ((v_next - v0) / 2.0 > SPEEDING_UP_MPS2)).sum())
    return {"states": n, "alone": n_alone, "steady_below": n_state, "speeding_up": n_up,
            "events": int(st.extra.get("desired_step_events", 0))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--networks", nargs="+", default=["motorway_merge", "lane_drop"])
    ap.add_argument("--seed", type=int, default=600000)
    ap.add_argument("--duration", type=float, default=240.0, help="recorded seconds after the warm-up")
    ap.add_argument("--rate", type=float, default=90.0, help="desired-speed steps per vehicle-hour of the second run")
    ap.add_argument("--ahead", type=float, default=80.0, help="[m] nothing this far ahead ...")
    ap.add_argument("--half-width", type=float, default=8.0, help="[m] ... within this far to either side")
    a = ap.parse_args(argv)
    for net in a.networks:
        for rate in (0.0, a.rate):
            c = count(net, a.seed, a.duration, rate, a.ahead, a.half_width)
            print(f"{net} steps/veh-h {rate:g} ({c['events']} events): {c['states']} agent-states, alone {c['alone']}, "
                  f"alone + steady + desired > {BELOW_MPS:g} m/s above: {c['steady_below']}, of which speeding up "
                  f"{c['speeding_up']} ({c['speeding_up'] / max(c['steady_below'], 1):.0%})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
