"""Logged trajectory data -> :class:`~r1sim_sumo.scenario.Scenario` windows (generic CSV and highD).

Both loaders resample every track to 10 Hz by linear interpolation (yaw unwrapped first, wrapped after), cut
each scene into windows of 91 states (11 history + 80 future, current index 10) every ``stride_steps``
states, and keep in a window the agents that exist at its current state. All outputs are in the internal
frame: metres, x east, y north, yaw radians counter-clockwise from +x, positions = box centres.

Bad input is refused with :class:`LoggedDataError` (a :class:`ScenarioError`) naming the file, the row
(1-based line number in the file, the header being line 1) and the column, never loaded partially:
missing files, empty files, missing columns, NaN/empty cells, unknown agent types, speeds that look like
km/h (the reported speed is ~3.6x the speed implied by the positions, or above 80 m/s), yaw in degrees.

Generic CSV format (also in ``docs/logged_csv.md``)
---------------------------------------------------
Tracks file, one row per agent per frame, any frame rate (even irregular)::

    scene_id,frame,time_s,agent_id,agent_type,x_m,y_m,yaw_rad,speed_mps,length_m,width_m[,vx_mps,vy_mps]

* ``scene_id`` (str): scenes are windowed independently; ``frame`` (int): the source frame number (kept
  for reference, ordering uses ``time_s``); ``time_s`` (float, s): sample time, strictly increasing per agent.
* ``agent_id`` (str, unique within a scene); ``agent_type``: ``vehicle`` | ``cyclist`` | ``pedestrian``.
* ``x_m, y_m``: box centre [m], internal frame (y north); ``yaw_rad``: heading [rad, CCW from +x], within
  [-2 pi, 2 pi] (any branch: it is unwrapped); ``speed_mps``: signed longitudinal speed [m/s].
* ``length_m, width_m`` [m] (> 0; the first row of an agent is used).
* ``vx_mps, vy_mps`` (optional, both or neither) [m/s]; derived as ``speed * (cos yaw, sin yaw)`` if absent.

Map file, one row per polyline vertex, in order along the polyline::

    polyline_id,kind,x_m,y_m,speed_limit_mps,width_m

* ``kind``: ``lane_centre`` (vertices in the direction of travel) | ``road_edge``.
* ``speed_limit_mps`` [m/s] and ``width_m`` [m] are per polyline (the first vertex row is used; 0 for edges).
One map serves all scenes of the tracks file. Windows carry ``metadata["source"] == "csv"``.

A track may have gaps: a 10 Hz state is valid only when the two source samples around it are at most
``max_gap_s`` (0.5 s) apart.

Teleport jumps (clean-up, not an error): where two consecutive samples of an agent are farther apart than
``TELEPORT_SPEED_MPS`` (100 m/s) x their time difference, the track is split there and the part after the jump
becomes a new agent ``<agent_id>~<k>`` (k = 1, 2, ...), as the SUMO generator does for teleports; no state
is ever interpolated across a jump.

highD
-----
``load_highd(data_dir, recording_id)`` reads ``XX_tracks.csv``, ``XX_tracksMeta.csv`` and
``XX_recordingMeta.csv`` (XX = zero-padded 2-digit id) exactly as released (25 Hz). highD's image frame has
y pointing down and ``(x, y)`` is the upper-left corner of the axis-aligned box whose ``width`` is the
vehicle length along x and ``height`` its width. Conversion: centre = ``(x + width/2, y + height/2)``, then
``y_internal = -y_image`` (as :func:`r1sim_sumo.geometry.highway_to_internal`), velocity ``(vx, -vy)``, yaw
``atan2(-yVelocity, xVelocity)`` (vehicles slower than 0.5 m/s keep the yaw of their driving direction:
``drivingDirection`` 1 = towards -x, 2 = towards +x). Lane markings (``upperLaneMarkings``,
``lowerLaneMarkings``, image y, semicolon-separated) become lane centrelines between consecutive markings
(upper carriageway driving -x, lower driving +x) and road edges at the outermost markings of each
carriageway; they span the x range of the tracks plus 10 m. ``speedLimit`` is in m/s; -1 (no limit) maps
to :data:`HIGHD_DEFAULT_SPEED_LIMIT_MPS` (130 km/h, the German advisory speed).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from r1sim_sumo.geometry import highway_to_internal, wrap_angle
from r1sim_sumo.scenario import (
    AGENT_TYPES,
    CURRENT_INDEX,
    DT_S,
    LANE_CENTRE,
    MAX_ABS_SPEED_MPS,
    N_WINDOW_10HZ,
    POLYLINE_KINDS,
    ROAD_EDGE,
    TELEPORT_SPEED_MPS,
    AgentTracks,
    MapPolylines,
    Scenario,
    ScenarioError,
)

LOADER_VERSION = "logged-1"
MAX_GAP_S = 0.5  # [s] longest gap between two source samples bridged by interpolation
HIGHD_DEFAULT_SPEED_LIMIT_MPS = 130.0 / 3.6  # [m/s] used when highD's speedLimit is -1 (no limit)
HIGHD_MAP_MARGIN_M = 10.0  # [m] lane polylines extend this far beyond the tracks' x range
HIGHD_MAP_VERTEX_SPACING_M = 10.0  # [m]
_MIN_SPEED_FOR_YAW_MPS = 0.5  # [m/s] below this, highD yaw falls back to the driving direction
_KMH_RATIO = (2.5, 5.0)  # reported/implied speed ratios flagged as km/h

TRACK_COLUMNS = (
    "scene_id", "frame", "time_s", "agent_id", "agent_type", "x_m", "y_m", "yaw_rad", "speed_mps",
    "length_m", "width_m",
)
MAP_COLUMNS = ("polyline_id", "kind", "x_m", "y_m", "speed_limit_mps", "width_m")
HIGHD_TRACK_COLUMNS = ("frame", "id", "x", "y", "width", "height", "xVelocity", "yVelocity")
HIGHD_TRACKS_META_COLUMNS = ("id", "width", "height", "initialFrame", "finalFrame", "numFrames", "class", "drivingDirection")
HIGHD_RECORDING_META_COLUMNS = ("id", "frameRate", "locationId", "speedLimit", "upperLaneMarkings", "lowerLaneMarkings")


class LoggedDataError(ScenarioError):
    """Logged data that cannot be converted; the message names the file, the row and the column."""


# ---------------------------------------------------------------------------- CSV reading and checks


def _read_csv(path: Path, required: tuple[str, ...], text_columns: tuple[str, ...] = ()):
    """Read a CSV with pandas, refusing missing/empty files, missing columns and empty (NaN) cells."""
    import pandas as pd

    if not path.exists():
        raise LoggedDataError(f"{path}: file not found")
    if path.stat().st_size == 0:
        raise LoggedDataError(f"{path}: file is empty (expected a header with columns {', '.join(required)})")
    dtypes = {c: str for c in text_columns}
    try:
        df = pd.read_csv(path, dtype=dtypes, keep_default_na=True, skipinitialspace=True)
    except pd.errors.EmptyDataError as exc:
        raise LoggedDataError(f"{path}: file is empty ({exc})") from exc
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise LoggedDataError(f"{path}: not a readable CSV file ({exc})") from exc
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise LoggedDataError(f"{path}: missing column(s) {missing}; found columns {list(df.columns)}")
    if len(df) == 0:
        raise LoggedDataError(f"{path}: file has a header but no data rows")
    _refuse_nan(df, path, [c for c in df.columns if c in required])
    return df


def _refuse_nan(df, path: Path, columns: list[str]) -> None:
    for c in columns:
        bad = df[c].isna().to_numpy()
        if bad.any():
            row = int(np.argmax(bad))
            raise LoggedDataError(
                f"{path}: row {row + 2} (line in file), column '{c}': empty or NaN value; "
                f"{int(bad.sum())} such row(s). Fix or remove them: partial datasets are not loaded"
            )


def _numeric(df, path: Path, column: str, dtype=np.float64) -> np.ndarray:
    """Column as numbers; a non-numeric cell is refused naming its row."""
    import pandas as pd

    vals = pd.to_numeric(df[column], errors="coerce")
    bad = vals.isna().to_numpy()
    if bad.any():
        row = int(np.argmax(bad))
        raise LoggedDataError(f"{path}: row {row + 2} (line in file), column '{column}': not a number ({df[column].iloc[row]!r})")
    out = vals.to_numpy(np.float64)
    if not np.isfinite(out).all():
        row = int(np.argmax(~np.isfinite(out)))
        raise LoggedDataError(f"{path}: row {row + 2} (line in file), column '{column}': non-finite value {out[row]}")
    return out.astype(dtype)


def _check_speed_units(path: Path, column: str, t_s, x_m, y_m, speed_abs, agent_rows) -> None:
    """Refuse speeds above 80 m/s or ~3.6x the speed implied by the positions (km/h given as m/s)."""
    if (speed_abs > MAX_ABS_SPEED_MPS).any():
        row = int(np.argmax(speed_abs > MAX_ABS_SPEED_MPS))
        raise LoggedDataError(
            f"{path}: row {row + 2} (line in file), column '{column}': speed {speed_abs[row]:.1f} exceeds "
            f"{MAX_ABS_SPEED_MPS:.0f} m/s; speeds must be in m/s (km/h given? divide by 3.6)"
        )
    implied, reported = 0.0, 0.0
    for rows in agent_rows:
        if len(rows) < 2:
            continue
        dt = np.diff(t_s[rows])
        ds = np.hypot(np.diff(x_m[rows]), np.diff(y_m[rows]))
        ok = dt > 0
        implied += float(ds[ok].sum())
        reported += float((0.5 * (speed_abs[rows][1:] + speed_abs[rows][:-1]) * dt)[ok].sum())
    if implied > 1.0:
        ratio = reported / implied
        if _KMH_RATIO[0] < ratio < _KMH_RATIO[1]:
            raise LoggedDataError(
                f"{path}: column '{column}': speeds are {ratio:.2f}x the speed implied by the positions; "
                f"they look like km/h. Convert them to m/s (divide by 3.6)"
            )


# ---------------------------------------------------------------------------- 10 Hz resampling


@dataclass
class _Track:
    """One agent resampled onto the scene's 10 Hz grid from step ``k0`` on (arrays ``[n]``)."""

    agent_id: str
    agent_type: int
    length_m: float
    width_m: float
    k0: int
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray
    vx_mps: np.ndarray
    vy_mps: np.ndarray
    valid: np.ndarray

    @property
    def k1(self) -> int:
        """One past the last grid step covered."""
        return self.k0 + len(self.valid)


