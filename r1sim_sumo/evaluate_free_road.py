"""Free-road speed probe: does the policy speed back up when nothing is in its way?

One vehicle alone on the middle mainline lane of the bundled ``motorway_merge`` (speed limit 33.3 m/s), 1.1 s of
history at a constant speed ``v0``, then ``decisions`` policy decisions (0.5 s each) through the drop-in path
(:class:`~r1sim_sumo.sim.policy_driver.PolicyDriver`, memory on, ``topk:5`` or ``--sampler``), the vehicle following its own plans
exactly (no safety layer, nothing ahead). Every probe vehicle's desired speed (an input of policies trained with
``desired_speed_input``) is the lane's speed limit, what a SUMO driver with ``speedFactor`` 1 wants. A SUMO driver
(Krauss, accel 2.6 m/s^2) is back at its desired speed (about the limit) within a few seconds; a policy that keeps
whatever speed it has turns every slowdown behind a merge into a permanent jam (``docs/simulate``: 8 m/s platoons on an open motorway).

``free_road_speeds(policy) -> {v0: mean speed [m/s] over the last 0.5 s}``, averaged over ``seeds``.
``python -m r1sim_sumo.evaluate_free_road r1sim-nano runs/campaign_a/ckpt-002500`` prints a row per checkpoint.

``desired_speed_tracking(policy)`` (``--desired``): the same lone vehicle given other desired speeds than the limit
(20, 27, 33.3, 40 m/s) from steady 15, 22 and 26 m/s; after 12 s a driver that uses the input is near it. Returns the
end speeds and their mean absolute error [m/s] to the desired speed. Session 16 (``python -m
r1sim_sumo.evaluate_free_road r1sim-nano --seeds 3 --desired``): 7.6 m/s for the session-15 r1sim-nano (from 26 m/s
with 20 m/s desired it speeds up to 35; from 22 m/s with 33.3 or 40 desired it stays at 21-24), 7.9 for the
session-12 one: the input barely steers the speed it settles at.

Frames: internal (metres, x east, y north, yaw radians CCW from +x, box centres).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from r1sim_sumo.scenario import N_HISTORY_10HZ, AgentTracks
from r1sim_sumo.sim.policy_driver import PolicyDriver

NETWORK, LANE = "motorway_merge", "main_in_1"
START_M = 50.0  # [m] along the lane where the history starts
V0_MPS = (8.0, 20.0)  # [m/s] start speeds probed by default
DECISIONS = 16  # 8 s
PROBE_SAMPLER = "topk:5"  # the probes' token sampler (the learning curve's); ``--sampler greedy`` = the drop-in's


def lane_axis(network: str = NETWORK, lane: str = LANE):
    """``(map polylines, start point [2] [m], unit direction [2], yaw [rad], speed limit [m/s])`` of a straight
    bundled lane."""
    from r1sim_sumo.adapters.sumo_map import read_sumo_map
    from r1sim_sumo.resources import network_files

    m = read_sumo_map(network_files(network)["net"])
    i = m.lane_index[lane]
    pts = m.polylines.polyline(i).astype(np.float64)
    d = pts[-1] - pts[0]
    limit = float(m.polylines.speed_limit_mps[i])
    return m.polylines, pts[0], d / np.linalg.norm(d), float(np.arctan2(d[1], d[0])), limit


def _history(xy: np.ndarray, yaw: np.ndarray, desired_speed_mps: float = float("nan")) -> AgentTracks:
    """Vehicles' last 11 states ``xy [n, 11, 2]`` [m], ``yaw [n, 11]`` [rad] at 10 Hz (speeds from the positions); a
    single vehicle may be given as ``[11, 2]`` / ``[11]``. All get ``desired_speed_mps`` (NaN: unknown)."""
    xy, yaw = np.asarray(xy, np.float64), np.asarray(yaw, np.float64)
    if xy.ndim == 2:
        xy, yaw = xy[None], yaw[None]
    n = len(xy)
    h = AgentTracks.empty(n, N_HISTORY_10HZ)
    sp = np.linalg.norm(np.diff(xy, axis=1), axis=2) / 0.1  # [n, 10]
    sp = np.concatenate([sp[:, :1], sp], 1)
    h.x_m[:], h.y_m[:], h.yaw_rad[:], h.speed_mps[:] = xy[..., 0], xy[..., 1], yaw, sp
    h.vx_mps[:], h.vy_mps[:] = sp * np.cos(yaw), sp * np.sin(yaw)
    h.valid[:] = True
    h.ids = np.array(["probe"] if n == 1 else [f"probe{i}" for i in range(n)])
    h.agent_type[:], h.length_m[:], h.width_m[:] = 0, 5.0, 1.8
    h.desired_speed_mps = np.full(n, desired_speed_mps, np.float32)
    return h


def drive_alone(policy, v0_mps: float, seed: int = 0, decisions: int = DECISIONS, axis=None,
                sampler: str = PROBE_SAMPLER, guidance: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """10 Hz positions ``[11 + 5 * decisions, 2]`` [m] and headings [rad] of the lone vehicle (history first)."""
    road, p0, u, yaw0, limit = axis if axis is not None else lane_axis()
    drv = PolicyDriver(policy, road, sampler=sampler, seed=seed, memory=True, guidance=guidance)
    s = START_M + np.arange(N_HISTORY_10HZ) * 0.1 * v0_mps
    xy = list(p0 + s[:, None] * u)
    yaw = [yaw0] * N_HISTORY_10HZ
    for _ in range(decisions):
        plan = drv.plan(_history(np.array(xy[-N_HISTORY_10HZ:]), np.array(yaw[-N_HISTORY_10HZ:]), limit))
        xy += list(plan.xy_m[0, 1:].astype(np.float64))
        yaw += list(plan.yaw_rad[0, 1:].astype(np.float64))
    return np.array(xy), np.array(yaw)


def drive_platoon(policy, v0_mps: float, n: int = 5, headway_s: float = 1.5, seed: int = 0, decisions: int = DECISIONS,
                  axis=None, sampler: str = PROBE_SAMPLER, guidance: float = 0.0) -> np.ndarray:
    """10 Hz positions ``[n, 11 + 5 * decisions, 2]`` [m] of ``n`` vehicles in one lane, front first, all at ``v0_mps``
    with ``headway_s`` between one's rear bumper and the next one's front bumper, nothing ahead of the front one; every
    vehicle is driven by the policy and sees the others where they really are (no safety layer)."""
    road, p0, u, yaw0, limit = axis if axis is not None else lane_axis()
    drv = PolicyDriver(policy, road, sampler=sampler, seed=seed, memory=True, guidance=guidance)
    spacing = 5.0 + headway_s * v0_mps  # [m] centre to centre (5 m cars)
    front = START_M + (n - 1) * spacing
    s = front - np.arange(n)[:, None] * spacing + np.arange(N_HISTORY_10HZ)[None] * 0.1 * v0_mps  # [n, 11]
    xy = [p0 + s[..., None] * u]  # chunks [n, k, 2]
    yaw = [np.full((n, N_HISTORY_10HZ), yaw0)]
    for _ in range(decisions):
        hx, hy = np.concatenate(xy, 1)[:, -N_HISTORY_10HZ:], np.concatenate(yaw, 1)[:, -N_HISTORY_10HZ:]
        plan = drv.plan(_history(hx, hy, limit))
        xy.append(plan.xy_m[:, 1:].astype(np.float64))
        yaw.append(plan.yaw_rad[:, 1:].astype(np.float64))
    return np.concatenate(xy, 1)


@torch.no_grad()
def platoon_speeds(policy, v0_mps: float = 10.0, n: int = 5, seeds: int = 6, decisions: int = DECISIONS,
                   sampler: str = PROBE_SAMPLER, guidance: float = 0.0) -> dict[str, float]:
    """Speeds [m/s] over the last 0.5 s of a platoon started at ``v0_mps`` on a free lane, means over ``seeds``: the
    front vehicle's (nothing ahead of it: it should speed up as a lone vehicle does) and the platoon's mean."""
    axis = lane_axis()
    front, mean = [], []
    for s in range(seeds):
        xy = drive_platoon(policy, v0_mps, n, seed=s, decisions=decisions, axis=axis, sampler=sampler, guidance=guidance)
        v = np.linalg.norm(xy[:, -1] - xy[:, -6], axis=1) / 0.5  # [n]
        front.append(v[0])
        mean.append(v.mean())
    return {"front": float(np.mean(front)), "mean": float(np.mean(mean))}


@torch.no_grad()
def free_road_speeds(policy, v0s=V0_MPS, seeds: int = 6, decisions: int = DECISIONS,
                     sampler: str = PROBE_SAMPLER, guidance: float = 0.0) -> dict[float, float]:
    """Mean over ``seeds`` of the lone vehicle's speed [m/s] over the last 0.5 s, per start speed ``v0``."""
    axis = lane_axis()
    out = {}
    for v0 in v0s:
        v = [np.linalg.norm(xy[-1] - xy[-6]) / 0.5 for xy, _ in (drive_alone(policy, v0, s, decisions, axis, sampler, guidance) for s in range(seeds))]
        out[float(v0)] = float(np.mean(v))
    return out


