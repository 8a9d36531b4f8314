"""Interaction features between agents' oriented boxes: collisions, distance to nearest object, TTC.

All functions take ``[R, A, T]`` tracks (``R`` rollouts, ``A`` agents, ``T`` steps at 10 Hz; internal frame,
box centres [m], yaw [rad]) with box sizes ``[A]`` and validity ``[R, A, T]``, and return ``[R, A, T]``.
Work is fully vectorised: a broad phase over all pairs as ``[Rc, T, A, A]`` float32 centre distances
(chunked over rollouts to bound memory) keeps the pairs that can matter, exactly (see ``_candidates``);
the narrow phase runs on those flat pairs in float64.

* Collision flags use :func:`r1sim_sumo.geometry.boxes_overlap` (the one shared SAT test); invalid agents
  and self-pairs are ignored.
* Distance to the nearest object is the signed box-to-box distance. ``box_shape="rounded"`` (default, as the
  official WOSAC code): each box's corners are rounded, i.e. the box is shrunk on every side by
  ``s = 0.7 * min(length, width) / 2`` (``CORNER_ROUNDING_FACTOR``) and the distance between the shrunk boxes is reduced
  by ``s_i + s_j``; a collision is a negative rounded distance (WOSAC: ``distance < 0``), so corner-to-corner touches
  that a sharp SAT test flags are not collisions. ``box_shape="sharp"``: the rectangles themselves, collisions by
  :func:`r1sim_sumo.geometry.boxes_overlap` (the shared SAT test). Either way, separated boxes: the exact Euclidean
  distance between the two (shrunk) rectangles, the smallest distance from a corner of either box to the other box;
  overlapping: minus the penetration depth, the smallest overlap of the projections over the 4 box axes (the minimum
  translation distance, what WOSAC's Minkowski-difference distance gives). No other valid object: ``+inf`` (clipped
  by the histogram). Invalid agents and self-pairs are ignored.
* Time to collision follows WOSAC (``compute_time_to_collision_with_object_in_front``): for each agent, the
  objects *ahead* in its frame (positive bumper-to-bumper longitudinal gap, lateral overlap of the boxes
  in the agent's frame, heading difference <= 75 deg, or <= 10 deg when the lateral overlap is < 0.5 m)
  are candidates; the nearest one (smallest gap) is the leader; ``TTC = gap / (v_agent - v_leader)``
  when closing, capped at 5 s, and 5 s when there is no leader, the gap is opening or a speed is ``nan``. Speeds
  are the linear speeds of :mod:`r1sim_sumo.metrics.kinematics`; boxes are sharp. ``ttc_heading="unwrapped"``
  (default, as WOSAC) takes the heading difference as ``|yaw_j - yaw_i|`` without wrapping (two agents heading
  west with yaws of opposite sign near +-pi are then not following each other); ``"wrapped"`` wraps it to [0, pi].
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
CORNER_ROUNDING_FACTOR = 0.7  # WOSAC: boxes shrunk by 0.7 * min(length, width) / 2 per side, corners rounded
BOX_SHAPES = ("rounded", "sharp")
TTC_HEADINGS = ("unwrapped", "wrapped")
_PAIR_BUDGET = 8_000_000  # [Rc * T * A * A] broad-phase elements per chunk (~ 32 MB per float32 temporary)


class InteractionFeatures(NamedTuple):
    """``[R, A, T]`` each: ``collision`` bool, ``distance_m`` signed [m], ``ttc_s`` [s] in [0, 5]."""

    collision: np.ndarray
    distance_m: np.ndarray
    ttc_s: np.ndarray


class _Chunk(NamedTuple):
    """Candidate pairs of one rollout chunk, flat: ``key`` = flat ``(r, t, i)`` index, ``i``/``j`` agents."""

    key: np.ndarray  # [P] int64 index into the chunk's [Rc * T * A] outputs
    i: np.ndarray  # [P] evaluated agent
    j: np.ndarray  # [P] other agent
    xi: np.ndarray  # [P] float64 pose of i and j
    yi: np.ndarray
    ai: np.ndarray
    xj: np.ndarray
    yj: np.ndarray
    aj: np.ndarray


def _chunks(R: int, T: int, A: int):
    step = max(1, _PAIR_BUDGET // max(1, T * A * A))
    for r0 in range(0, R, step):
        yield slice(r0, min(R, r0 + step))


def _candidates(x, y, yaw, hl, hw, valid, speed, max_ttc_s) -> _Chunk:
    """Broad phase on ``[Rc, T, A]`` tracks: keep the pairs that can matter, exactly.

    Kept: (a) pairs that may overlap or be the nearest box (``centre distance - r_i - r_j`` at most the
    nearest centre distance of ``i``, with ``r`` the box circumradius: box distance lies in
    ``[cd - r_i - r_j, cd]``); (b) with speeds, pairs whose bumper gap can be below ``max_ttc_s * v_i``
    (a lower bound of the gap of any "ahead" pair is ``cd - m_i - m_j``, ``m = sqrt(2) (hl + hw)``); a
    leader left out has a gap of at least ``max_ttc_s * v_i`` and so a TTC at the cap, like any farther one.
    An "ahead" pair also has its centre at ``lon > hl_i`` and ``|lat| < hw_i + r_j`` in the ego frame.
    """
    Rc, T, A = x.shape
    x32, y32 = x.astype(np.float32), y.astype(np.float32)
    pv = valid[..., :, None] & valid[..., None, :] & ~np.eye(A, dtype=bool)  # [Rc, T, A, A]
    cd = np.hypot(x32[..., None, :] - x32[..., :, None], y32[..., None, :] - y32[..., :, None])
    cd = np.where(pv, cd, np.float32(np.inf))
    rad = np.hypot(hl, hw).astype(np.float32)  # [A]
    slack = np.float32(1e-3)  # [m] float32 rounding margin
    lb = cd - rad[:, None] - rad[None, :]
    cand = pv & (lb <= cd.min(-1, keepdims=True) + slack)
    if speed is not None:
        m = (np.sqrt(2.0) * (hl + hw)).astype(np.float32)
        reach = (max_ttc_s * speed).astype(np.float32)[..., :, None]  # [Rc, T, A, 1]
        ci, si = np.cos(yaw).astype(np.float32)[..., :, None], np.sin(yaw).astype(np.float32)[..., :, None]
        dx, dy = x32[..., None, :] - x32[..., :, None], y32[..., None, :] - y32[..., :, None]
        lon = dx * ci + dy * si  # other's centre in the ego frame
        lat = np.abs(dy * ci - dx * si)
        ahead = (lon > hl.astype(np.float32)[:, None] - slack) & (lat < (hw[:, None] + rad[None, :]) + slack)
        cand |= pv & ahead & (cd - m[:, None] - m[None, :] < reach + slack)
    r, t, i, j = np.nonzero(cand)
    key = (r * T + t) * A + i
    return _Chunk(key, i, j, x[r, t, i], y[r, t, i], yaw[r, t, i], x[r, t, j], y[r, t, j], yaw[r, t, j])


def _signed_distance(c: _Chunk, hl, hw, overlap: np.ndarray) -> np.ndarray:
    """``[P]`` signed box-to-box distance [m] of candidate pairs (see module doc)."""
    hli, hwi, hlj, hwj = hl[c.i], hw[c.i], hl[c.j], hw[c.j]

    def corners_to_box(xa, ya, aa, hla, hwa, xb, yb, ab, hlb, hwb):
        k = box_corners(xa, ya, aa, 2 * hla, 2 * hwa)  # [P, 4, 2] corners of a
        cb, sb = np.cos(ab)[:, None], np.sin(ab)[:, None]
        dx, dy = k[..., 0] - xb[:, None], k[..., 1] - yb[:, None]
        ex = np.maximum(np.abs(dx * cb + dy * sb) - hlb[:, None], 0.0)  # outside-extent in b's frame
        ey = np.maximum(np.abs(-dx * sb + dy * cb) - hwb[:, None], 0.0)
        return np.hypot(ex, ey).min(-1)  # [P]

    dist = np.minimum(corners_to_box(c.xi, c.yi, c.ai, hli, hwi, c.xj, c.yj, c.aj, hlj, hwj),
                      corners_to_box(c.xj, c.yj, c.aj, hlj, hwj, c.xi, c.yi, c.ai, hli, hwi))
    # penetration depth: smallest projection overlap over the 4 box axes (used where the SAT test overlaps)
    ci, si, cj, sj = np.cos(c.ai), np.sin(c.ai), np.cos(c.aj), np.sin(c.aj)
    dx, dy = c.xj - c.xi, c.yj - c.yi
    cc, ss = np.abs(ci * cj + si * sj), np.abs(si * cj - ci * sj)
    depth = np.minimum.reduce([
        hli + hlj * cc + hwj * ss - np.abs(dx * ci + dy * si),
        hwi + hlj * ss + hwj * cc - np.abs(-dx * si + dy * ci),
        hlj + hli * cc + hwi * ss - np.abs(dx * cj + dy * sj),
        hwj + hli * ss + hwi * cc - np.abs(-dx * sj + dy * cj),
    ])
    return np.where(overlap, -np.maximum(depth, 0.0), dist)


def _ttc(c: _Chunk, hl, hw, speed_flat: np.ndarray, n_out: int, A: int, max_ttc_s: float,
         ttc_heading: str = "unwrapped") -> np.ndarray:
    """``[n_out]`` time to collision [s] with the nearest object ahead (WOSAC definition, module doc)."""
    ci, si = np.cos(c.ai), np.sin(c.ai)
    dx, dy = c.xj - c.xi, c.yj - c.yi  # other minus ego
    lon, lat = dx * ci + dy * si, -dx * si + dy * ci
    yd = np.abs(c.aj - c.ai) if ttc_heading == "unwrapped" else np.abs(wrap_angle(c.aj - c.ai))
    cyd, syd = np.abs(np.cos(yd)), np.abs(np.sin(yd))
    hlj, hwj = hl[c.j], hw[c.j]
    gap = lon - hl[c.i] - (hlj * cyd + hwj * syd)  # bumper-to-bumper longitudinal distance [m]
    lat_overlap = np.abs(lat) - hw[c.i] - (hlj * syd + hwj * cyd)  # < 0: boxes overlap laterally
    ahead = (gap > 0.0) & (yd <= TTC_MAX_HEADING_DIFF_RAD) & (lat_overlap < 0.0)
    ahead &= (lat_overlap < -TTC_SMALL_OVERLAP_M) | (yd <= TTC_MAX_HEADING_DIFF_SMALL_OVERLAP_RAD)
    key, gap = c.key[ahead], gap[ahead]
    gmin = np.full(n_out, np.inf)
    np.minimum.at(gmin, key, gap)
    lead = gap == gmin[key]
    v_lead = np.zeros(n_out)
    other = (key // A) * A + c.j[ahead]  # flat index of the leader's own (r, t, j) entry
    v_lead[key[lead]] = speed_flat[other[lead]]
    closing = speed_flat - v_lead  # nan (no speed) compares False: TTC at the cap
    ok = np.isfinite(gmin) & (closing > 0.0)
    return np.where(ok, np.minimum(gmin / np.where(ok, closing, 1.0), max_ttc_s), max_ttc_s)


def interaction_features(x_m, y_m, yaw_rad, length_m, width_m, valid, speed_mps=None,
                         max_ttc_s: float = MAX_TTC_S, box_shape: str = "rounded",
                         ttc_heading: str = "unwrapped") -> InteractionFeatures:
    """Collision flags, signed distance to the nearest object and TTC, all ``[R, A, T]``.

    :param x_m, y_m, yaw_rad: ``[R, A, T]`` box centres [m] and headings [rad].
    :param length_m, width_m: ``[A]`` box sizes [m].
    :param valid: ``[R, A, T]`` bool; invalid agents neither collide nor count as obstacles.
    :param speed_mps: ``[R, A, T]`` linear speeds [m/s] for TTC (``None``: TTC is all ``max_ttc_s``; ``nan``: no
        speed at that step, TTC at the cap).
    :param box_shape: ``rounded`` (WOSAC, default) or ``sharp`` boxes for distance and collision (module doc).
    :param ttc_heading: ``unwrapped`` (WOSAC, default) or ``wrapped`` heading difference in the TTC test.
    Invalid entries read ``False`` / ``+inf`` / ``max_ttc_s``.
    """
    return _interactions(x_m, y_m, yaw_rad, length_m, width_m, valid, speed_mps, max_ttc_s, distances=True,
                         box_shape=box_shape, ttc_heading=ttc_heading)


def _interactions(x_m, y_m, yaw_rad, length_m, width_m, valid, speed_mps, max_ttc_s, distances: bool,
                  box_shape: str = "sharp", ttc_heading: str = "unwrapped"):
    if box_shape not in BOX_SHAPES:
        raise ValueError(f"box_shape '{box_shape}' unknown; use one of {BOX_SHAPES}")
    if ttc_heading not in TTC_HEADINGS:
        raise ValueError(f"ttc_heading '{ttc_heading}' unknown; use one of {TTC_HEADINGS}")
    x = np.asarray(x_m, np.float64)
    R, A, T = x.shape
    hl, hw = 0.5 * np.asarray(length_m, np.float64), 0.5 * np.asarray(width_m, np.float64)
    # rounded boxes: shrunk by s per side, distances reduced by s_i + s_j (module doc)
    shrink = CORNER_ROUNDING_FACTOR * np.minimum(hl, hw) if box_shape == "rounded" else np.zeros_like(hl)  # [A] [m]
    shl, shw = hl - shrink, hw - shrink
    tr = lambda a, dt: np.ascontiguousarray(np.swapaxes(np.asarray(a, dt), 1, 2))  # noqa: E731  [R, T, A]
    X, Y, YAW, V = tr(x, np.float64), tr(y_m, np.float64), tr(yaw_rad, np.float64), tr(valid, bool)
    S = None if speed_mps is None else tr(speed_mps, np.float64)
    col = np.zeros((R, T, A), bool)
    dist = np.full((R, T, A), np.inf)
    ttc = np.full((R, T, A), float(max_ttc_s))
    for sl in _chunks(R, T, A):
        sp = None if S is None else S[sl]
        c = _candidates(X[sl], Y[sl], YAW[sl], hl, hw, V[sl], sp, max_ttc_s)
        n = X[sl].size
        ov = boxes_overlap(c.xi, c.yi, c.ai, 2 * shl[c.i], 2 * shw[c.i], c.xj, c.yj, c.aj, 2 * shl[c.j], 2 * shw[c.j])
        cf = np.zeros(n, bool)
        if box_shape == "sharp":
            cf[c.key[ov]] = True
        if distances or box_shape == "rounded":
            sd = _signed_distance(c, shl, shw, ov) - shrink[c.i] - shrink[c.j]  # [P]
            if box_shape == "rounded":
                cf[c.key[sd < 0.0]] = True
            d = np.full(n, np.inf)
            np.minimum.at(d, c.key, sd)
            dist[sl] = d.reshape(X[sl].shape)
        col[sl] = cf.reshape(X[sl].shape)
        if sp is not None:
            ttc[sl] = _ttc(c, hl, hw, sp.reshape(-1), n, A, max_ttc_s, ttc_heading).reshape(X[sl].shape)
    back = lambda a: np.swapaxes(a, 1, 2)  # noqa: E731  [R, A, T]
    v = np.asarray(valid, bool)
    return InteractionFeatures(back(col) & v, np.where(v, back(dist), np.inf), np.where(v, back(ttc), max_ttc_s))


def collision_flags(x_m, y_m, yaw_rad, length_m, width_m, valid) -> np.ndarray:
    """``[R, A, T]`` bool: the agent's box overlaps another valid agent's box at that step (SAT)."""
    return _interactions(x_m, y_m, yaw_rad, length_m, width_m, valid, None, MAX_TTC_S, distances=False).collision


def distance_to_nearest_object(x_m, y_m, yaw_rad, length_m, width_m, valid, box_shape: str = "rounded") -> np.ndarray:
    """``[R, A, T]`` signed distance [m] to the nearest other valid box (negative = overlapping; module doc)."""
    return interaction_features(x_m, y_m, yaw_rad, length_m, width_m, valid, box_shape=box_shape).distance_m


def time_to_collision(x_m, y_m, yaw_rad, length_m, width_m, valid, speed_mps,
                      max_ttc_s: float = MAX_TTC_S, ttc_heading: str = "unwrapped") -> np.ndarray:
    """``[R, A, T]`` WOSAC time to collision [s] with the object ahead, capped at ``max_ttc_s``."""
    return _interactions(x_m, y_m, yaw_rad, length_m, width_m, valid, speed_mps, max_ttc_s, distances=False,
                         ttc_heading=ttc_heading).ttc_s