def resample_track_10hz(t_s: np.ndarray, t0_s: float, values: dict[str, np.ndarray], angle_keys=("yaw_rad",),
                        max_gap_s: float = MAX_GAP_S) -> tuple[int, dict[str, np.ndarray], np.ndarray]:
    """Linearly interpolate one agent's samples onto the grid ``t0_s + k * 0.1`` s.

    :param t_s: ``[n]`` strictly increasing sample times [s].
    :param values: name -> ``[n]`` samples; keys in ``angle_keys`` are unwrapped before and wrapped after.
    :returns: ``(k0, resampled [m] arrays, valid [m])`` covering grid steps ``k0 .. k0+m-1``; a step is
        valid when the samples around it are at most ``max_gap_s`` apart (or it hits a sample exactly).
    """
    eps = 1e-6
    k0 = int(math.ceil((t_s[0] - t0_s) / DT_S - eps))
    k1 = int(math.floor((t_s[-1] - t0_s) / DT_S + eps))
    if k1 < k0:
        return k0, {k: np.zeros(0) for k in values}, np.zeros(0, bool)
    g = t0_s + DT_S * np.arange(k0, k1 + 1)  # [m]
    g = np.clip(g, t_s[0], t_s[-1])
    out = {}
    for k, v in values.items():
        v = np.asarray(v, np.float64)
        if k in angle_keys:
            out[k] = wrap_angle(np.interp(g, t_s, np.unwrap(v)))
        else:
            out[k] = np.interp(g, t_s, v)
    i = np.clip(np.searchsorted(t_s, g, side="right") - 1, 0, len(t_s) - 1)
    j = np.minimum(i + 1, len(t_s) - 1)
    on_sample = np.abs(t_s[i] - g) < eps
    valid = on_sample | (t_s[j] - t_s[i] <= max_gap_s + eps)
    return k0, out, valid