DESIRED_MPS = (20.0, 27.0, 33.3, 40.0)  # [m/s] desired speeds of the tracking probe
TRACK_V0_MPS = (15.0, 22.0, 26.0)  # [m/s] its steady start speeds
TRACK_DECISIONS = 24  # 12 s


@torch.no_grad()
def desired_speed_tracking(policy, desired=DESIRED_MPS, v0s=TRACK_V0_MPS, seeds: int = 3,
                           decisions: int = TRACK_DECISIONS, sampler: str = PROBE_SAMPLER, guidance: float = 0.0) -> dict:
    """End speeds [m/s] (mean over the last 0.5 s) of the lone vehicle given each desired speed, from each steady
    start speed, per seed: ``{"rows": [{"desired_mps", "v0_mps", "end_mps": [per seed]}], "mae_mps": mean |end -
    desired| over all runs}``."""
    road, p0, u, yaw0, _ = lane_axis()
    rows, err = [], []
    for d in desired:
        for v0 in v0s:
            end = []
            for s in range(seeds):
                xy, _ = drive_alone(policy, v0, s, decisions, (road, p0, u, yaw0, d), sampler, guidance)
                end.append(float(np.linalg.norm(xy[-1] - xy[-6]) / 0.5))
            rows.append({"desired_mps": d, "v0_mps": v0, "end_mps": end})
            err += [abs(e - d) for e in end]
    return {"rows": rows, "mae_mps": float(np.mean(err))}


