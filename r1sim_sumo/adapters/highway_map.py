"""highway-env road network -> :class:`~r1sim_sumo.scenario.MapPolylines` (internal frame).

highway-env describes lanes in a y-down screen frame; every point is converted with
:func:`r1sim_sumo.geometry.highway_to_internal` (``y -> -y``), so the internal map is the mirror image of
highway-env's coordinates and looks exactly like the rendered screen with y pointing up.

What is extracted, for every lane of ``network.graph[from][to][index]`` (any :class:`AbstractLane`:
StraightLane, SineLane, CircularLane, PolyLane, ...):

* a lane centreline (``kind = LANE_CENTRE``), ``lane.position(s, 0)`` for ``s`` in ``[0, lane.length]``
  every ``step_m`` (both ends kept; ``s`` is arc length except on a SineLane, where it runs along the
  straight base, so points there are slightly more than ``step_m`` apart), in the direction of travel, ``lane_id = "from->to#index"``;
  ``speed_limit_mps = lane.speed_limit`` (0 where the lane has none), ``width_m`` = mean of
  ``lane.width_at(s)`` over the samples;
* road edges (``kind = ROAD_EDGE``) from the lane boundaries ``lane.position(s, -/+ width_at(s) / 2)``.
  **Rule:** highway-env's ``line_types[0]`` is the boundary at lateral ``-width/2`` (the left of the direction
  of travel on screen and in the internal frame) and ``line_types[1]`` the one at ``+width/2`` (the right).
  A side whose line type is ``CONTINUOUS`` or ``CONTINUOUS_LINE`` (a solid line, the lines highway-env
  draws as the limit of the drivable road) becomes a road edge, ``lane_id = "from->to#index#left"`` /
  ``"#right"``, ordered in the direction of travel. ``STRIPED`` (lane divider that may be crossed) and
  ``NONE`` (the neighbouring lane draws the line) are not road edges.
* successors: lane ``(a, b, i)`` -> lane ``(b, c, j)`` for every outgoing edge ``(b, c)`` of node ``b``. Only
  lanes heading within 60 deg of lane ``i``'s end heading count (two-way roads share node names, so this
  removes U-turns); of those, the lanes ``j`` whose start lies within half a lane width of the end of lane
  ``i`` are kept (lanes that continue each other); if none is that close, the closest one is kept, as
  highway-env's ``RoadNetwork.next_lane`` does, provided it starts within two lane widths of the end
  (roundabout entries and exits in highway-env start a few metres off the ring).

Straight lanes are affine in ``s``, so their samples are interpolated between ``lane.position`` at both ends
(exact, and fast on highway-v0's 10 km lanes); every other lane type is sampled point by point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from r1sim_sumo.geometry import highway_to_internal
from r1sim_sumo.scenario import LANE_CENTRE, ROAD_EDGE, MapPolylines

LaneIndex = tuple[str, str, int]

# highway-env LineType values (highway_env.road.lane.LineType), repeated here so that this module imports
# without highway-env; checked against the installed package in tests.
LINE_NONE, LINE_STRIPED, LINE_CONTINUOUS, LINE_CONTINUOUS_LINE = 0, 1, 2, 3
ROAD_EDGE_LINE_TYPES = (LINE_CONTINUOUS, LINE_CONTINUOUS_LINE)
MIN_HEADING_COS = 0.5  # successor lanes start within 60 deg of the heading at the end of the lane
MAX_GAP_LANE_WIDTHS = 2.0  # fallback successor: closest lane starting within 2 lane widths of the end


@dataclass
class HighwayMap:
    """A highway-env road network in the internal frame.

    :param polylines: lane centrelines and road edges (see module docstring for the rules).
    :param lane_index: highway-env lane index ``(from, to, index)`` -> row of its centreline in ``polylines``.
    """

    polylines: MapPolylines
    lane_index: dict[LaneIndex, int]


def lane_id(index: LaneIndex) -> str:
    """String id of a highway-env lane index: ``"from->to#index"``."""
    a, b, i = index
    return f"{a}->{b}#{i}"


def _sample_s(length_m: float, step_m: float) -> np.ndarray:
    """Arc-length samples ``[n + 1]`` from 0 to ``length_m`` [m], spacing at most ``step_m``."""
    n = max(int(math.ceil(max(length_m, 0.0) / step_m)), 1)
    return np.linspace(0.0, max(length_m, 0.0), n + 1)


def _is_straight(lane) -> bool:
    # exact class check: SineLane subclasses StraightLane but is not affine in s
    return type(lane).__name__ == "StraightLane"


def _lane_points_hw(lane, s: np.ndarray, lateral: np.ndarray) -> np.ndarray:
    """``lane.position(s, lateral)`` for every sample, ``[n, 2]`` in highway-env's y-down frame."""
    if _is_straight(lane):
        # position(s, r) = start + s * direction + r * normal: affine, interpolate from four calls
        p00 = np.asarray(lane.position(0.0, 0.0), np.float64)
        ds = np.asarray(lane.position(1.0, 0.0), np.float64) - p00
        dr = np.asarray(lane.position(0.0, 1.0), np.float64) - p00
        return p00[None] + s[:, None] * ds[None] + lateral[:, None] * dr[None]
    return np.array(
        [lane.position(float(si), float(ri)) for si, ri in zip(s, lateral, strict=True)], np.float64
    ).reshape(-1, 2)


def _to_internal(points_hw: np.ndarray) -> np.ndarray:
    x, y, _ = highway_to_internal(points_hw[:, 0], points_hw[:, 1], 0.0)
    return np.stack([x, y], axis=1)