def split_at_jumps(t_s: np.ndarray, x_m: np.ndarray, y_m: np.ndarray, max_speed_mps: float = TELEPORT_SPEED_MPS) -> list[np.ndarray]:
    """Index ranges of one agent's time-sorted samples ``[n]`` between teleport jumps.

    A jump is a pair of consecutive samples whose implied speed (distance / time difference) exceeds
    ``max_speed_mps``; returns ``[idx_0, idx_1, ...]`` (``idx_k`` the sample indices of piece ``k``).
    """
    if len(t_s) < 2:
        return [np.arange(len(t_s))]
    dist = np.hypot(np.diff(x_m), np.diff(y_m))  # [n-1] m
    jump = dist > max_speed_mps * np.maximum(np.diff(t_s), 1e-9)
    cuts = np.flatnonzero(jump) + 1
    return np.split(np.arange(len(t_s)), cuts)


def _piece_id(agent_id: str, k: int) -> str:
    return str(agent_id) if k == 0 else f"{agent_id}~{k}"


def _windows(tracks: list[_Track], num_steps: int, stride_steps: int, map_: MapPolylines, meta: dict,
             t0_s: float, max_windows: int | None) -> Iterator[Scenario]:
    """Cut 91-step windows every ``stride_steps``; keep agents valid at each window's current step."""
    if stride_steps < 1:
        raise ValueError(f"stride_steps must be >= 1, got {stride_steps}")
    n = 0
    for s in range(0, num_steps - N_WINDOW_10HZ + 1, stride_steps):
        if max_windows is not None and n >= max_windows:
            return
        cur = s + CURRENT_INDEX
        chosen = [tr for tr in tracks if tr.k0 <= cur < tr.k1 and tr.valid[cur - tr.k0]]
        if not chosen:
            continue
        a = AgentTracks.empty(len(chosen), N_WINDOW_10HZ)
        a.ids = np.array([tr.agent_id for tr in chosen], dtype=str)
        a.agent_type = np.array([tr.agent_type for tr in chosen], np.int8)
        a.length_m = np.array([tr.length_m for tr in chosen], np.float32)
        a.width_m = np.array([tr.width_m for tr in chosen], np.float32)
        for r, tr in enumerate(chosen):
            lo, hi = max(s, tr.k0), min(s + N_WINDOW_10HZ, tr.k1)  # grid steps overlapping the window
            src = slice(lo - tr.k0, hi - tr.k0)
            dst = slice(lo - s, hi - s)
            valid = tr.valid[src]
            a.valid[r, dst] = valid
            for f in AgentTracks.PER_STEP:
                getattr(a, f)[r, dst] = np.where(valid, getattr(tr, f)[src], 0.0)
        md = dict(meta, start_time_s=round(t0_s + s * DT_S, 6), window_start_step=s, window_index=n)
        yield Scenario(agents=a, map=map_, metadata=md).validate(source=meta.get("tracks_file"))
        n += 1