ACCEL_V0_MPS = (10.0, 15.0, 20.0, 25.0, 30.0)  # [m/s] steady start speeds of the acceleration map
ACCEL_GAPS_MPS = (0.0, 5.0, 10.0)  # [m/s] desired minus start speed
KRAUSS_MEAN_ACCEL_MPS2 = 2.6 * (1.0 - 0.5 / 2.0)  # a Krauss driver below its desired speed: accel 2.6 m/s^2 less
# sigma-0.5 dawdling (on average sigma/2 of it), per step


@torch.no_grad()
def acceleration_map(policy, v0s=ACCEL_V0_MPS, gaps=ACCEL_GAPS_MPS, seeds: int = 12, sampler: str = PROBE_SAMPLER, guidance: float = 0.0) -> dict:
    """How hard the policy speeds up from a steady history: the lone vehicle's mean acceleration [m/s^2] over its
    first 1 s (two decisions) from a steady ``v0`` with desired speed ``v0 + gap``, averaged over ``seeds``.

    A Krauss driver (SUMO's default) below its desired speed accelerates at about :data:`KRAUSS_MEAN_ACCEL_MPS2`; a
    policy that answers a gap of 5-10 m/s with a few tenths of a m/s^2 holds a steady speed in closed loop (the drop-in's
    ``free_road_speed_share``). Returns ``{"rows": [{"v0_mps", "gap_mps", "accel_mps2"}], "mean_accel_gap_mps2": mean
    over rows with a gap > 0, "mean_accel_no_gap_mps2": over rows with gap 0}``."""
    road, p0, u, yaw0, _ = lane_axis()
    rows = []
    for v0 in v0s:
        for g in gaps:
            acc = []
            for s in range(seeds):
                xy, _ = drive_alone(policy, v0, s, 2, (road, p0, u, yaw0, v0 + g), sampler, guidance)
                acc.append((float(np.linalg.norm(xy[-1] - xy[-2])) / 0.1 - v0) / 1.0)
            rows.append({"v0_mps": float(v0), "gap_mps": float(g), "accel_mps2": float(np.mean(acc))})
    gap = [r["accel_mps2"] for r in rows if r["gap_mps"] > 0]
    none = [r["accel_mps2"] for r in rows if r["gap_mps"] == 0]
    return {"rows": rows, "mean_accel_gap_mps2": float(np.mean(gap)) if gap else float("nan"),
            "mean_accel_no_gap_mps2": float(np.mean(none)) if none else float("nan")}


