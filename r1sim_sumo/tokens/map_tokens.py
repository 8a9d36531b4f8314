"""Map tokens: polylines cut into segments of at most 5 m, each resampled to 11 points in its own frame.

A polyline of arc length ``S`` is cut into ``ceil(S / seg_len_m)`` equal segments (so every segment is at
most ``seg_len_m`` long; a polyline shorter than one segment gives one shorter segment) and each segment
is resampled at ``n = round(seg_len_m / step_m) + 1`` points evenly spaced in arc length. Points are stored
in the segment's OWN frame: origin at the segment start, x along the chord start -> end. Polylines of
(near) zero length carry no direction and are dropped.

A token's ``kind`` is its polyline's (0 lane centre, 1 road edge), except that the tokens of a lane that ends beside a
lane of its edge that goes on (:meth:`~r1sim_sumo.scenario.MapPolylines.ending_lanes`: an acceleration lane, a dropped
lane) are kind 2, ``ENDING_LANE``: a vehicle there has to change lanes, which the geometry of 5 m segments alone
hardly tells the policy. Models trained before that kind existed (``PolicyConfig.num_map_kinds == 2``) read it as a
lane centre (:func:`~r1sim_sumo.model.layers.map_kind_index`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from r1sim_sumo.scenario import MapPolylines
from r1sim_sumo.tokens.constants import N_POSE, STEPS_PER_TOKEN

MIN_POLYLINE_LENGTH_M = 1e-3
ENDING_LANE = 2
"""Map token kind of a lane centre of a lane that ends beside one that goes on (0 and 1: ``scenario.LANE_CENTRE``,
``scenario.ROAD_EDGE``)."""


@dataclass
class MapTokens:
    """``M`` map tokens (numpy).

    :param pts: float32 ``[M, 11, 2]`` points in the segment's own frame [m] (start at origin, x along it).
    :param pos: float32 ``[M, 2]`` world position of the segment start [m].
    :param yaw: float32 ``[M]`` direction of the segment (atan2 of end - start) [rad].
    :param kind: int64 ``[M]`` 0 lane centre / 1 road edge / 2 lane centre of an ending lane (``ENDING_LANE``).
    :param speed_limit_mps: float32 ``[M]`` [m/s].
    :param tl: int64 ``[M, n_pose]`` traffic-light state of the source polyline at each boundary (state 5k);
        0 none / 1 green / 2 yellow / 3 red.
    :param polyline: int64 ``[M]`` source polyline index.
    """

    pts: np.ndarray
    pos: np.ndarray
    yaw: np.ndarray
    kind: np.ndarray
    speed_limit_mps: np.ndarray
    tl: np.ndarray
    polyline: np.ndarray

    FIELDS = ("pts", "pos", "yaw", "kind", "speed_limit_mps", "tl", "polyline")

    @property
    def num_tokens(self) -> int:
        return int(len(self.kind))

    def select(self, idx) -> MapTokens:
        """Subset of tokens by index array or boolean mask."""
        return MapTokens(**{f: getattr(self, f)[idx] for f in self.FIELDS})

    def world_points(self) -> np.ndarray:
        """Token points in the world frame, float32 ``[M, n, 2]``."""
        c, s = np.cos(self.yaw)[:, None], np.sin(self.yaw)[:, None]
        x = self.pos[:, None, 0] + c * self.pts[..., 0] - s * self.pts[..., 1]
        y = self.pos[:, None, 1] + s * self.pts[..., 0] + c * self.pts[..., 1]
        return np.stack([x, y], -1).astype(np.float32)

    def within(self, centres_xy: np.ndarray, radius_m: float) -> np.ndarray:
        """Boolean ``[M]``: any of the token's start, middle or end point within ``radius_m`` of any centre ``[K, 2]``."""
        centres = np.asarray(centres_xy, np.float64).reshape(-1, 2)
        keep = np.zeros(self.num_tokens, bool)
        if not len(centres) or not self.num_tokens:
            return keep
        n = self.pts.shape[1]
        probe = self.world_points()[:, [0, n // 2, n - 1]].astype(np.float64).reshape(-1, 2)  # [M*3, 2]
        # nearest centre of every probe, searched only up to the radius (a k-d tree: O(M log K), not M x K)
        dist, _ = cKDTree(centres).query(probe, distance_upper_bound=float(radius_m) * (1 + 1e-12))
        return (dist <= float(radius_m)).reshape(-1, 3).any(1)


def token_kinds(map: MapPolylines) -> np.ndarray:
    """``[L]`` int64 kind of each polyline's tokens: its own kind, ``ENDING_LANE`` for the map's ending lanes."""
    kind = np.asarray(map.kind, np.int64).copy()
    kind[map.ending_lanes()] = ENDING_LANE
    return kind


def tokenize_map(
    map: MapPolylines,
    seg_len_m: float = 5.0,
    step_m: float = 0.5,
    n_pose: int = N_POSE,
    first_step: int = 0,
) -> MapTokens:
    """Cut all polylines into map tokens (vectorised over polylines and segments).

    :param map: the scenario map (internal frame).
    :param seg_len_m: maximum segment length [m]; ``step_m``: point spacing of a full segment [m].
    :param n_pose: number of boundary poses for the traffic-light states.
    :param first_step: state index (column of ``map.tl_state``) of boundary 0; boundary ``k`` reads column
        ``first_step + 5k``. Columns outside the table give 0 (no signal information).
    """
    if seg_len_m <= 0 or step_m <= 0:
        raise ValueError(f"tokenize_map: seg_len_m ({seg_len_m}) and step_m ({step_m}) must be > 0")
    n_pts = int(round(seg_len_m / step_m)) + 1
    P = np.asarray(map.points_m, np.float64)  # [N, 2]
    start = np.asarray(map.start, np.int64)
    L = len(start) - 1
    lens = np.diff(start)
    poly_of_pt = np.repeat(np.arange(L), lens)  # [N]
    # arc length within each polyline
    d = np.linalg.norm(np.diff(P, axis=0), axis=1) if len(P) > 1 else np.zeros(0)
    d[poly_of_pt[1:] != poly_of_pt[:-1]] = 0.0  # no arc across polyline boundaries
    s_glob = np.concatenate([[0.0], np.cumsum(d)])  # [N]
    s_local = s_glob - s_glob[start[:-1]][poly_of_pt]  # [N]
    length = s_local[start[1:] - 1] if L else np.zeros(0)  # [L]
    # a strictly separated global parameter so one np.interp serves all polylines
    offset = np.concatenate([[0.0], np.cumsum(length + 1.0)[:-1]]) if L else np.zeros(0)  # [L]
    G = s_local + offset[poly_of_pt]

    keep = length > MIN_POLYLINE_LENGTH_M
    n_seg = np.where(keep, np.maximum(np.ceil(length / seg_len_m - 1e-9), 1), 0).astype(np.int64)  # [L]
    seg_poly = np.repeat(np.arange(L), n_seg)  # [M]
    first_seg = np.concatenate([[0], np.cumsum(n_seg)[:-1]]) if L else np.zeros(0, np.int64)
    seg_idx = np.arange(len(seg_poly)) - first_seg[seg_poly]  # [M] index within its polyline
    seg_l = length[seg_poly] / np.maximum(n_seg[seg_poly], 1)  # [M] segment length [m]
    frac = np.linspace(0.0, 1.0, n_pts)  # [n]
    q = (seg_idx[:, None] + frac[None]) * seg_l[:, None]  # [M, n] arc position within the polyline
    q = np.clip(q, 0.0, length[seg_poly][:, None]) + offset[seg_poly][:, None]
    wx = np.interp(q, G, P[:, 0]) if len(P) else q * 0
    wy = np.interp(q, G, P[:, 1]) if len(P) else q * 0
    pos = np.stack([wx[:, 0], wy[:, 0]], -1)  # [M, 2]
    chord = np.stack([wx[:, -1] - wx[:, 0], wy[:, -1] - wy[:, 0]], -1)
    first = np.stack([wx[:, 1] - wx[:, 0], wy[:, 1] - wy[:, 0]], -1)
    direction = np.where((np.linalg.norm(chord, axis=-1) > 1e-6)[:, None], chord, first)  # closed loops
    yaw = np.arctan2(direction[:, 1], direction[:, 0])
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    rx, ry = wx - pos[:, :1], wy - pos[:, 1:]
    pts = np.stack([c * rx + s * ry, -s * rx + c * ry], -1)  # [M, n, 2] own frame

    tl_tab = np.asarray(map.tl_state)
    cols = first_step + STEPS_PER_TOKEN * np.arange(n_pose)
    tl = np.zeros((len(seg_poly), n_pose), np.int64)
    if tl_tab.ndim == 2 and tl_tab.shape[1] > 0:
        ok = (cols >= 0) & (cols < tl_tab.shape[1])
        tl[:, ok] = tl_tab[seg_poly][:, cols[ok]]
    return MapTokens(
        pts=pts.astype(np.float32), pos=pos.astype(np.float32), yaw=yaw.astype(np.float32),
        kind=token_kinds(map)[seg_poly], speed_limit_mps=np.asarray(map.speed_limit_mps, np.float32)[seg_poly],
        tl=tl, polyline=seg_poly.astype(np.int64),
    )