# ---------------------------------------------------------------------------- generic CSV


def _group_rows(keys: np.ndarray) -> dict[str, np.ndarray]:
    """Row indices per key, in order of first appearance."""
    order: dict[str, list[int]] = {}
    for i, k in enumerate(keys.tolist()):
        order.setdefault(k, []).append(i)
    return {k: np.asarray(v, np.int64) for k, v in order.items()}


def load_generic_map_csv(map_csv: str | os.PathLike) -> MapPolylines:
    """Read the map CSV (one row per vertex, see the module docstring) into :class:`MapPolylines`."""
    path = Path(map_csv)
    df = _read_csv(path, MAP_COLUMNS, text_columns=("polyline_id", "kind"))
    x, y = _numeric(df, path, "x_m"), _numeric(df, path, "y_m")
    spd, wid = _numeric(df, path, "speed_limit_mps"), _numeric(df, path, "width_m")
    kinds = df["kind"].str.strip().to_numpy()
    bad = ~np.isin(kinds, POLYLINE_KINDS)
    if bad.any():
        row = int(np.argmax(bad))
        raise LoggedDataError(f"{path}: row {row + 2} (line in file), column 'kind': {kinds[row]!r} is not one of {list(POLYLINE_KINDS)}")
    if (spd > MAX_ABS_SPEED_MPS).any():
        row = int(np.argmax(spd > MAX_ABS_SPEED_MPS))
        raise LoggedDataError(f"{path}: row {row + 2} (line in file), column 'speed_limit_mps': {spd[row]:.1f} m/s is not a road speed limit; km/h given? divide by 3.6")
    polys, kind, ids, limits, widths = [], [], [], [], []
    for pid, rows in _group_rows(df["polyline_id"].str.strip().to_numpy()).items():
        if len(set(kinds[rows].tolist())) != 1:
            raise LoggedDataError(f"{path}: polyline '{pid}', column 'kind': mixes {sorted(set(kinds[rows].tolist()))}")
        if len(rows) < 2:
            raise LoggedDataError(f"{path}: row {rows[0] + 2} (line in file), polyline '{pid}': needs at least 2 vertices")
        polys.append(np.stack([x[rows], y[rows]], 1))
        kind.append(POLYLINE_KINDS.index(kinds[rows[0]]))
        ids.append(pid)
        limits.append(spd[rows[0]])
        widths.append(wid[rows[0]])
    return MapPolylines.from_lists(polys, kind, ids, limits, widths)


