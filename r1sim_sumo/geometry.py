"""Frames, angle conventions, oriented boxes and the batched SAT overlap test.

Internal frame: metres, x east, y north, yaw in radians counter-clockwise from +x, position = box centre.

SUMO: ``vehicle.getPosition``/``moveToXY`` use the *front-bumper centre*; angles are navigational degrees
(0 = north, clockwise): ``sumo_angle_deg = (90 - degrees(yaw_rad)) % 360``.

highway-env: y grows downward (screen frame), heading in radians in that frame, position = centre.
Ours = (x, -y), yaw = -heading.

All functions accept numpy arrays or torch tensors where noted and broadcast over leading dimensions.
"""

from __future__ import annotations

import math

import numpy as np

# ---------------------------------------------------------------- angles


def wrap_angle(a):
    """Wrap radians to [-pi, pi). Works on floats, numpy arrays and torch tensors."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def sumo_angle_deg_to_yaw_rad(angle_deg):
    """SUMO navigational degrees (0 = north, clockwise) -> yaw radians (0 = east, counter-clockwise)."""
    return wrap_angle(np.deg2rad(90.0 - np.asarray(angle_deg, dtype=np.float64)))


def yaw_rad_to_sumo_angle_deg(yaw_rad):
    """Yaw radians (0 = east, counter-clockwise) -> SUMO navigational degrees in [0, 360)."""
    return (90.0 - np.rad2deg(np.asarray(yaw_rad, dtype=np.float64))) % 360.0


# ---------------------------------------------------------------- reference points


def front_bumper_to_centre(x_m, y_m, yaw_rad, length_m):
    """SUMO front-bumper centre -> box centre (moves back by length/2 along the heading)."""
    half = 0.5 * np.asarray(length_m, dtype=np.float64)
    return x_m - half * np.cos(yaw_rad), y_m - half * np.sin(yaw_rad)


def centre_to_front_bumper(x_m, y_m, yaw_rad, length_m):
    """Box centre -> SUMO front-bumper centre (for ``vehicle.moveToXY``)."""
    half = 0.5 * np.asarray(length_m, dtype=np.float64)
    return x_m + half * np.cos(yaw_rad), y_m + half * np.sin(yaw_rad)


# ---------------------------------------------------------------- highway-env frame


def highway_to_internal(x_m, y_hw_m, heading_hw_rad):
    """highway-env (y down, heading clockwise on screen) -> internal (y up, yaw counter-clockwise)."""
    return x_m, -np.asarray(y_hw_m), wrap_angle(-np.asarray(heading_hw_rad))


def internal_to_highway(x_m, y_m, yaw_rad):
    """Inverse of :func:`highway_to_internal` (the map is its own inverse)."""
    return x_m, -np.asarray(y_m), wrap_angle(-np.asarray(yaw_rad))


# ---------------------------------------------------------------- oriented boxes


def box_corners(x, y, yaw, length, width):
    """Corners of oriented boxes, ``[..., 4, 2]`` (front-left, rear-left, rear-right, front-right).

    numpy or torch inputs of broadcastable shape ``[...]``; output in the same library.
    """
    lib = _lib(x)
    c, s = lib.cos(yaw), lib.sin(yaw)
    hl, hw = 0.5 * length, 0.5 * width
    dx = lib.stack([hl, -hl, -hl, hl], -1) if lib is np else _tstack([hl, -hl, -hl, hl], x)
    dy = lib.stack([hw, hw, -hw, -hw], -1) if lib is np else _tstack([hw, hw, -hw, -hw], x)
    c, s = c[..., None], s[..., None]
    cx = x[..., None] + c * dx - s * dy
    cy = y[..., None] + s * dx + c * dy
    return lib.stack([cx, cy], -1)


def boxes_overlap(x1, y1, yaw1, l1, w1, x2, y2, yaw2, l2, w2):
    """Batched separating-axis test for pairs of oriented boxes (numpy or torch, broadcasting).

    Two rectangles overlap iff on each of the 4 candidate axes (the two boxes' heading and normal) the
    centre distance projected on the axis is at most the sum of the projected half-extents. Pure
    broadcasting: pass e.g. ``[G, T, A, 1]`` and ``[G, T, 1, A]`` to get all pairs ``[G, T, A, A]``.
    Touching boxes (distance exactly equal) count as overlapping. Returns a boolean array.
    """
    lib = _lib(x1)
    dx, dy = x2 - x1, y2 - y1
    c1, s1, c2, s2 = lib.cos(yaw1), lib.sin(yaw1), lib.cos(yaw2), lib.sin(yaw2)
    hl1, hw1, hl2, hw2 = 0.5 * l1, 0.5 * w1, 0.5 * l2, 0.5 * w2
    # relative rotation terms |cos(d)|, |sin(d)| between the two headings
    cc = lib.abs(c1 * c2 + s1 * s2)
    ss = lib.abs(s1 * c2 - c1 * s2)
    eps = 1e-9
    # axis 1: box-1 heading, axis 2: box-1 normal, axis 3: box-2 heading, axis 4: box-2 normal
    sep = lib.abs(dx * c1 + dy * s1) > hl1 + hl2 * cc + hw2 * ss + eps
    sep = sep | (lib.abs(-dx * s1 + dy * c1) > hw1 + hl2 * ss + hw2 * cc + eps)
    sep = sep | (lib.abs(dx * c2 + dy * s2) > hl2 + hl1 * cc + hw1 * ss + eps)
    sep = sep | (lib.abs(-dx * s2 + dy * c2) > hw2 + hl1 * ss + hw1 * cc + eps)
    return ~sep


def _lib(x):
    if isinstance(x, np.ndarray) or np.isscalar(x):
        return np
    import torch

    if isinstance(x, torch.Tensor):
        return torch
    return np


def _tstack(items, like):
    import torch

    items = [torch.as_tensor(v, dtype=like.dtype, device=like.device) for v in items]  # python-float sizes too
    return torch.stack(torch.broadcast_tensors(*items), -1)


# ---------------------------------------------------------------- polylines


def resample_polyline(points: np.ndarray, step_m: float) -> np.ndarray:
    """Resample a polyline ``[N, 2]`` at (about) uniform arc-length spacing ``step_m``; keeps both ends."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        return pts.copy()
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    total = s[-1]
    if total <= 1e-9:
        return pts[:1].copy()
    n = max(int(math.ceil(total / step_m)), 1)
    t = np.linspace(0.0, total, n + 1)
    return np.stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])], axis=1)


def offset_polyline(points: np.ndarray, offset_m: float) -> np.ndarray:
    """Offset a polyline sideways by ``offset_m`` (positive = left of the direction of travel)."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        return pts.copy()
    d = np.diff(pts, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    # per-vertex tangent: average of adjacent segment directions
    t = np.empty_like(pts)
    t[0], t[-1] = d[0], d[-1]
    if len(pts) > 2:
        m = d[:-1] + d[1:]
        n = np.linalg.norm(m, axis=1, keepdims=True)
        t[1:-1] = np.where(n > 1e-9, m / np.maximum(n, 1e-12), d[1:])
    normal = np.stack([-t[:, 1], t[:, 0]], axis=1)
    return pts + offset_m * normal
