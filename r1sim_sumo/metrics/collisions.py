"""Interaction features between agents' oriented boxes: collisions, distance to nearest object, TTC.

All functions take ``[R, A, T]`` tracks (``R`` rollouts, ``A`` agents, ``T`` steps at 10 Hz; internal frame,
box centres [m], yaw [rad]) with box sizes ``[A]`` and validity ``[R, A, T]``, and return ``[R, A, T]``.
Work is fully vectorised over pairs as ``[Rc, T, A, A]`` arrays, chunked over rollouts to bound memory.

* Collision flags use :func:`r1sim_sumo.geometry.boxes_overlap` (the one shared SAT test); invalid agents
  and self-pairs are ignored.
* Distance to the nearest object is the signed box-to-box distance. Separated boxes: the exact Euclidean
  distance between two convex polygons, i.e. the smallest distance from a corner of either box to the
  other box (each corner measured in the other box's frame as a point-to-rectangle distance).
  Overlapping boxes (per ``boxes_overlap``): minus the penetration depth, the smallest overlap of the two
  boxes' projections over the 4 box axes (the minimum translation distance). WOSAC instead rounds box
  corners (factor 0.7) before measuring; we keep sharp rectangles so that "negative" means exactly
  "colliding" as flagged by the SAT test. No other valid object: ``+inf`` (clipped by the histogram).
* Time to collision follows WOSAC ("sim agents" metrics, interaction features): for each agent, the
  objects *ahead* in its frame (positive bumper-to-bumper longitudinal gap, lateral overlap of the boxes
  in the agent's frame, heading difference <= 75 deg, or <= 10 deg when the lateral overlap is < 0.5 m)
  are candidates; the nearest one (smallest gap) is the leader; ``TTC = gap / (v_agent - v_leader)``
  when closing, capped at 5 s, and 5 s when there is no leader or the gap is opening. Speeds are the
  linear speeds of :mod:`r1sim_sumo.metrics.kinematics`. Heading differences are wrapped to [0, pi].
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from r1sim_sumo.geometry import box_corners, boxes_overlap, wrap_angle

MAX_TTC_S = 5.0  # [s] cap and value when no object is ahead (WOSAC)
TTC_MAX_HEADING_DIFF_RAD = math.radians(75.0)
TTC_MAX_HEADING_DIFF_SMALL_OVERLAP_RAD = math.radians(10.0)
TTC_SMALL_OVERLAP_M = 0.5
_PAIR_BUDGET = 4_000_000  # [Rc * T * A * A] elements per chunk (~ a few hundred MB of temporaries at most)


class InteractionFeatures(NamedTuple):
    """``[R, A, T]`` each: ``collision`` bool, ``distance_m`` signed [m], ``ttc_s`` [s] in [0, 5]."""

    collision: np.ndarray
    distance_m: np.ndarray
    ttc_s: np.ndarray


class _Pairs(NamedTuple):
    """One chunk in ``[Rc, T, A]`` layout, ``i`` = evaluated agent (axis -2), ``j`` = other (axis -1)."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    hl: np.ndarray  # [A] half length [m]
    hw: np.ndarray  # [A] half width [m]
    pair_valid: np.ndarray  # [Rc, T, A, A] both valid and i != j