def _generic_scene_tracks(df, path: Path, rows_all: np.ndarray, t0_s: float) -> list[_Track]:
    """Resample the agents of one scene (``rows_all`` = its row indices in ``df``)."""
    cols = {c: df[c] for c in df.columns}
    tracks = []
    agent_ids = cols["agent_id"].to_numpy()[rows_all]
    for aid, local in _group_rows(agent_ids).items():
        rows = rows_all[local]
        t = cols["time_s"].to_numpy(np.float64)[rows]
        order = np.argsort(t, kind="stable")
        rows, t = rows[order], t[order]
        if (np.diff(t) <= 0).any():
            r = rows[int(np.argmax(np.diff(t) <= 0)) + 1]
            raise LoggedDataError(f"{path}: row {r + 2} (line in file), column 'time_s': agent '{aid}' has two rows at time {t[1:][np.diff(t) <= 0][0]} s")
        vals_all = {f: cols[f].to_numpy(np.float64)[rows] for f in ("x_m", "y_m", "yaw_rad", "speed_mps", "vx_mps", "vy_mps")}
        for piece, idx in enumerate(split_at_jumps(t, vals_all["x_m"], vals_all["y_m"])):  # teleports: new agent
            k0, res, valid = resample_track_10hz(t[idx], t0_s, {f: v[idx] for f, v in vals_all.items()})
            if len(valid) == 0:
                continue
            tracks.append(_Track(
                agent_id=_piece_id(aid, piece), agent_type=AGENT_TYPES.index(cols["agent_type"].iloc[rows[0]]),
                length_m=float(cols["length_m"].iloc[rows[0]]), width_m=float(cols["width_m"].iloc[rows[0]]),
                k0=k0, valid=valid, **res,
            ))
    return tracks


