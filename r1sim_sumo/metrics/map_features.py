"""Map-based features: signed distance to the road edge, offroad flags, lanes and red-light violations.

Frame: internal (metres, x east, y north, yaw radians CCW from +x, box centres), 10 Hz.

Drivable area = union of the lane polygons, each ``LANE_CENTRE`` polyline buffered by ``width/2`` (shapely 2,
vectorised ``buffer`` + ``union_all``; round caps so that consecutive lanes meeting at an angle leave no
wedge-shaped gap; a dead end therefore reaches ``width/2`` past its last point). It is built once per map
and cached by :meth:`MapPolylines.content_key`.

* ``distance_to_road_edge``: as in WOSAC, the signed distance of each of the 4 box corners to the boundary of
  the drivable area (negative inside), reduced to the most off-road corner (max over corners). The boundary
  is resampled every 0.25 m and searched with a k-d tree (scipy): the distance to the nearest boundary
  vertex overestimates the distance to the boundary by at most 0.125 m at the boundary and much less away
  from it; the sign comes from an exact point-in-polygon test (``shapely.contains_xy``). Distances beyond
  ``MAX_EDGE_DISTANCE_M`` are clipped to it (the histogram range is [-20, 40] m).
* ``offroad``: WOSAC's rule, any corner farther than ``tolerance_m`` outside the drivable area
  (``distance_to_road_edge > tolerance_m``; WOSAC uses 0 m, the default here).
* Lanes: an agent is on the nearest lane centre (vertices every 0.5 m) whose lateral offset is at most that
  lane's ``width/2`` and whose direction agrees with the agent's heading within ``LANE_HEADING_TOL_RAD``
  (60 deg); ``-1`` when no lane qualifies.
* Red-light violation at step ``t``: the agent's lane changes from ``p`` (at ``t-1``) to ``q`` (at ``t``), lane
  ``q`` reads ``TL_RED`` at ``t`` and ``p`` is signal-controlled at ``t`` (its state is not ``TL_NONE``), i.e. the
  agent crossed a stop line into a red movement. With SUMO maps the movement is the junction-internal (via)
  lane, which carries its own link's state; requiring a signalised ``p`` keeps an agent that merely arrives
  on an approach lane whose signals are all red from being flagged. Only for maps with ``tl_state`` columns.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from r1sim_sumo.geometry import box_corners, resample_polyline, wrap_angle
from r1sim_sumo.scenario import LANE_CENTRE, TL_NONE, TL_RED, MapPolylines

MAX_EDGE_DISTANCE_M = 50.0  # [m] |distance to road edge| is clipped here
BOUNDARY_STEP_M = 0.25  # [m] boundary resampling for the nearest-vertex search
LANE_STEP_M = 0.5  # [m] lane-centre resampling for lane assignment
LANE_HEADING_TOL_RAD = math.radians(60.0)
DEFAULT_LANE_WIDTH_M = 3.2  # used for lanes stored with width 0
_LANE_CANDIDATES = 32
_CACHE_SIZE = 32


def _import_spatial():
    try:
        import shapely
        from scipy.spatial import cKDTree
    except ImportError as exc:  # pragma: no cover - both are installed with the package
        raise ImportError(f"r1sim_sumo.metrics.map_features needs shapely>=2 and scipy ({exc}); pip install shapely scipy") from exc
    return shapely, cKDTree


@dataclass
class DrivableArea:
    """Cached per-map geometry.

    :param polygon: shapely (Multi)Polygon, union of the buffered lanes (prepared for fast tests).
    :param boundary_xy: ``[N, 2]`` boundary vertices [m] every ~0.25 m; ``boundary_tree`` its k-d tree.
    :param lane_xy: ``[M, 2]`` lane-centre vertices [m]; ``lane_dir`` ``[M, 2]`` unit direction of travel;
        ``lane_index`` ``[M]`` polyline index into the map; ``lane_half_width`` ``[M]`` [m]; ``lane_tree``.
    """

    polygon: object
    boundary_xy: np.ndarray
    boundary_tree: object
    lane_xy: np.ndarray
    lane_dir: np.ndarray
    lane_index: np.ndarray
    lane_half_width: np.ndarray
    lane_tree: object


_CACHE: OrderedDict[str, DrivableArea] = OrderedDict()


def drivable_area(map_: MapPolylines) -> DrivableArea:
    """Build (or fetch from the cache, keyed by ``map_.content_key()``) the drivable area of a map."""
    key = map_.content_key()
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    area = _build(map_)
    _CACHE[key] = area
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return area


def _build(map_: MapPolylines) -> DrivableArea:
    shapely, cKDTree = _import_spatial()
    lanes = np.flatnonzero(np.asarray(map_.kind) == LANE_CENTRE)
    if len(lanes) == 0:
        raise ValueError("map.kind: no LANE_CENTRE polylines, cannot build the drivable area for map metrics")
    widths = np.asarray(map_.width_m, np.float64)[lanes]
    widths = np.where(widths > 0, widths, DEFAULT_LANE_WIDTH_M)
    pts = [np.asarray(map_.polyline(int(i)), np.float64) for i in lanes]
    geoms = np.array([shapely.LineString(p) if len(p) >= 2 else shapely.Point(p[0]) for p in pts], dtype=object)
    polygon = shapely.union_all(shapely.buffer(geoms, widths / 2.0, cap_style="round", quad_segs=4))
    shapely.prepare(polygon)
    rings = []
    for poly in shapely.get_parts(polygon):  # Polygon parts of a (Multi)Polygon
        rings.append(np.asarray(poly.exterior.coords))
        rings += [np.asarray(r.coords) for r in poly.interiors]
    boundary = np.concatenate([resample_polyline(r, BOUNDARY_STEP_M) for r in rings])  # [N, 2]
    lxy, ldir, lidx, lhw = [], [], [], []
    for i, p, w in zip(lanes, pts, widths, strict=True):
        q = resample_polyline(p, LANE_STEP_M)  # [M_i, 2]
        if len(q) < 2:
            continue
        d = np.diff(q, axis=0)
        d = np.concatenate([d, d[-1:]])
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        lxy.append(q)
        ldir.append(d)
        lidx.append(np.full(len(q), i, np.int64))
        lhw.append(np.full(len(q), w / 2.0))
    lane_xy = np.concatenate(lxy)
    return DrivableArea(polygon, boundary, cKDTree(boundary), lane_xy, np.concatenate(ldir),
                        np.concatenate(lidx), np.concatenate(lhw), cKDTree(lane_xy))


def signed_distance_to_edge(area: DrivableArea, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Signed distance [m] of points ``[N]`` to the drivable-area boundary, negative inside, clipped to +-50 m."""
    shapely, _ = _import_spatial()
    px, py = np.asarray(px, np.float64).ravel(), np.asarray(py, np.float64).ravel()
    d, _ = area.boundary_tree.query(np.stack([px, py], 1), k=1, distance_upper_bound=MAX_EDGE_DISTANCE_M)
    d = np.minimum(d, MAX_EDGE_DISTANCE_M)
    inside = shapely.contains_xy(area.polygon, px, py)
    return np.where(inside, -d, d)