def _chunks(R: int, T: int, A: int):
    step = max(1, _PAIR_BUDGET // max(1, T * A * A))
    for r0 in range(0, R, step):
        yield slice(r0, min(R, r0 + step))


def _pairs(x, y, yaw, length_m, width_m, valid, sl) -> _Pairs:
    tr = lambda a: np.ascontiguousarray(np.swapaxes(np.asarray(a)[sl], 1, 2))  # noqa: E731  [Rc, T, A]
    v = tr(valid).astype(bool)
    A = v.shape[-1]
    pv = v[..., :, None] & v[..., None, :] & ~np.eye(A, dtype=bool)  # [Rc, T, A, A]
    return _Pairs(tr(x).astype(np.float64), tr(y).astype(np.float64), tr(yaw).astype(np.float64),
                  0.5 * np.asarray(length_m, np.float64), 0.5 * np.asarray(width_m, np.float64), pv)


def _overlap(p: _Pairs) -> np.ndarray:
    """``[Rc, T, A, A]`` bool SAT overlap of valid pairs (shared :func:`boxes_overlap`)."""
    ij = lambda a: (a[..., :, None], a[..., None, :])  # noqa: E731
    (xi, xj), (yi, yj), (ai, aj) = ij(p.x), ij(p.y), ij(p.yaw)
    L, W = 2 * p.hl, 2 * p.hw
    return boxes_overlap(xi, yi, ai, L[:, None], W[:, None], xj, yj, aj, L[None, :], W[None, :]) & p.pair_valid


def _signed_distance(p: _Pairs, overlap: np.ndarray) -> np.ndarray:
    """``[Rc, T, A, A]`` signed box-to-box distance [m] (see module doc); ``+inf`` for invalid pairs."""
    corners = box_corners(p.x, p.y, p.yaw, 2 * p.hl, 2 * p.hw)  # [Rc, T, A, 4, 2]
    cj, sj = np.cos(p.yaw)[..., None, :, None], np.sin(p.yaw)[..., None, :, None]  # [Rc, T, 1, A, 1]
    dx = corners[..., :, None, :, 0] - p.x[..., None, :, None]  # [Rc, T, A(i), A(j), 4]
    dy = corners[..., :, None, :, 1] - p.y[..., None, :, None]
    lx = np.abs(dx * cj + dy * sj) - p.hl[None, :, None]  # corner of i in j's frame, outside-extent
    ly = np.abs(-dx * sj + dy * cj) - p.hw[None, :, None]
    m = np.hypot(np.maximum(lx, 0.0), np.maximum(ly, 0.0)).min(-1)  # [Rc, T, A, A] corners of i -> box j
    dist = np.minimum(m, np.swapaxes(m, -1, -2))
    # penetration depth over the 4 box axes (only used where boxes_overlap says the boxes overlap)
    ci, si = np.cos(p.yaw)[..., :, None], np.sin(p.yaw)[..., :, None]
    cj2, sj2 = np.cos(p.yaw)[..., None, :], np.sin(p.yaw)[..., None, :]
    ddx = p.x[..., None, :] - p.x[..., :, None]
    ddy = p.y[..., None, :] - p.y[..., :, None]
    cc = np.abs(ci * cj2 + si * sj2)
    ss = np.abs(si * cj2 - ci * sj2)
    hli, hwi, hlj, hwj = p.hl[:, None], p.hw[:, None], p.hl[None, :], p.hw[None, :]
    depth = np.minimum.reduce([
        hli + hlj * cc + hwj * ss - np.abs(ddx * ci + ddy * si),
        hwi + hlj * ss + hwj * cc - np.abs(-ddx * si + ddy * ci),
        hlj + hli * cc + hwi * ss - np.abs(ddx * cj2 + ddy * sj2),
        hwj + hli * ss + hwi * cc - np.abs(-ddx * sj2 + ddy * cj2),
    ])
    signed = np.where(overlap, -np.maximum(depth, 0.0), dist)
    return np.where(p.pair_valid, signed, np.inf)


def _ttc(p: _Pairs, speed: np.ndarray, max_ttc_s: float) -> np.ndarray:
    """``[Rc, T, A]`` time to collision [s] with the object ahead (WOSAC definition, module doc)."""
    ci, si = np.cos(p.yaw)[..., :, None], np.sin(p.yaw)[..., :, None]
    dx = p.x[..., None, :] - p.x[..., :, None]  # [Rc, T, A(i), A(j)] other minus ego
    dy = p.y[..., None, :] - p.y[..., :, None]
    lon = dx * ci + dy * si
    lat = -dx * si + dy * ci
    yd = np.abs(wrap_angle(p.yaw[..., None, :] - p.yaw[..., :, None]))
    cyd, syd = np.abs(np.cos(yd)), np.abs(np.sin(yd))
    hlj, hwj = p.hl[None, :], p.hw[None, :]
    gap = lon - p.hl[:, None] - (hlj * cyd + hwj * syd)  # bumper-to-bumper longitudinal distance [m]
    lat_overlap = np.abs(lat) - p.hw[:, None] - (hlj * syd + hwj * cyd)  # < 0: boxes overlap laterally
    ahead = (gap > 0.0) & (yd <= TTC_MAX_HEADING_DIFF_RAD) & (lat_overlap < 0.0)
    ahead &= (lat_overlap < -TTC_SMALL_OVERLAP_M) | (yd <= TTC_MAX_HEADING_DIFF_SMALL_OVERLAP_RAD)
    ahead &= p.pair_valid
    masked = np.where(ahead, gap, np.inf)
    k = masked.argmin(-1)[..., None]  # [Rc, T, A, 1] leader index
    gap_lead = np.take_along_axis(masked, k, -1)[..., 0]
    sp = speed  # [Rc, T, A]
    v_lead = np.take_along_axis(np.broadcast_to(sp[..., None, :], masked.shape), k, -1)[..., 0]
    closing = sp - v_lead
    ok = np.isfinite(gap_lead) & (closing > 0.0)
    return np.where(ok, np.minimum(gap_lead / np.where(ok, closing, 1.0), max_ttc_s), max_ttc_s)


def interaction_features(x_m, y_m, yaw_rad, length_m, width_m, valid, speed_mps=None,
                         max_ttc_s: float = MAX_TTC_S) -> InteractionFeatures:
    """Collision flags, signed distance to the nearest object and TTC, all ``[R, A, T]``.

    :param x_m, y_m, yaw_rad: ``[R, A, T]`` box centres [m] and headings [rad].
    :param length_m, width_m: ``[A]`` box sizes [m].
    :param valid: ``[R, A, T]`` bool; invalid agents neither collide nor count as obstacles.
    :param speed_mps: ``[R, A, T]`` linear speeds [m/s] for TTC (``None``: TTC is all ``max_ttc_s``).
    Invalid entries read ``False`` / ``+inf`` / ``max_ttc_s``.
    """
    x = np.asarray(x_m)
    R, A, T = x.shape
    col = np.zeros((R, A, T), bool)
    dist = np.full((R, A, T), np.inf)
    ttc = np.full((R, A, T), float(max_ttc_s))
    for sl in _chunks(R, T, A):
        p = _pairs(x_m, y_m, yaw_rad, length_m, width_m, valid, sl)
        ov = _overlap(p)
        col[sl] = np.swapaxes(ov.any(-1), 1, 2)
        dist[sl] = np.swapaxes(_signed_distance(p, ov).min(-1), 1, 2)
        if speed_mps is not None:
            sp = np.swapaxes(np.asarray(speed_mps, np.float64)[sl], 1, 2)
            ttc[sl] = np.swapaxes(_ttc(p, sp, max_ttc_s), 1, 2)
    v = np.asarray(valid, bool)
    return InteractionFeatures(col & v, np.where(v, dist, np.inf), np.where(v, ttc, max_ttc_s))


def collision_flags(x_m, y_m, yaw_rad, length_m, width_m, valid) -> np.ndarray:
    """``[R, A, T]`` bool: the agent's box overlaps another valid agent's box at that step (SAT)."""
    x = np.asarray(x_m)
    R, A, T = x.shape
    out = np.zeros((R, A, T), bool)
    for sl in _chunks(R, T, A):
        out[sl] = np.swapaxes(_overlap(_pairs(x_m, y_m, yaw_rad, length_m, width_m, valid, sl)).any(-1), 1, 2)
    return out


def distance_to_nearest_object(x_m, y_m, yaw_rad, length_m, width_m, valid) -> np.ndarray:
    """``[R, A, T]`` signed distance [m] to the nearest other valid box (negative = overlapping)."""
    return interaction_features(x_m, y_m, yaw_rad, length_m, width_m, valid).distance_m


def time_to_collision(x_m, y_m, yaw_rad, length_m, width_m, valid, speed_mps,
                      max_ttc_s: float = MAX_TTC_S) -> np.ndarray:
    """``[R, A, T]`` WOSAC time to collision [s] with the object ahead, capped at ``max_ttc_s``."""
    return interaction_features(x_m, y_m, yaw_rad, length_m, width_m, valid, speed_mps, max_ttc_s).ttc_s