def load_generic_csv(tracks_csv: str | os.PathLike, map_csv: str | os.PathLike, stride_steps: int = 20,
                     max_windows: int | None = None) -> list[Scenario]:
    """Load the generic logged-CSV format (module docstring, ``docs/logged_csv.md``) as 91-step windows.

    :param tracks_csv: tracks file (one row per agent per frame, any rate; resampled to 10 Hz).
    :param map_csv: map file (one row per polyline vertex), shared by all scenes.
    :param stride_steps: window start spacing [10 Hz steps].
    :param max_windows: stop after this many windows per scene (None = all).
    :returns: validated scenarios, ``metadata["source"] == "csv"``; a scene shorter than 9.1 s gives none.
    :raises LoggedDataError: on any bad input (file, row and column named).
    """
    path = Path(tracks_csv)
    map_ = load_generic_map_csv(map_csv)
    df = _read_csv(path, TRACK_COLUMNS, text_columns=("scene_id", "agent_id", "agent_type"))
    has_v = [c in df.columns for c in ("vx_mps", "vy_mps")]
    if any(has_v) and not all(has_v):
        raise LoggedDataError(f"{path}: column '{'vy_mps' if has_v[0] else 'vx_mps'}' missing: give both vx_mps and vy_mps or neither")
    numeric = ["frame", "time_s", "x_m", "y_m", "yaw_rad", "speed_mps", "length_m", "width_m"] + (["vx_mps", "vy_mps"] if all(has_v) else [])
    if all(has_v):
        _refuse_nan(df, path, ["vx_mps", "vy_mps"])
    for c in numeric:
        df[c] = _numeric(df, path, c)
    for c in ("scene_id", "agent_id", "agent_type"):
        df[c] = df[c].str.strip()
    types = df["agent_type"].to_numpy()
    bad = ~np.isin(types, AGENT_TYPES)
    if bad.any():
        row = int(np.argmax(bad))
        raise LoggedDataError(f"{path}: row {row + 2} (line in file), column 'agent_type': {types[row]!r} is not one of {list(AGENT_TYPES)}")
    for c in ("length_m", "width_m"):
        if (df[c] <= 0).any():
            row = int(np.argmax((df[c] <= 0).to_numpy()))
            raise LoggedDataError(f"{path}: row {row + 2} (line in file), column '{c}': box size must be > 0 m")
    yaw = df["yaw_rad"].to_numpy()
    if (np.abs(yaw) > 2 * math.pi + 1e-3).any():
        row = int(np.argmax(np.abs(yaw) > 2 * math.pi + 1e-3))
        raise LoggedDataError(f"{path}: row {row + 2} (line in file), column 'yaw_rad': {yaw[row]:.2f} is not an angle in radians (degrees given? multiply by pi/180)")
    if not all(has_v):
        df["vx_mps"] = df["speed_mps"] * np.cos(df["yaw_rad"])
        df["vy_mps"] = df["speed_mps"] * np.sin(df["yaw_rad"])

    out: list[Scenario] = []
    scenes = _group_rows(df["scene_id"].to_numpy())
    t_all, x_all, y_all = (df[c].to_numpy() for c in ("time_s", "x_m", "y_m"))
    for scene_id, rows in scenes.items():
        per_agent = [rows[r] for r in _group_rows(df["agent_id"].to_numpy()[rows]).values()]
        per_agent = [r[np.argsort(t_all[r], kind="stable")] for r in per_agent]
        _check_speed_units(path, "speed_mps", t_all, x_all, y_all, np.abs(df["speed_mps"].to_numpy()), per_agent)
        t0 = float(t_all[rows].min())
        tracks = _generic_scene_tracks(df, path, rows, t0)
        num_steps = max((tr.k1 for tr in tracks), default=0)
        meta = {"source": "csv", "network": f"csv:{Path(map_csv).name}", "scene_id": str(scene_id), "seed": None,
                "generator_version": LOADER_VERSION, "tracks_file": str(path)}
        out.extend(_windows(tracks, num_steps, stride_steps, map_, meta, t0, max_windows))
    return out


# ---------------------------------------------------------------------------- highD


def highd_paths(data_dir: str | os.PathLike, recording_id: int) -> tuple[Path, Path, Path]:
    """``(XX_tracks.csv, XX_tracksMeta.csv, XX_recordingMeta.csv)`` for a recording id (XX = 2 digits)."""
    d = Path(data_dir)
    p = f"{int(recording_id):02d}_"
    return d / f"{p}tracks.csv", d / f"{p}tracksMeta.csv", d / f"{p}recordingMeta.csv"


def _parse_markings(path: Path, column: str, text: str) -> np.ndarray:
    try:
        m = np.array([float(v) for v in str(text).split(";") if v.strip()], np.float64)
    except ValueError as exc:
        raise LoggedDataError(f"{path}: row 2 (line in file), column '{column}': expected ';'-separated numbers, got {text!r}") from exc
    if len(m) < 2 or (np.diff(m) <= 0).any():
        raise LoggedDataError(f"{path}: row 2 (line in file), column '{column}': need >= 2 increasing lane-marking y values, got {text!r}")
    return m


