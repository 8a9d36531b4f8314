"""SUMO network (``.net.xml``) -> simulator-free map (:class:`~r1sim_sumo.scenario.MapPolylines`).

Frame: SUMO network coordinates are already metres in a Cartesian frame (x east, y north), which is the
internal frame; they are kept as they are (the geo offset ``net_offset`` is *not* applied, it is only kept
for reference, e.g. to convert back to the original projection).

What the map holds (one polyline per row of ``MapPolylines``):

* ``LANE_CENTRE`` polylines, one for every *drivable* lane of every normal and junction-internal edge, in
  the direction of travel, ``lane_id`` = SUMO lane id, ``speed_limit_mps`` and ``width_m`` from the net.
  A lane is drivable when it allows at least one vehicle class other than ``pedestrian`` (sidewalks,
  crossings and walking areas are left out; bike lanes are kept, cyclists are agents too).
* ``ROAD_EDGE`` polylines: for each normal edge, the left border of its leftmost drivable lane
  (``<edge>#left``) and the right border of its rightmost drivable lane (``<edge>#right``), i.e. the
  centreline offset by +-width/2 (:func:`~r1sim_sumo.geometry.offset_polyline`). Junction-internal edges
  get no road edges: their lanes overlap each other inside the junction, so per-lane borders would cut
  through drivable area; the junction area is delimited by the borders of the edges entering/leaving it.
* Zero-length lanes (shape shorter than ``MIN_LANE_LENGTH_M``) are left out with a logged warning; overlapping
  junctions and crossing lanes are kept as they are (the lane locator resolves overlaps by heading).
* ``successors``: lane connectivity, including the junction-internal lanes: a connection
  ``from -> to via v`` gives ``from -> v`` and the internal lane's own connection ``v -> to`` (or
  ``v -> v2 -> to`` for internal lanes split at an internal junction).

* ``turns_off_major_road``: the junction-internal lanes of the unsignalised connections that turn (SUMO direction
  ``r l R L``) from an edge onto one of lower SUMO ``priority`` (leaving the major road: a roundabout's exits). The SUMO
  controller's position drive lets SUMO drive a vehicle through such a turn (the policy has no route input).

Traffic lights (:meth:`SumoMap.tl_states`): each signalised connection ``from -> to via v`` has a TLS id
and a link index into the TLS's ``getRedYellowGreenState`` string. The via (internal) lane gets its
link's state. The incoming lane gets the state of its *most permissive* link (green > none > yellow >
red), so a lane with a green left turn and a red straight link reads green: "some movement may go".
Character mapping: ``G g s`` -> green (``s`` = green right-turn arrow after stopping), ``y Y`` -> yellow,
``r R u`` -> red (``u`` = red+yellow before green), ``o O`` -> none (signal off: the junction behaves
as unsignalised). Lanes without a signalised link and road edges read ``TL_NONE``.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from r1sim_sumo.geometry import offset_polyline
from r1sim_sumo.scenario import (
    LANE_CENTRE,
    ROAD_EDGE,
    TL_GREEN,
    TL_NONE,
    TL_RED,
    TL_YELLOW,
    MapPolylines,
)

NON_DRIVING_CLASSES = frozenset({"pedestrian"})
TURN_DIRECTIONS = frozenset("rlRL")  # SUMO connection directions that turn (right, left, partially right / left)
MIN_LANE_LENGTH_M = 1e-3  # [m] lanes with a shorter shape (degenerate, zero length) are left out with a warning
LOG = logging.getLogger(__name__)

# SUMO signal character -> TL code (anything unknown is treated as TL_NONE)
_TL_CHAR_TO_CODE = {"G": TL_GREEN, "g": TL_GREEN, "s": TL_GREEN, "y": TL_YELLOW, "Y": TL_YELLOW,
                    "r": TL_RED, "R": TL_RED, "u": TL_RED, "o": TL_NONE, "O": TL_NONE}
_CHAR_LUT = np.full(256, TL_NONE, np.int8)
for _c, _v in _TL_CHAR_TO_CODE.items():
    _CHAR_LUT[ord(_c)] = _v
# permissiveness rank of a TL code for the incoming-lane aggregate (lower = more permissive)
_CODE_TO_RANK = np.zeros(4, np.int8)
_CODE_TO_RANK[[TL_GREEN, TL_NONE, TL_YELLOW, TL_RED]] = [0, 1, 2, 3]
_RANK_TO_CODE = np.array([TL_GREEN, TL_NONE, TL_YELLOW, TL_RED], np.int8)
_NO_RANK = 127


class MapError(ValueError):
    """A SUMO network could not be turned into a map. The message names the file and what to do."""


def sumo_chars_to_tl(state: str) -> np.ndarray:
    """SUMO ``getRedYellowGreenState`` string -> ``[len(state)]`` int8 TL codes (see module doc)."""
    return _CHAR_LUT[np.frombuffer(state.encode("ascii", "replace"), np.uint8)]


@dataclass
class TlLinkTable:
    """Signalised connections of the network, ``K`` rows (one per controlled connection).

    :param tls_ids: ``[S]`` traffic-light system ids, in the order states are read.
    :param link_tls: ``[K]`` int32 index into ``tls_ids``.
    :param link_index: ``[K]`` int32 index into that TLS's state string.
    :param from_poly: ``[K]`` int32 polyline index of the incoming lane.
    :param via_poly: ``[K]`` int32 polyline index of the internal (via) lane, -1 when the net has none.
    :param to_poly: ``[K]`` int32 polyline index of the outgoing lane.
    """

    tls_ids: list[str]
    link_tls: np.ndarray
    link_index: np.ndarray
    from_poly: np.ndarray
    via_poly: np.ndarray
    to_poly: np.ndarray

    @property
    def num_links(self) -> int:
        return int(len(self.link_tls))


@dataclass
class SumoMap:
    """A SUMO network as map polylines plus connectivity and the traffic-light link table.

    :param polylines: lane centrelines + road edges, ``tl_state`` with 0 columns (static map).
    :param successors: lane id -> successor lane ids (through internal lanes, see module doc).
    :param lane_index: lane id -> polyline index (lane centrelines only).
    :param tl_links: the signalised connections (:class:`TlLinkTable`).
    :param net_offset: SUMO ``netOffset`` (x, y) [m], *not* applied to the coordinates.
    :param bounds: ``(xmin, ymin, xmax, ymax)`` [m] of the network (SUMO ``convBoundary``).
    :param net_file: the file read.
    :param turns_off_major_road: the junction-internal lanes (the via lane and the internal lanes it leads on to) of
        every unsignalised connection that turns (SUMO direction ``r``, ``l``, ``R`` or ``L``) from an edge onto one of
        lower SUMO priority: leaving the major road, e.g. a roundabout's exits (its ring has the higher priority). At a
        signal the signal orders the streams, not the roads' priorities (game/cross: SUMO driving its turns gave the
        same arrivals and 2 more collision events per run, docs/simulate/roundabout_s61).
    """

    polylines: MapPolylines
    successors: dict[str, list[str]]
    lane_index: dict[str, int]
    tl_links: TlLinkTable
    net_offset: tuple[float, float] = (0.0, 0.0)
    bounds: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    net_file: str = ""
    turns_off_major_road: frozenset[str] = frozenset()

    @property
    def num_polylines(self) -> int:
        return self.polylines.num_polylines

    @property
    def has_traffic_lights(self) -> bool:
        return self.tl_links.num_links > 0

    def tl_states(self, conn) -> np.ndarray:
        """Current traffic-light state per polyline, ``[L]`` int8 (TL_NONE/GREEN/YELLOW/RED).

        :param conn: the ``libsumo`` module or a ``traci`` connection running this network.
        Via lanes get their link's state, incoming lanes the most permissive of their links' states.
        """
        L = self.polylines.num_polylines
        out = np.full(L, TL_NONE, np.int8)  # [L]
        t = self.tl_links
        if t.num_links == 0:
            return out
        states = [conn.trafficlight.getRedYellowGreenState(tls) for tls in t.tls_ids]
        lens = np.array([len(s) for s in states], np.int64)
        offsets = np.concatenate([[0], np.cumsum(lens)[:-1]])
        if (t.link_index >= lens[t.link_tls]).any():
            k = int(np.argmax(t.link_index >= lens[t.link_tls]))
            tls = t.tls_ids[t.link_tls[k]]
            raise MapError(
                f"{self.net_file}: traffic light '{tls}' reports {lens[t.link_tls[k]]} signals but the network "
                f"file uses link index {t.link_index[k]}; the running simulation loaded a different network or "
                "TLS program: start SUMO with this net file"
            )
        codes = sumo_chars_to_tl("".join(states))[offsets[t.link_tls] + t.link_index]  # [K]
        has_via = t.via_poly >= 0
        out[t.via_poly[has_via]] = codes[has_via]
        rank = np.full(L, _NO_RANK, np.int8)  # [L]
        np.minimum.at(rank, t.from_poly, _CODE_TO_RANK[codes])
        hit = rank != _NO_RANK
        out[hit] = _RANK_TO_CODE[rank[hit]]
        return out


# ---------------------------------------------------------------------------- reading


def _load_net(path: Path):
    if not path.exists():
        raise MapError(f"{path}: SUMO network file not found; pass the path of an existing .net.xml "
                       "(bundled ones: r1sim_sumo.resources.network_files(name)['net'])")
    if path.is_dir():
        raise MapError(f"{path}: is a folder; pass the .net.xml file inside it")
    from r1sim_sumo._sumo_env import ensure_sumo_home

    ensure_sumo_home()
    import sumolib

    try:
        return sumolib.net.readNet(str(path), withInternal=True)
    except Exception as exc:  # sumolib surfaces SAX / attribute errors from deep inside its parser
        raise MapError(
            f"{path}: could not be read as a SUMO network ({type(exc).__name__}: {exc}); the file is not valid "
            "SUMO .net.xml: rebuild it with netconvert (e.g. `netconvert --node-files ... -o net.net.xml`)"
        ) from exc


def _drivable(lane) -> bool:
    return bool(set(lane.getPermissions()) - NON_DRIVING_CLASSES)


def _shape(lane) -> np.ndarray:
    return np.asarray(lane.getShape(), np.float64).reshape(-1, 2)  # [P, 2]


def read_sumo_map(net_file: str | os.PathLike) -> SumoMap:
    """Read a SUMO ``.net.xml`` (or ``.net.xml.gz``) into a :class:`SumoMap` covering the whole network.

    Raises :class:`MapError` for a missing or unreadable file, or a network without drivable lanes.
    """
    path = Path(net_file)
    net = _load_net(path)
    edges = [e for e in net.getEdges(withInternal=True) if e.getFunction() in ("", "normal", "internal")]

    lines: list[np.ndarray] = []
    kind: list[int] = []
    ids: list[str] = []
    speed: list[float] = []
    width: list[float] = []
    lane_index: dict[str, int] = {}
    lanes = []
    skipped: list[str] = []  # zero-length lanes (degenerate shapes): left out, logged
    for e in edges:
        for lane in e.getLanes():
            if not _drivable(lane):
                continue
            shp = _shape(lane)
            if len(shp) < 2:
                continue
            if np.hypot(*np.diff(shp, axis=0).T).sum() < MIN_LANE_LENGTH_M:
                skipped.append(lane.getID())
                continue
            lane_index[lane.getID()] = len(lines)
            lanes.append(lane)
            lines.append(shp)
            kind.append(LANE_CENTRE)
            ids.append(lane.getID())
            speed.append(float(lane.getSpeed()))
            width.append(float(lane.getWidth()))
    if skipped:
        LOG.warning("%s: %d zero-length lane(s) left out of the map (shape shorter than %.3f m): %s", path, len(skipped),
                    MIN_LANE_LENGTH_M, ", ".join(skipped[:10]))
    if not lines:
        raise MapError(
            f"{path}: the network has no drivable lanes (edges found: {len(edges)}); a map needs at least one "
            "lane allowing vehicles: check the file is a SUMO .net.xml built by netconvert, not a route file"
        )

    # road edges: left border of the leftmost and right border of the rightmost drivable lane per normal edge
    for e in edges:
        if e.getFunction() == "internal":
            continue
        dl = [ln for ln in e.getLanes() if ln.getID() in lane_index]
        if not dl:
            continue
        right = min(dl, key=lambda ln: ln.getIndex())  # SUMO lane index 0 = rightmost
        left = max(dl, key=lambda ln: ln.getIndex())
        for lane, sign, tag in ((left, 1.0, "left"), (right, -1.0, "right")):
            lines.append(offset_polyline(_shape(lane), sign * 0.5 * lane.getWidth()))
            kind.append(ROAD_EDGE)
            ids.append(f"{e.getID()}#{tag}")
            speed.append(0.0)
            width.append(0.0)

    # connectivity and the signalised link table
    successors: dict[str, list[str]] = {ln.getID(): [] for ln in lanes}
    succ_idx: list[tuple[int, int]] = []
    tls_pos: dict[str, int] = {}
    tl_rows: list[tuple[int, int, int, int, int]] = []
    off_major: set[str] = set()
    for lane in lanes:
        src = lane.getID()
        for c in lane.getOutgoing():
            via = c.getViaLaneID() or ""
            to = c.getToLane().getID()
            if via and c.getDirection() in TURN_DIRECTIONS and not c.getTLSID() and _leaves_major_road(c):
                off_major.add(via)
            nxt = via if via else to
            if nxt in lane_index and nxt not in successors[src]:
                successors[src].append(nxt)
                succ_idx.append((lane_index[src], lane_index[nxt]))
            tls = c.getTLSID()
            if tls and c.getTLLinkIndex() >= 0 and to in lane_index:
                s = tls_pos.setdefault(tls, len(tls_pos))
                tl_rows.append((s, int(c.getTLLinkIndex()), lane_index[src], lane_index.get(via, -1), lane_index[to]))
    rows = np.asarray(tl_rows, np.int32).reshape(-1, 5)
    tl_links = TlLinkTable(
        tls_ids=list(tls_pos), link_tls=rows[:, 0].copy(), link_index=rows[:, 1].copy(),
        from_poly=rows[:, 2].copy(), via_poly=rows[:, 3].copy(), to_poly=rows[:, 4].copy(),
    )

    off_major = _with_internal_successors(off_major, successors)
    polylines = MapPolylines.from_lists(lines, kind, ids, speed, width, successors=succ_idx)
    xmin, ymin, xmax, ymax = (float(v) for v in net.getBoundary())
    ox, oy = (float(v) for v in net.getLocationOffset())
    return SumoMap(
        polylines=polylines, successors=successors, lane_index=lane_index, tl_links=tl_links,
        net_offset=(ox, oy), bounds=(xmin, ymin, xmax, ymax), net_file=str(path),
        turns_off_major_road=frozenset(off_major),
    )


def _leaves_major_road(conn) -> bool:
    """Whether connection ``conn`` leads from a normal edge onto a normal edge of lower SUMO priority."""
    src, dst = conn.getFrom(), conn.getTo()
    if src.getFunction() == "internal" or dst.getFunction() == "internal":
        return False
    return src.getPriority() > dst.getPriority()


def _with_internal_successors(vias: set[str], successors: dict[str, list[str]]) -> set[str]:
    """``vias`` and the internal lanes they lead on to before a normal lane (an internal junction splits a junction's
    way in two), along the map's ``successors``."""
    out, todo = set(vias), list(vias)
    while todo:
        for nxt in successors.get(todo.pop(), ()):
            if nxt.startswith(":") and nxt not in out:
                out.add(nxt)
                todo.append(nxt)
    return out