def distance_to_road_edge(area: DrivableArea, x_m, y_m, yaw_rad, length_m, width_m, valid) -> np.ndarray:
    """``[R, A, T]`` signed distance [m] of the most off-road box corner to the road edge (WOSAC).

    :param x_m, y_m, yaw_rad: ``[R, A, T]`` box centres [m] / headings [rad]; ``length_m, width_m`` ``[A]``.
    :param valid: ``[R, A, T]`` bool; invalid entries read ``-MAX_EDGE_DISTANCE_M`` (deep inside).
    """
    v = np.asarray(valid, bool)
    out = np.full(v.shape, -MAX_EDGE_DISTANCE_M)
    if not v.any():
        return out
    L = np.broadcast_to(np.asarray(length_m, np.float64)[None, :, None], v.shape)[v]
    W = np.broadcast_to(np.asarray(width_m, np.float64)[None, :, None], v.shape)[v]
    c = box_corners(np.asarray(x_m, np.float64)[v], np.asarray(y_m, np.float64)[v], np.asarray(yaw_rad, np.float64)[v], L, W)
    d = signed_distance_to_edge(area, c[..., 0], c[..., 1]).reshape(-1, 4)  # [N, 4]
    out[v] = d.max(-1)
    return out


def offroad_flags(distance_to_edge_m: np.ndarray, tolerance_m: float = 0.0) -> np.ndarray:
    """Offroad when the most off-road corner is more than ``tolerance_m`` outside the drivable area."""
    return np.asarray(distance_to_edge_m) > tolerance_m


