"""Longitudinal safety filter for policy-driven vehicles: never faster than a safe following speed.

The learned policy decides *where* a vehicle goes (its 0.5 s path); this filter only limits *how fast* it
travels along that path, so that it does not drive into the vehicle ahead. It is what keeps a drop-in
controller from producing rear-end crashes that SUMO-native traffic never has (the policy follows closer than
SUMO's safe gap: ``scripts/diag_follow_leader.py``, docs/simulate/report.md). Off by default in evaluation (raw policy), on by
default in :class:`~r1sim_sumo.sim.sumo_controller.SumoController` (``safety="krauss"``).

Leader: the nearest other vehicle whose box lies in the corridor ahead of the ego along its planned path.
The corridor is the ego's width plus the other box's lateral extent plus ``lateral_margin_m``, bent with the
plan's curvature ``kappa`` (lateral offset measured from the arc ``lat - kappa * lon^2 / 2``), and reaches
``max(min_lookahead_m, speed * lookahead_s)`` ahead. An oncoming vehicle (heading more than 135 degrees away)
counts only head-on: straight ahead with the boxes overlapping laterally, no margin, no bend (so a queue on the
other lane of a two-way road is not a leader). Safe speed: SUMO's Krauss ``v_safe``,

    v_safe = v_l + (g - v_l * tau) / ((v + v_l) / (2 b) + tau),

with ``g`` the bumper-to-bumper gap minus ``min_gap_m``, ``v_l`` the leader's speed along the ego's heading
(>= 0), ``v`` the ego's speed, ``tau`` [s] and ``b`` [m/s^2]; the filtered speed never drops faster than the
emergency deceleration (a crash that no real braking could avoid still happens and is counted).

Frames: internal (metres, x east, y north, yaw radians CCW from +x, box centres); speeds [m/s].
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

ONCOMING_RAD = np.deg2rad(135.0)  # [rad] heading difference from which another vehicle is oncoming
TREE_MIN_PAIRS = 20_000  # ego x vehicle pairs from which leader_gap looks only at the k-d tree's candidates


@dataclass(frozen=True)
class SafetyFilter:
    """Krauss-style safe-speed limit along the planned path (parameters as SUMO's defaults)."""

    tau_s: float = 1.0  # [s] reaction time
    decel_mps2: float = 4.5  # [m/s^2] comfortable deceleration b
    emergency_decel_mps2: float = 9.0  # [m/s^2] the most a step may slow down
    min_gap_m: float = 2.0  # [m] standstill gap kept to the leader
    lateral_margin_m: float = 0.3  # [m] added to the half-widths for the corridor
    lookahead_s: float = 4.0  # [s] corridor length = max(min_lookahead_m, speed * lookahead_s)
    min_lookahead_m: float = 20.0  # [m]

    def leader_gap(self, ego: np.ndarray, x, y, yaw, length, width, speed, kappa=None):
        """Nearest vehicle ahead in each ego's corridor.

        :param ego: ``[C]`` row indices of the filtered vehicles in the state arrays ``x, y, yaw, length, width,
            speed`` (``[N]`` each: box centre [m], heading [rad], size [m], speed [m/s]).
        :param kappa: ``[C]`` curvature [1/m] of each ego's planned path (``None`` = straight).
        :return: ``gap [C]`` bumper-to-bumper distance [m] to the leader (``inf`` = none), ``lead_speed [C]``
            its speed along the ego's heading [m/s] (>= 0), ``lead [C]`` its row index (-1 = none).

        From :data:`TREE_MIN_PAIRS` ego-vehicle pairs on, only the vehicles a k-d tree finds near each ego are tested
        (:meth:`_candidates`; 700 vehicles on a city grid: 29 ms per call for all pairs under cProfile, session 27); the same
        leader, gap and speed as testing every pair (``tests/test_safety_filter.py``).
        """
        x, y, yaw, length, width, speed = (np.asarray(a, np.float64) for a in (x, y, yaw, length, width, speed))
        ego = np.asarray(ego, np.int64)
        C, N = len(ego), len(x)
        gap = np.full(C, np.inf)
        lead_v = np.zeros(C)
        lead = np.full(C, -1, np.int64)
        if C == 0 or N < 2:
            return gap, lead_v, lead
        kappa = None if kappa is None else np.asarray(kappa, np.float64)
        if C * N >= TREE_MIN_PAIRS:
            e, j = self._candidates(ego, x, y, length, width, speed, kappa)  # [P] each: ego row, other vehicle
        else:
            e, j = np.repeat(np.arange(C), N), np.tile(np.arange(N), C)  # every pair, ego-major, others in order
        g, ok, dpsi = self._corridor_gap(ego[e], j, x, y, yaw, length, width, speed, None if kappa is None else kappa[e])
        ok &= j != ego[e]
        if not ok.any():
            return gap, lead_v, lead
        e, j, g, dpsi = e[ok], j[ok], g[ok], dpsi[ok]
        first = np.lexsort((j, g, e))  # per ego: the smallest gap, the lowest index among equal gaps (as argmin)
        e, j, g, dpsi = e[first], j[first], g[first], dpsi[first]
        head = np.r_[True, e[1:] != e[:-1]]
        e, j, g, dpsi = e[head], j[head], g[head], dpsi[head]
        gap[e], lead[e] = g, j
        lead_v[e] = np.maximum(speed[j] * np.cos(dpsi), 0.0)
        return gap, lead_v, lead

    def _corridor_gap(self, ei, j, x, y, yaw, length, width, speed, kappa):
        """Per pair (ego vehicle ``ei [P]``, other ``j [P]``): the bumper-to-bumper gap [m] along the ego's heading,
        whether the other box lies in the ego's corridor (ahead, within reach, laterally inside), and the heading
        difference [rad]. ``kappa [P]``: the ego's path curvature [1/m] or ``None``."""
        c, s = np.cos(yaw[ei]), np.sin(yaw[ei])
        dx, dy = x[j] - x[ei], y[j] - y[ei]
        lon = dx * c + dy * s
        lat_straight = dy * c - dx * s
        lat = lat_straight if kappa is None else lat_straight - 0.5 * kappa * lon * lon
        dpsi = yaw[j] - yaw[ei]
        cd, sd = np.abs(np.cos(dpsi)), np.abs(np.sin(dpsi))
        half_lon = 0.5 * (cd * length[j] + sd * width[j])  # other box's extent along the ego heading
        half_lat = 0.5 * (sd * length[j] + cd * width[j])
        reach = np.maximum(self.min_lookahead_m, np.abs(speed[ei]) * self.lookahead_s)
        g = lon - 0.5 * length[ei] - half_lon  # bumper-to-bumper gap
        inside = (lon > 0) & (g < reach) & (np.abs(lat) < 0.5 * width[ei] + half_lat + self.lateral_margin_m)
        # an oncoming box (heading more than ONCOMING_RAD away) is a leader only when it is head-on in the ego's own
        # lane: straight ahead and laterally overlapping without margin. Beside it (the other direction's lane of a
        # two-way road, 3-3.5 m away) the bent, widened corridor would otherwise take a queue on the opposite lane for a
        # standing leader and brake every vehicle leaving a roundabout or junction past it.
        oncoming = np.cos(dpsi) < np.cos(ONCOMING_RAD)
        inside &= ~oncoming | (np.abs(lat_straight) < 0.5 * width[ei] + half_lat)
        return g, inside, dpsi

    def _candidates(self, ego, x, y, length, width, speed, kappa):
        """Pairs (ego row, other vehicle) that can lie in an ego's corridor, from a k-d tree over the centres: every
        other box in the corridor has its centre within ``sqrt(L^2 + (B + |kappa| L^2 / 2)^2)`` of the ego's, with
        ``L`` the reach plus half the ego's length plus the largest half-diagonal of any box and ``B`` half the ego's
        width plus that half-diagonal plus the margin (a box's extent along any direction is at most its
        half-diagonal). Per ego the others come in index order, so the nearest-gap pick is the dense path's."""
        from scipy.spatial import cKDTree

        h = 0.5 * float(np.hypot(length, width).max())
        reach = np.maximum(self.min_lookahead_m, np.abs(speed[ego]) * self.lookahead_s)
        L = reach + 0.5 * length[ego] + h
        B = 0.5 * width[ego] + h + self.lateral_margin_m
        if kappa is not None:
            B = B + 0.5 * np.abs(kappa) * L * L
        r = np.hypot(L, B) * (1.0 + 1e-9) + 1e-6
        xy = np.stack([x, y], -1)
        lists = cKDTree(xy).query_ball_point(xy[ego], r, return_sorted=True)
        n = np.fromiter((len(a) for a in lists), np.int64, len(lists))
        j = np.fromiter(itertools.chain.from_iterable(lists), np.int64, int(n.sum()))
        return np.repeat(np.arange(len(ego)), n), j

    def safe_speed(self, v: np.ndarray, gap: np.ndarray, lead_speed: np.ndarray, decel_mps2=None,
                   min_gap_m: float | None = None) -> np.ndarray:
        """Krauss safe speed [m/s] ``[C]`` for ego speeds ``v``, gaps [m] and leader speeds [m/s] (``inf`` = free);
        ``decel_mps2`` ``[C]`` each ego's comfortable deceleration (default ``self.decel_mps2``), ``min_gap_m`` the
        gap kept at standstill (default ``self.min_gap_m``; 0 for a stop line)."""
        v, gap, vl = (np.asarray(a, np.float64) for a in (v, gap, lead_speed))
        b = self.decel_mps2 if decel_mps2 is None else np.asarray(decel_mps2, np.float64)
        g = gap - (self.min_gap_m if min_gap_m is None else min_gap_m)
        with np.errstate(invalid="ignore"):
            vs = vl + (g - vl * self.tau_s) / ((np.maximum(v, 0.0) + vl) / (2.0 * b) + self.tau_s)
        return np.where(np.isfinite(gap), np.maximum(vs, 0.0), np.inf)

    def allowed(self, v_now: np.ndarray, v_safe: np.ndarray, dt_s: float, emergency_decel_mps2=None) -> np.ndarray:
        """The most a vehicle may drive this step [m/s]: ``v_safe``, but slowing from ``v_now`` by at most the emergency
        deceleration per step (``[C]`` per vehicle or the default) and never below 0."""
        e = self.emergency_decel_mps2 if emergency_decel_mps2 is None else np.asarray(emergency_decel_mps2, np.float64)
        floor = np.maximum(np.asarray(v_now, np.float64) - e * dt_s, 0.0)
        return np.maximum(np.asarray(v_safe, np.float64), floor)

    def limit(self, v_plan: np.ndarray, v_now: np.ndarray, v_safe: np.ndarray, dt_s: float,
              emergency_decel_mps2=None) -> np.ndarray:
        """Speed [m/s] to drive this step: the plan's, capped by :meth:`allowed`."""
        return np.minimum(np.asarray(v_plan, np.float64), self.allowed(v_now, v_safe, dt_s, emergency_decel_mps2))


def path_arc_length(xy: np.ndarray) -> np.ndarray:
    """Cumulative arc length [m] ``[..., F]`` of paths ``xy [..., F, 2]`` (0 at frame 0)."""
    seg = np.linalg.norm(np.diff(xy, axis=-2), axis=-1)
    return np.concatenate([np.zeros(seg.shape[:-1] + (1,)), np.cumsum(seg, axis=-1)], axis=-1)


def point_along(xy: np.ndarray, yaw: np.ndarray, arc: np.ndarray, s: np.ndarray, extrapolate: bool = False):
    """Pose at arc length ``s [n]`` along each path ``xy [n, F, 2]``, ``yaw [n, F]`` (``arc [n, F]`` from
    :func:`path_arc_length`): linear interpolation between frames, yaw unwrapped. Returns ``xy [n, 2], yaw [n]``.
    ``s`` is clipped to the path, or with ``extrapolate`` continues along the last segment past its end (along the
    last frame's heading when that segment has no length, e.g. a plan that stands still)."""
    n, F = arc.shape
    s = np.maximum(s, 0.0) if extrapolate else np.clip(s, 0.0, arc[:, -1])
    i = np.clip((arc[:, 1:] < s[:, None]).sum(1), 0, F - 2)  # segment index: arc[i] <= s <= arc[i+1]
    r = np.arange(n)
    a0, a1 = arc[r, i], arc[r, i + 1]
    w = np.where(a1 > a0, (s - a0) / np.maximum(a1 - a0, 1e-12), 1.0)
    p = xy[r, i] + w[:, None] * (xy[r, i + 1] - xy[r, i])
    y0 = yaw[r, i]
    dyaw = np.arctan2(np.sin(yaw[r, i + 1] - y0), np.cos(yaw[r, i + 1] - y0))
    h = y0 + w * dyaw
    if extrapolate:  # a last segment without length gives no direction: go on along the last frame's heading
        flat = (s > arc[:, -1]) & ~(a1 > a0)
        if flat.any():
            d = (s - arc[:, -1])[flat]
            h = np.array(h, copy=True)
            h[flat] = yaw[flat, -1]
            p[flat] = xy[flat, -1] + d[:, None] * np.stack([np.cos(h[flat]), np.sin(h[flat])], -1)
    return p, h


def path_curvature(yaw: np.ndarray, arc: np.ndarray, min_length_m: float = 1.0) -> np.ndarray:
    """Mean curvature [1/m] ``[n]`` of each planned path (heading change / length; 0 for paths shorter than
    ``min_length_m``)."""
    d = yaw[:, -1] - yaw[:, 0]
    d = np.arctan2(np.sin(d), np.cos(d))
    L = arc[:, -1]
    return np.where(L >= min_length_m, d / np.maximum(L, 1e-9), 0.0)