def highd_map(upper_markings: np.ndarray, lower_markings: np.ndarray, x_min_m: float, x_max_m: float,
              speed_limit_mps: float) -> MapPolylines:
    """Straight-highway map from highD lane markings (image y, pointing down) over ``[x_min_m, x_max_m]``.

    Lane centres lie halfway between consecutive markings; upper-carriageway lanes run towards -x, lower
    ones towards +x. Road edges follow the outermost markings of each carriageway (``#left``/``#right``
    relative to the direction of travel). Output in the internal frame (y up).
    """
    n = max(int(math.ceil((x_max_m - x_min_m) / HIGHD_MAP_VERTEX_SPACING_M)), 1) + 1
    xs = np.linspace(x_min_m, x_max_m, n)
    polys, kind, ids, limits, widths = [], [], [], [], []

    def line(y_img: float, towards_plus_x: bool) -> np.ndarray:
        xx = xs if towards_plus_x else xs[::-1]
        _, y_int, _ = highway_to_internal(xx, np.full_like(xx, y_img), np.zeros_like(xx))
        return np.stack([xx, y_int], 1)

    for name, m, plus_x in (("upper", upper_markings, False), ("lower", lower_markings, True)):
        for i in range(len(m) - 1):
            polys.append(line(0.5 * (m[i] + m[i + 1]), plus_x))
            kind.append(LANE_CENTRE)
            ids.append(f"{name}_{i}")
            limits.append(speed_limit_mps)
            widths.append(m[i + 1] - m[i])
        # driving -x (upper) the left side is +y_image (the median, last marking); driving +x it is -y_image
        left, right = (m[-1], m[0]) if not plus_x else (m[0], m[-1])
        for side, y_img in (("left", left), ("right", right)):
            polys.append(line(y_img, plus_x))
            kind.append(ROAD_EDGE)
            ids.append(f"{name}#{side}")
            limits.append(0.0)
            widths.append(0.0)
    return MapPolylines.from_lists(polys, kind, ids, limits, widths)