def _crop(points: np.ndarray, bounds_m: tuple[float, float, float, float] | None) -> np.ndarray:
    """Keep the span from the first to the last point inside ``bounds_m`` (plus one point each side)."""
    if bounds_m is None:
        return points
    xmin, ymin, xmax, ymax = bounds_m
    inside = (points[:, 0] >= xmin) & (points[:, 0] <= xmax) & (points[:, 1] >= ymin) & (points[:, 1] <= ymax)
    idx = np.flatnonzero(inside)
    if len(idx) == 0:
        return points[:0]
    lo, hi = max(int(idx[0]) - 1, 0), min(int(idx[-1]) + 2, len(points))
    return points[lo:hi]


def _network_of(road_or_network):
    """Accept a ``RoadNetwork`` or a ``Road`` (uses its ``.network``)."""
    net = getattr(road_or_network, "network", road_or_network)
    if not hasattr(net, "graph"):
        raise TypeError(
            f"read_highway_map: expected a highway-env RoadNetwork (env.unwrapped.road.network) or Road, "
            f"got {type(road_or_network).__name__}"
        )
    return net


def read_highway_map(
    road_network,
    step_m: float = 1.0,
    bounds_m: tuple[float, float, float, float] | None = None,
) -> HighwayMap:
    """Extract lane centrelines, road edges and lane successors from a highway-env road network.

    :param road_network: ``env.unwrapped.road.network`` (a ``Road`` is accepted too).
    :param step_m: sampling step along each lane [m], > 0.
    :param bounds_m: optional crop box ``(x_min, y_min, x_max, y_max)`` in the internal frame [m]; each
        polyline keeps the span between its first and last sample inside the box, polylines with fewer
        than 2 points left are dropped (highway-v0's lanes are 10 km long: crop to where traffic drives).
    :return: :class:`HighwayMap` (polylines in the internal frame + lane index -> polyline row).
    """
    if not step_m > 0:
        raise ValueError(f"read_highway_map: step_m must be > 0 metres, got {step_m}")
    net = _network_of(road_network)
    polylines: list[np.ndarray] = []
    kinds: list[int] = []
    ids: list[str] = []
    speeds: list[float] = []
    widths: list[float] = []
    lane_row: dict[LaneIndex, int] = {}
    ends_hw: dict[LaneIndex, tuple] = {}  # uncropped (start, end, width, start dir, end dir), y-down frame

    for a in net.graph:
        for b in net.graph[a]:
            for i, lane in enumerate(net.graph[a][b]):
                index: LaneIndex = (a, b, i)
                s = _sample_s(float(lane.length), step_m)  # [n]
                half_w = 0.5 * np.array([lane.width_at(float(si)) for si in s], np.float64)  # [n]
                centre_hw = _lane_points_hw(lane, s, np.zeros_like(s))  # [n, 2]
                ends_hw[index] = (
                    centre_hw[0],
                    centre_hw[-1],
                    float(2.0 * half_w.mean()),
                    _unit(centre_hw[1] - centre_hw[0]),  # start direction
                    _unit(centre_hw[-1] - centre_hw[-2]),  # end direction
                )
                centre = _crop(_to_internal(centre_hw), bounds_m)
                if len(centre) >= 2:
                    lane_row[index] = len(polylines)
                    polylines.append(centre)
                    kinds.append(LANE_CENTRE)
                    ids.append(lane_id(index))
                    limit = getattr(lane, "speed_limit", None)
                    speeds.append(float(limit) if limit is not None else 0.0)
                    widths.append(float(2.0 * half_w.mean()))
                line_types = list(getattr(lane, "line_types", None) or [])
                for side, (name, sign) in enumerate((("left", -1.0), ("right", 1.0))):
                    if side >= len(line_types) or line_types[side] not in ROAD_EDGE_LINE_TYPES:
                        continue
                    edge = _crop(_to_internal(_lane_points_hw(lane, s, sign * half_w)), bounds_m)
                    if len(edge) >= 2:
                        polylines.append(edge)
                        kinds.append(ROAD_EDGE)
                        ids.append(f"{lane_id(index)}#{name}")
                        speeds.append(0.0)
                        widths.append(0.0)

    successors = _successors(net, ends_hw, lane_row)
    mp = MapPolylines.from_lists(polylines, kinds, ids, speeds, widths, successors=successors)
    return HighwayMap(polylines=mp, lane_index=lane_row)


def _successors(net, ends_hw, lane_row) -> list[tuple[int, int]]:
    """Polyline-row pairs (lane, next lane) following the graph, filtered by geometric continuity."""
    out: list[tuple[int, int]] = []
    for a in net.graph:
        for b in net.graph[a]:
            for i in range(len(net.graph[a][b])):
                src = (a, b, i)
                if src not in lane_row:
                    continue
                _, end, width, _, end_dir = ends_hw[src]
                for c in net.graph.get(b, {}):
                    # same direction of travel only (two-way roads share node names: no U-turns)
                    cands = [
                        (b, c, j)
                        for j in range(len(net.graph[b][c]))
                        if float(ends_hw[(b, c, j)][3] @ end_dir) > MIN_HEADING_COS
                    ]
                    if not cands:
                        continue
                    dist = np.array([np.linalg.norm(ends_hw[d][0] - end) for d in cands])
                    tol = np.array([0.5 * max(width, ends_hw[d][2]) for d in cands])
                    keep = [d for d, di, ti in zip(cands, dist, tol, strict=True) if di <= ti]
                    k = int(np.argmin(dist))
                    if not keep and dist[k] <= MAX_GAP_LANE_WIDTHS * 2.0 * tol[k]:
                        keep = [cands[k]]
                    out.extend((lane_row[src], lane_row[d]) for d in keep if d in lane_row)
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-9)