def main(argv=None) -> int:
    from r1sim_sumo.model.checkpoint import load_policy

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="+", help="checkpoint folders or bundled names")
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--sampler", default=PROBE_SAMPLER, help="token sampler (default topk:5, the learning curve's; the "
                    "drop-in's is greedy)")
    ap.add_argument("--guidance", type=float, default=0.0,
                    help="desired-speed guidance weight of the driver (PolicyDriver guidance; default 0 = off)")
    ap.add_argument("--platoon", action="store_true",
                    help="also drive a platoon of 5 at 10 m/s (1.5 s headways): does its front vehicle speed up too?")
    ap.add_argument("--desired", action="store_true",
                    help="also the desired-speed tracking probe (20-40 m/s desired from steady 15-26 m/s; 3 seeds)")
    ap.add_argument("--accel", action="store_true",
                    help="also the acceleration map: mean acceleration over 1 s from steady 10-30 m/s with the desired "
                         "speed 0, 5 and 10 m/s above (12 seeds)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    for ck in a.checkpoints:
        pol = load_policy(ck)
        res = free_road_speeds(pol, seeds=a.seeds, sampler=a.sampler, guidance=a.guidance)
        line = ", ".join(f"{v0:g} m/s -> {v:.1f} m/s after {DECISIONS * 0.5:g} s" for v0, v in res.items())
        if a.platoon:
            p = platoon_speeds(pol, seeds=a.seeds, sampler=a.sampler, guidance=a.guidance)
            line += f"; platoon of 5 from 10 m/s: front {p['front']:.1f} m/s, mean {p['mean']:.1f} m/s"
        if a.desired:
            t = desired_speed_tracking(pol, sampler=a.sampler, guidance=a.guidance)
            line += f"; desired-speed tracking error {t['mae_mps']:.1f} m/s (" + ", ".join(
                f"{r['desired_mps']:g} from {r['v0_mps']:g}: {np.mean(r['end_mps']):.1f}" for r in t["rows"]) + ")"
        if a.accel:
            m = acceleration_map(pol, sampler=a.sampler, guidance=a.guidance)
            line += (f"; acceleration from a steady speed {m['mean_accel_gap_mps2']:.2f} m/s^2 below the desired speed "
                     f"(Krauss ~{KRAUSS_MEAN_ACCEL_MPS2:.1f}), {m['mean_accel_no_gap_mps2']:+.2f} at it (" + ", ".join(
                         f"{r['v0_mps']:g}+{r['gap_mps']:g}: {r['accel_mps2']:+.2f}" for r in m["rows"]) + ")")
        print(f"{ck}: {line}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