def lane_assignment(area: DrivableArea, x_m, y_m, yaw_rad, valid) -> np.ndarray:
    """``[...]`` int64 map polyline index of the lane each valid agent state is on, ``-1`` when none."""
    v = np.asarray(valid, bool)
    out = np.full(v.shape, -1, np.int64)
    if not v.any():
        return out
    q = np.stack([np.asarray(x_m, np.float64)[v], np.asarray(y_m, np.float64)[v]], 1)  # [N, 2]
    yaw = np.asarray(yaw_rad, np.float64)[v]
    bound = float(area.lane_half_width.max()) + LANE_STEP_M
    k = min(_LANE_CANDIDATES, len(area.lane_xy))
    dist, idx = area.lane_tree.query(q, k=k, distance_upper_bound=bound)  # [N, k], sorted by distance
    dist, idx = dist.reshape(len(q), k), idx.reshape(len(q), k)
    found = np.isfinite(dist)
    idx = np.where(found, idx, 0)
    rel = q[:, None, :] - area.lane_xy[idx]  # [N, k, 2]
    tang = area.lane_dir[idx]
    lat = np.abs(tang[..., 0] * rel[..., 1] - tang[..., 1] * rel[..., 0])
    lon = np.abs((tang * rel).sum(-1))
    head = np.abs(wrap_angle(yaw[:, None] - np.arctan2(tang[..., 1], tang[..., 0])))
    ok = found & (lat <= area.lane_half_width[idx]) & (lon <= LANE_STEP_M) & (head <= LANE_HEADING_TOL_RAD)
    first = ok.argmax(1)
    lane = np.where(ok.any(1), area.lane_index[idx[np.arange(len(q)), first]], -1)
    out[v] = lane
    return out


def red_light_violations(lanes: np.ndarray, valid: np.ndarray, tl_state: np.ndarray) -> np.ndarray:
    """``[..., T]`` bool red-light violations from lanes ``[..., T + 1]`` (index 0 = the step before).

    :param lanes: lane (map polyline) index per step, ``-1`` none; step 0 is the state before the first.
    :param valid: ``[..., T + 1]`` bool.
    :param tl_state: ``[L, T + 1]`` int8 traffic-light state of each polyline at the same steps.
    """
    lanes = np.asarray(lanes)
    tl = np.asarray(tl_state)
    prev, cur = lanes[..., :-1], lanes[..., 1:]
    ok = (prev >= 0) & (cur >= 0) & (prev != cur) & np.asarray(valid)[..., 1:] & np.asarray(valid)[..., :-1]
    steps = np.broadcast_to(np.arange(1, lanes.shape[-1]), cur.shape)
    cur_state = tl[np.where(ok, cur, 0), steps]
    prev_state = tl[np.where(ok, prev, 0), steps]
    return ok & (cur_state == TL_RED) & (prev_state != TL_NONE)