def load_highd(data_dir: str | os.PathLike, recording_id: int, stride_steps: int = 20,
               max_windows: int | None = None) -> list[Scenario]:
    """Load one highD recording as 91-step, 10 Hz windows (conversion in the module docstring).

    :param data_dir: folder holding ``XX_tracks.csv``, ``XX_tracksMeta.csv``, ``XX_recordingMeta.csv``.
    :param recording_id: highD recording number (1..60), zero-padded to 2 digits in file names.
    :param stride_steps: window start spacing [10 Hz steps].
    :param max_windows: stop after this many windows (None = all).
    :returns: validated scenarios with ``metadata["source"] == "highd"``.
    :raises LoggedDataError: on missing files/columns, NaN cells, inconsistent ids or non-m/s speeds.
    """
    tracks_p, tmeta_p, rmeta_p = highd_paths(data_dir, recording_id)
    for p in (tracks_p, tmeta_p, rmeta_p):
        if not p.exists():
            raise LoggedDataError(f"{p}: file not found (highD recording {int(recording_id):02d} expects "
                                  f"{tracks_p.name}, {tmeta_p.name}, {rmeta_p.name} in {Path(data_dir)})")
    rmeta = _read_csv(rmeta_p, HIGHD_RECORDING_META_COLUMNS, text_columns=("upperLaneMarkings", "lowerLaneMarkings"))
    frame_rate = float(_numeric(rmeta, rmeta_p, "frameRate")[0])
    if frame_rate <= 0:
        raise LoggedDataError(f"{rmeta_p}: row 2 (line in file), column 'frameRate': must be > 0, got {frame_rate}")
    speed_limit = float(_numeric(rmeta, rmeta_p, "speedLimit")[0])
    if speed_limit > MAX_ABS_SPEED_MPS:
        raise LoggedDataError(f"{rmeta_p}: row 2 (line in file), column 'speedLimit': {speed_limit} is not in m/s (km/h given? divide by 3.6)")
    speed_limit_used = HIGHD_DEFAULT_SPEED_LIMIT_MPS if speed_limit <= 0 else speed_limit
    upper = _parse_markings(rmeta_p, "upperLaneMarkings", rmeta["upperLaneMarkings"].iloc[0])
    lower = _parse_markings(rmeta_p, "lowerLaneMarkings", rmeta["lowerLaneMarkings"].iloc[0])

    tmeta = _read_csv(tmeta_p, HIGHD_TRACKS_META_COLUMNS, text_columns=("class",))
    meta_ids = _numeric(tmeta, tmeta_p, "id", np.int64)
    direction = dict(zip(meta_ids.tolist(), _numeric(tmeta, tmeta_p, "drivingDirection", np.int64).tolist(), strict=True))
    bad_dir = [i for i, d in direction.items() if d not in (1, 2)]
    if bad_dir:
        row = int(np.flatnonzero(meta_ids == bad_dir[0])[0])
        raise LoggedDataError(f"{tmeta_p}: row {row + 2} (line in file), column 'drivingDirection': must be 1 (towards -x) or 2 (towards +x)")
    klass = dict(zip(meta_ids.tolist(), tmeta["class"].str.strip().tolist(), strict=True))

    df = _read_csv(tracks_p, HIGHD_TRACK_COLUMNS)
    c = {k: _numeric(df, tracks_p, k) for k in HIGHD_TRACK_COLUMNS}
    ids = c["id"].astype(np.int64)
    unknown = ~np.isin(ids, meta_ids)
    if unknown.any():
        row = int(np.argmax(unknown))
        raise LoggedDataError(f"{tracks_p}: row {row + 2} (line in file), column 'id': track {ids[row]} not listed in {tmeta_p.name}")
    if (c["width"] <= 0).any() or (c["height"] <= 0).any():
        col = "width" if (c["width"] <= 0).any() else "height"
        row = int(np.argmax(c[col] <= 0))
        raise LoggedDataError(f"{tracks_p}: row {row + 2} (line in file), column '{col}': box size must be > 0 m")

    t_s = c["frame"] / frame_rate
    # image frame (upper-left corner, y down) -> internal frame (centre, y up)
    xc_img = c["x"] + 0.5 * c["width"]
    yc_img = c["y"] + 0.5 * c["height"]
    heading_img = np.arctan2(c["yVelocity"], c["xVelocity"])
    x_m, y_m, yaw = highway_to_internal(xc_img, yc_img, heading_img)
    vx, vy = c["xVelocity"], -c["yVelocity"]
    speed = np.hypot(vx, vy)
    rows_by_id = _group_rows(ids.astype(str))
    per_agent = [r[np.argsort(t_s[r], kind="stable")] for r in rows_by_id.values()]
    _check_speed_units(tracks_p, "xVelocity", t_s, x_m, y_m, speed, per_agent)

    t0 = float(t_s.min())
    tracks = []
    for aid, rows in zip(rows_by_id.keys(), per_agent, strict=True):
        t = t_s[rows]
        if (np.diff(t) <= 0).any():
            r = rows[int(np.argmax(np.diff(t) <= 0)) + 1]
            raise LoggedDataError(f"{tracks_p}: row {r + 2} (line in file), column 'frame': track {aid} has two rows at frame {int(c['frame'][r])}")
        yaw_a = yaw[rows].copy()
        slow = speed[rows] < _MIN_SPEED_FOR_YAW_MPS
        yaw_a[slow] = math.pi if direction[int(aid)] == 1 else 0.0
        vals = {"x_m": x_m[rows], "y_m": y_m[rows], "yaw_rad": yaw_a, "speed_mps": speed[rows],
                "vx_mps": vx[rows], "vy_mps": vy[rows]}
        for piece, idx in enumerate(split_at_jumps(t, vals["x_m"], vals["y_m"])):  # teleports: new agent
            k0, res, valid = resample_track_10hz(t[idx], t0, {f: v[idx] for f, v in vals.items()},
                                                 max_gap_s=max(MAX_GAP_S, 2.0 / frame_rate))
            if len(valid) == 0:
                continue
            tracks.append(_Track(agent_id=_piece_id(aid, piece), agent_type=AGENT_TYPES.index("vehicle"),
                                 length_m=float(np.median(c["width"][rows])), width_m=float(np.median(c["height"][rows])),
                                 k0=k0, valid=valid, **res))
    x_lo = float((c["x"]).min()) - HIGHD_MAP_MARGIN_M
    x_hi = float((c["x"] + c["width"]).max()) + HIGHD_MAP_MARGIN_M
    map_ = highd_map(upper, lower, x_lo, x_hi, speed_limit_used)
    num_steps = max((tr.k1 for tr in tracks), default=0)
    meta = {
        "source": "highd", "network": f"highd:location{int(_numeric(rmeta, rmeta_p, 'locationId')[0])}",
        "recording_id": int(recording_id), "seed": None, "generator_version": LOADER_VERSION,
        "frame_rate_hz": frame_rate, "speed_limit_mps": speed_limit_used, "speed_limit_given": speed_limit > 0,
        "num_trucks": int(sum(1 for k in klass.values() if k.lower() == "truck")), "tracks_file": str(tracks_p),
    }
    return list(_windows(tracks, num_steps, stride_steps, map_, meta, t0, max_windows))
