"""Motion vocabulary: 0.5 s trajectory segments clustered by k-disk, one sub-vocabulary per agent type.

A token is a 6-frame trajectory (5 steps at 10 Hz, both ends included) ``(x [m], y [m], yaw [rad])`` in the
frame of its START pose (frame 0 is ``(0, 0, 0)``, x forward, y left), together with the corners of a
fixed-size box (:data:`BOX_SIZE_M`) at each frame. Token 0 of every type is "standing still".

Building (SMART-style k-disk): all valid 6-frame segments of all agents at every start offset are
extracted in the start pose's frame; their box corners are compared by the *mean corner distance*
(mean Euclidean distance over the 6 frames x 4 corners [m]). The greedy k-disk repeatedly picks a random
remaining segment as a token and removes every segment within ``tolerance_m`` of it, until the requested
size is reached or nothing remains. Forced first: token 0 = standing still, then a kinematic grid of exact
straight and constant-curvature tokens at every speed (:func:`kinematic_grid_segments`; without it motorway
vehicles cannot drive straight in token space). Tokens are pairwise farther apart than the tolerance, so
there are no duplicates.

Types with fewer than ``min_real_segments`` segments in the data (e.g. SUMO/highway-env data without
cyclists or pedestrians) are built from *synthetic* segments: a unicycle model with random initial speed,
longitudinal acceleration, yaw rate and yaw acceleration within kinematically plausible bounds
(:data:`SYNTHETIC_LIMITS`: cyclists 0-8 m/s, pedestrians 0-2.5 m/s). The vocabulary's ``meta["source"]``
records which types came from data and which are synthetic.

Storage: ``save(path)`` writes a safetensors file (tensors ``traj/<type>``, ``corners/<type>``; the JSON
metadata in the safetensors header) and a human-readable JSON sidecar ``<path>.json``. No pickle.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from r1sim_sumo.geometry import box_corners, wrap_angle
from r1sim_sumo.scenario import AGENT_TYPES, CYCLIST, DT_S, PEDESTRIAN, VEHICLE, AgentTracks
from r1sim_sumo.tokens.constants import FRAMES_PER_TOKEN as FRAMES
from r1sim_sumo.tokens.constants import STEPS_PER_TOKEN as STEPS

TYPES = (VEHICLE, CYCLIST, PEDESTRIAN)
BOX_SIZE_M: dict[int, tuple[float, float]] = {VEHICLE: (4.8, 2.0), CYCLIST: (2.0, 1.0), PEDESTRIAN: (1.0, 1.0)}
MAX_STEP_DISPLACEMENT_M = 8.0  # [m per 0.1 s] = 80 m/s; larger jumps are teleports, not motion
VOCAB_FORMAT_VERSION = 1
GRID_MAX_SPEED_MPS = {VEHICLE: 40.0, CYCLIST: 10.0, PEDESTRIAN: 3.0}  # top speed of the kinematic grid

# (max speed [m/s], max |accel| [m/s^2], max |yaw rate| [rad/s], max lateral accel [m/s^2], max |yaw accel| [rad/s^2])
SYNTHETIC_LIMITS: dict[int, tuple[float, float, float, float, float]] = {
    VEHICLE: (35.0, 5.0, 1.0, 5.0, 2.0),
    CYCLIST: (8.0, 2.5, 1.5, 3.0, 3.0),
    PEDESTRIAN: (2.5, 1.5, 2.5, 3.0, 5.0),
}


class VocabError(ValueError):
    """A vocabulary (or a file holding one) is invalid; the message names the file and field."""


# ---------------------------------------------------------------------------- segments


def segment_corners(traj: np.ndarray, agent_type: int) -> np.ndarray:
    """Corners of the type's fixed-size box along trajectories ``[..., 6, 3]`` -> ``[..., 6, 4, 2]`` (same frame)."""
    length, width = BOX_SIZE_M[agent_type]
    traj = np.asarray(traj)
    return box_corners(traj[..., 0], traj[..., 1], traj[..., 2], length, width).astype(np.float32)


def extract_segments(tracks: AgentTracks, agent_type: int | None = None, stride: int = 1) -> np.ndarray:
    """All valid 6-frame (0.5 s) segments of the tracks, every start offset, in the start pose's frame.

    :param tracks: agent tracks at 10 Hz (world frame, box centres).
    :param agent_type: keep only agents of this type (0/1/2); ``None`` keeps all.
    :param stride: start offsets ``0, stride, 2*stride, ...`` (1 = every offset).
    :return: float32 ``[S, 6, 3]`` (x [m], y [m], yaw [rad]); frame 0 is ``(0, 0, 0)``. Segments with a
        jump above :data:`MAX_STEP_DISPLACEMENT_M` per step (teleports) are dropped.
    """
    sel = np.ones(tracks.num_agents, bool) if agent_type is None else np.asarray(tracks.agent_type) == agent_type
    T = tracks.num_steps
    if not sel.any() or T < FRAMES:
        return np.zeros((0, FRAMES, 3), np.float32)
    win = lambda a: np.lib.stride_tricks.sliding_window_view(np.asarray(a)[sel], FRAMES, axis=1)[:, ::stride]  # noqa: E731
    x, y, yaw = (win(a).astype(np.float64) for a in (tracks.x_m, tracks.y_m, tracks.yaw_rad))  # [A, W, 6]
    ok = win(tracks.valid).all(-1)  # [A, W]
    x, y, yaw = x[ok], y[ok], yaw[ok]  # [S, 6]
    step = np.hypot(np.diff(x, axis=1), np.diff(y, axis=1))
    ok = (step <= MAX_STEP_DISPLACEMENT_M).all(-1)
    x, y, yaw = x[ok], y[ok], yaw[ok]
    dx, dy = x - x[:, :1], y - y[:, :1]
    c, s = np.cos(yaw[:, :1]), np.sin(yaw[:, :1])
    local = np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(yaw - yaw[:, :1])], -1)  # [S, 6, 3]
    return local.astype(np.float32)


def synthetic_segments(agent_type: int, n: int, seed: int = 0) -> np.ndarray:
    """Kinematically plausible synthetic 0.5 s segments ``[n, 6, 3]`` (start-pose frame) for ``agent_type``.

    Unicycle model at 10 Hz: initial speed ~ U(0, v_max) (a quarter of the samples below 1 m/s so slow
    motion is well covered), constant longitudinal acceleration ~ U(-a_max, a_max) (speed clipped at 0),
    initial yaw rate ~ U(-w, w) with ``w = min(w_max, a_lat_max / v)`` and yaw acceleration ~
    U(-dw_max, dw_max). Limits per type: :data:`SYNTHETIC_LIMITS`.
    """
    v_max, a_max, w_max, alat_max, dw_max = SYNTHETIC_LIMITS[agent_type]
    rng = np.random.default_rng(seed)
    v0 = rng.uniform(0.0, v_max, n)
    slow = rng.random(n) < 0.25
    v0[slow] = rng.uniform(0.0, min(1.0, v_max), slow.sum())
    acc = rng.uniform(-a_max, a_max, n)
    w_lim = np.minimum(w_max, alat_max / np.maximum(v0, 1e-3))
    w0 = rng.uniform(-1.0, 1.0, n) * w_lim
    dw = rng.uniform(-dw_max, dw_max, n)
    t = np.arange(STEPS) * DT_S  # [5] start time of each step [s]
    v = np.clip(v0[:, None] + acc[:, None] * (t + 0.5 * DT_S), 0.0, v_max)  # [n, 5] mean speed in step
    w = np.clip(w0[:, None] + dw[:, None] * (t + 0.5 * DT_S), -w_max, w_max)  # [n, 5] mean yaw rate in step
    dyaw = w * DT_S
    yaw = np.concatenate([np.zeros((n, 1)), np.cumsum(dyaw, 1)], 1)  # [n, 6]
    mid = yaw[:, :-1] + 0.5 * dyaw
    x = np.concatenate([np.zeros((n, 1)), np.cumsum(v * DT_S * np.cos(mid), 1)], 1)
    y = np.concatenate([np.zeros((n, 1)), np.cumsum(v * DT_S * np.sin(mid), 1)], 1)
    return np.stack([x, y, wrap_angle(yaw)], -1).astype(np.float32)


def constant_curvature_segments(arc_m, dyaw_rad) -> np.ndarray:
    """``[n, 6, 3]`` constant-speed, constant-curvature 0.5 s segments (start-pose frame) of arc lengths ``arc_m [n]``
    [m] and heading changes ``dyaw_rad [n]`` [rad, + = left]; ``dyaw 0`` is straight."""
    d = np.asarray(arc_m, np.float64)[:, None]  # [n, 1] arc length [m]
    dyaw = np.asarray(dyaw_rad, np.float64)[:, None]  # [n, 1] heading change [rad]
    f = np.arange(FRAMES)[None] / (FRAMES - 1)  # [1, 6] fraction of the segment
    s = d * f  # arc length travelled
    curv = np.where(np.abs(dyaw) > 0, dyaw / np.maximum(d, 1e-9), 0.0)  # [n, 1] [1/m]
    safe = np.where(np.abs(curv) > 0, curv, 1.0)
    x = np.where(np.abs(curv) > 0, np.sin(curv * s) / safe, s)
    y = np.where(np.abs(curv) > 0, (1.0 - np.cos(curv * s)) / safe, 0.0)
    return np.stack([x, y, dyaw * f], -1).astype(np.float32)


def kinematic_grid_segments(agent_type: int, tolerance_m: float) -> np.ndarray:
    """Exact straight and constant-curvature 0.5 s segments ``[n, 6, 3]`` (start-pose frame) at every speed.

    Data-driven k-disk spends its budget where the data is dense (urban speeds); at motorway speeds it leaves
    few tokens, none of them exactly straight, and rolling matching of a vehicle driving straight at 30 m/s
    then zig-zags by a metre (heading errors of the nearest tokens accumulate). This grid guarantees that
    straight driving is representable exactly: constant-speed straight tokens every ``2.5 * tolerance_m`` of
    displacement up to the type's maximum speed x 0.5 s, plus constant-curvature tokens with heading changes
    of +-0.5, 1 and 2 degrees from 5 m of displacement (10 m/s) on, every metre. Tokens closer than
    ``tolerance_m`` (mean corner distance) to an earlier grid token are dropped, so the grid has no duplicates.
    """
    d_max = GRID_MAX_SPEED_MPS[agent_type] * STEPS * DT_S  # [m] per token
    step = 2.5 * tolerance_m  # mean corner distance between neighbours = step / 2 (mean over the 6 frames)
    rows = [(d, 0.0) for d in np.arange(step, d_max + 1e-9, step)]
    for d in np.arange(5.0, d_max + 1e-9, 1.0):
        for dyaw_deg in (0.5, -0.5, 1.0, -1.0, 2.0, -2.0):
            rows.append((d, math.radians(dyaw_deg)))
    seg = constant_curvature_segments([r[0] for r in rows], [r[1] for r in rows])  # [n, 6, 3]
    corners = segment_corners(seg, agent_type).reshape(len(seg), -1, 2)
    keep: list[int] = []
    for i in range(len(seg)):
        if keep:
            dist = np.sqrt(((corners[keep] - corners[i]) ** 2).sum(-1)).mean(-1)
            if dist.min() <= 1.001 * tolerance_m:
                continue
        keep.append(i)
    return seg[keep]


# ---------------------------------------------------------------------------- k-disk


def kdisk_cluster(
    corners: np.ndarray,
    tolerance_m: float,
    max_tokens: int,
    seed: int = 0,
    force_first: bool = False,
    progress: Callable[[int], None] | None = None,
    init_centres: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Greedy k-disk clustering on mean corner distance, vectorised over segments (numpy).

    Repeatedly pick a random remaining segment as a centre and remove every remaining segment whose mean
    corner distance to it (mean over 6 frames x 4 corners) is at most ``tolerance_m``.

    Pruning (exact, not an approximation): the mean of a box's 4 corners is its centre, so by the triangle
    inequality the mean corner distance is at least ``|end centre difference| / 6``; only segments whose
    end-frame centre x and y lie within ``6 * tolerance_m`` of the centre's can be removed. Segments are
    sorted by that x once and each pick computes exact distances only for that slice's candidates, which makes ~1M segments x 2048 picks take
    seconds on one CPU core.

    :param corners: ``[N, 6, 4, 2]`` box corners of the candidate segments [m].
    :param tolerance_m: disk radius [m] on the mean corner distance.
    :param max_tokens: stop after this many centres.
    :param force_first: candidate 0 is always the first centre (e.g. standing still).
    :param progress: called with the number of newly picked centres (for a progress bar).
    :param init_centres: ``[K, 6, 4, 2]`` existing centres: candidates within tolerance of them are removed
        first (they are not returned).
    :return: (indices of the picked centres ``[V]`` int64, fraction of candidates within tolerance of a centre).
    """
    import torch

    if tolerance_m <= 0:
        raise VocabError(f"tolerance_m must be > 0 (got {tolerance_m})")
    N = len(corners)
    if N == 0:
        return np.zeros(0, np.int64), 1.0
    X = np.asarray(corners, np.float32).reshape(N, -1, 2)  # [N, 24, 2]
    end_x = X[:, -4:, 0].mean(1)  # [N] end-frame box centre x (sort key)
    order = np.argsort(end_x, kind="stable")
    X, end_x = X[order], end_x[order]  # sorted by end x; rows map back through `order`
    end_y = X[:, -4:, 1].mean(1)  # [N] end-frame box centre y
    Xt = torch.from_numpy(X)  # shares memory
    alive = np.ones(N, bool)
    n_alive = N
    rng = np.random.default_rng(seed)
    reach = 6.0 * tolerance_m
    picked: list[int] = []
    pool = np.arange(N)  # superset of the alive rows, refreshed when mostly dead

    def remove_near(centre: np.ndarray, cx: float, cy: float) -> int:
        lo, hi = np.searchsorted(end_x, cx - reach, side="left"), np.searchsorted(end_x, cx + reach, side="right")
        near = lo + np.flatnonzero(alive[lo:hi] & (np.abs(end_y[lo:hi] - cy) <= reach))  # [n] candidates
        diff = Xt[torch.from_numpy(near)] - torch.from_numpy(np.asarray(centre, np.float32))  # [n, 24, 2]
        d = diff.square().sum(-1).sqrt().mean(-1).numpy()  # [n] mean corner distance
        kill = near[d <= tolerance_m]
        alive[kill] = False
        return len(kill)

    if init_centres is not None and len(init_centres):
        C = np.asarray(init_centres, np.float32).reshape(len(init_centres), -1, 2)
        for c in C:
            n_alive -= remove_near(c, float(c[-4:, 0].mean()), float(c[-4:, 1].mean()))
    while len(picked) < max_tokens and n_alive > 0:
        if force_first and not picked:
            row = int(np.flatnonzero(order == 0)[0])
        else:
            row = -1
            for _ in range(32):  # rejection sampling from the pool
                r = int(pool[rng.integers(len(pool))])
                if alive[r]:
                    row = r
                    break
            if row < 0:
                pool = np.flatnonzero(alive)
                row = int(pool[rng.integers(len(pool))])
        n_alive -= remove_near(X[row], float(end_x[row]), float(end_y[row]))
        if alive[row]:  # rounding: the centre always covers itself
            alive[row] = False
            n_alive -= 1
        picked.append(int(order[row]))
        if progress is not None:
            progress(1)
    covered = 1.0 - n_alive / N
    return np.asarray(picked, np.int64), covered


# ---------------------------------------------------------------------------- vocabulary


@dataclass
class MotionVocab:
    """Per-type token trajectories and box corners (start-pose frame); see the module docstring.

    :param traj: ``{type: float32 [V, 6, 3]}`` (x [m], y [m], yaw [rad]), frame 0 = (0, 0, 0).
    :param corners: ``{type: float32 [V, 6, 4, 2]}`` corners of the type's :data:`BOX_SIZE_M` box [m].
    :param meta: JSON-serialisable build information (tolerances, sources, report).
    """

    traj: dict[int, np.ndarray]
    corners: dict[int, np.ndarray]
    meta: dict = field(default_factory=dict)
    _torch_cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for t in TYPES:
            if t not in self.traj or t not in self.corners:
                raise VocabError(f"vocabulary misses agent type {t} ({AGENT_TYPES[t]})")
            tr, co = self.traj[t], self.corners[t]
            if tr.ndim != 3 or tr.shape[1:] != (FRAMES, 3) or co.shape != (len(tr), FRAMES, 4, 2) or len(tr) == 0:
                raise VocabError(f"traj/{AGENT_TYPES[t]}: expected [V>0, 6, 3] and corners [V, 6, 4, 2], got {tr.shape}, {co.shape}")
            self.traj[t] = np.ascontiguousarray(tr, np.float32)
            self.corners[t] = np.ascontiguousarray(co, np.float32)

    @classmethod
    def from_traj(cls, traj: dict[int, np.ndarray], meta: dict | None = None) -> MotionVocab:
        """Vocabulary from per-type trajectories ``[V, 6, 3]``; corners computed from :data:`BOX_SIZE_M`."""
        return cls({t: np.asarray(traj[t], np.float32) for t in TYPES},
                   {t: segment_corners(traj[t], t) for t in TYPES}, dict(meta or {}))

    # ----- sizes
    def size(self, agent_type: int) -> int:
        return int(len(self.traj[agent_type]))

    @property
    def sizes(self) -> tuple[int, int, int]:
        """Vocabulary size per type (vehicle, cyclist, pedestrian)."""
        return tuple(self.size(t) for t in TYPES)  # type: ignore[return-value]

    @property
    def max_size(self) -> int:
        """Largest sub-vocabulary (the width of a shared logits head)."""
        return max(self.sizes)

    # ----- torch views
    def torch_tables(self, device=None, dtype=None):
        """Padded torch tables ``(traj [3, V_max, 6, 3], corners [3, V_max, 6, 4, 2], valid [3, V_max] bool)``.

        Row ``t`` is agent type ``t``; ids ``>= size(t)`` are padding (standing still, ``valid`` False).
        Cached per (device, dtype).
        """
        import torch

        dtype = dtype or torch.float32
        key = (str(device), str(dtype))
        if key not in self._torch_cache:
            V = self.max_size
            traj = np.zeros((len(TYPES), V, FRAMES, 3), np.float32)
            corners = np.zeros((len(TYPES), V, FRAMES, 4, 2), np.float32)
            valid = np.zeros((len(TYPES), V), bool)
            for t in TYPES:
                n = self.size(t)
                traj[t, :n], corners[t, :n], valid[t, :n] = self.traj[t], self.corners[t], True
                corners[t, n:] = self.corners[t][0]  # padding = standing still
            self._torch_cache[key] = (
                torch.as_tensor(traj, dtype=dtype, device=device),
                torch.as_tensor(corners, dtype=dtype, device=device),
                torch.as_tensor(valid, device=device),
            )
        return self._torch_cache[key]

    # ----- identity and (de)serialisation
    def fingerprint(self) -> str:
        """16-hex hash of the token trajectories and box sizes (metadata excluded)."""
        h = hashlib.sha1(f"r1sim-vocab-v{VOCAB_FORMAT_VERSION}".encode())
        for t in TYPES:
            h.update(f"{AGENT_TYPES[t]}:{BOX_SIZE_M[t]}:{self.traj[t].shape}".encode())
            h.update(np.ascontiguousarray(self.traj[t], np.float32).tobytes())
        return h.hexdigest()[:16]

    def _meta_json(self) -> str:
        meta = dict(self.meta)
        meta.update(format_version=VOCAB_FORMAT_VERSION, fingerprint=self.fingerprint(),
                    sizes={AGENT_TYPES[t]: self.size(t) for t in TYPES},
                    box_size_m={AGENT_TYPES[t]: list(BOX_SIZE_M[t]) for t in TYPES})
        return json.dumps(meta, sort_keys=True, default=float)

    def to_dict(self, prefix: str = "vocab/") -> dict:
        """Tensors for embedding in a checkpoint: ``{prefix}traj/<type>``, ``{prefix}corners/<type>`` and
        ``{prefix}meta_json`` (uint8 bytes of the JSON metadata)."""
        import torch

        out = {}
        for t in TYPES:
            out[f"{prefix}traj/{AGENT_TYPES[t]}"] = torch.from_numpy(self.traj[t].copy())
            out[f"{prefix}corners/{AGENT_TYPES[t]}"] = torch.from_numpy(self.corners[t].copy())
        out[f"{prefix}meta_json"] = torch.frombuffer(bytearray(self._meta_json().encode()), dtype=torch.uint8).clone()
        return out

    @classmethod
    def from_dict(cls, d: dict, prefix: str = "vocab/", source: str = "checkpoint") -> MotionVocab:
        """Inverse of :meth:`to_dict` (accepts torch tensors or numpy arrays); checks the stored fingerprint."""
        def arr(k):
            if k not in d:
                raise VocabError(f"{source}: field '{k}' missing; not a r1sim motion vocabulary")
            v = d[k]
            return v.detach().cpu().numpy() if hasattr(v, "detach") else np.asarray(v)

        meta = json.loads(bytes(arr(f"{prefix}meta_json").astype(np.uint8)).decode())
        if meta.get("format_version") != VOCAB_FORMAT_VERSION:
            raise VocabError(f"{source}: vocabulary format_version {meta.get('format_version')} unsupported (expected {VOCAB_FORMAT_VERSION})")
        traj = {t: arr(f"{prefix}traj/{AGENT_TYPES[t]}") for t in TYPES}
        corners = {t: arr(f"{prefix}corners/{AGENT_TYPES[t]}") for t in TYPES}
        stored = meta.pop("fingerprint", None)
        for k in ("format_version", "sizes", "box_size_m"):
            meta.pop(k, None)
        vocab = cls(traj, corners, meta)
        if stored is not None and stored != vocab.fingerprint():
            raise VocabError(f"{source}: stored fingerprint {stored} does not match the tensors ({vocab.fingerprint()}); file corrupted?")
        return vocab

    def save(self, path: str | os.PathLike) -> Path:
        """Write ``path`` (safetensors, metadata JSON in the header) and ``path + '.json'`` (readable sidecar)."""
        from safetensors.numpy import save_file

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        d = {k: v.numpy() for k, v in self.to_dict(prefix="").items()}
        meta_json = self._meta_json()
        tmp = path.with_name(path.name + ".tmp")
        save_file(d, str(tmp), metadata={"r1sim_vocab": meta_json})
        os.replace(tmp, path)
        Path(str(path) + ".json").write_text(json.dumps(json.loads(meta_json), indent=2, sort_keys=True))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> MotionVocab:
        """Load a vocabulary written by :meth:`save` (no pickle)."""
        from safetensors.numpy import load_file

        path = Path(path)
        if not path.exists():
            raise VocabError(f"{path}: vocabulary file not found (build one with `r1sim vocab --data DIR --out {path}`)")
        try:
            d = load_file(str(path))
        except Exception as exc:  # safetensors raises its own error types
            raise VocabError(f"{path}: not a readable safetensors vocabulary ({exc})") from exc
        return cls.from_dict(d, prefix="", source=str(path))


# ---------------------------------------------------------------------------- building


@dataclass
class VocabBuildConfig:
    """Vocabulary build settings (per-type tuples are ordered vehicle, cyclist, pedestrian)."""

    size: tuple[int, int, int] = (2048, 512, 512)
    """Maximum tokens per type."""
    tolerance_m: tuple[float, float, float] = (0.05, 0.05, 0.05)
    """k-disk radius on mean corner distance [m]."""
    max_segments: int = 200_000
    """Segments per type fed to the clustering (random subsample)."""
    min_real_segments: int = 2_000
    """Types with fewer real segments are built from synthetic segments."""
    n_synthetic: int = 100_000
    """Synthetic segments generated for such a type (and for ``synthetic_fill``)."""
    synthetic_fill: float = 0.1
    """Fraction of a data-built sub-vocabulary reserved for synthetic segments that no data token covers
    (sharper or harsher motion than the data shows): rolling matching needs them to recover from poses the
    data tokens cannot follow, e.g. heading kinks in simulator geometry. 0 disables."""
    kinematic_grid: bool = True
    """Force :func:`kinematic_grid_segments` (exact straight / constant-curvature tokens at every speed) into
    data-built sub-vocabularies, after standing still and before the k-disk picks."""
    heldout_fraction: float = 0.1
    """Trailing fraction of the scenarios held out for the reconstruction report."""
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("size", "tolerance_m"):
            v = getattr(self, name)
            if isinstance(v, int | float):
                setattr(self, name, (v,) * 3)
            elif len(v) != 3:
                raise VocabError(f"VocabBuildConfig.{name}: expected one value or three (vehicle, cyclist, pedestrian), got {v}")
        if min(self.size) < 1:
            raise VocabError(f"VocabBuildConfig.size: each size must be >= 1, got {self.size}")
        if not 0.0 <= self.heldout_fraction < 1.0:
            raise VocabError(f"VocabBuildConfig.heldout_fraction must be in [0, 1), got {self.heldout_fraction}")


def build_vocab(segments: dict[int, np.ndarray], cfg: VocabBuildConfig | None = None, progress: bool = False) -> MotionVocab:
    """k-disk vocabulary from per-type segments ``{type: [S, 6, 3]}`` (start-pose frame).

    Types with fewer than ``cfg.min_real_segments`` segments get ``cfg.n_synthetic`` synthetic segments
    (:func:`synthetic_segments`) instead. Token 0 is forced to standing still.
    """
    cfg = cfg or VocabBuildConfig()
    rng = np.random.default_rng(cfg.seed)
    traj, meta = {}, {"tolerance_m": {}, "source": {}, "n_segments": {}, "coverage": {}, "seed": cfg.seed}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=int(sum(cfg.size)), desc="k-disk", unit="tok")
    for t in TYPES:
        seg = np.asarray(segments.get(t, np.zeros((0, FRAMES, 3))), np.float32).reshape(-1, FRAMES, 3)
        source = "data"
        if len(seg) < cfg.min_real_segments:
            seg = synthetic_segments(t, cfg.n_synthetic, seed=cfg.seed + 1 + t)
            source = "synthetic"
        if len(seg) > cfg.max_segments:
            seg = seg[rng.choice(len(seg), cfg.max_segments, replace=False)]
        forced = np.zeros((1, FRAMES, 3), np.float32)  # token 0 = standing still
        if cfg.kinematic_grid and source == "data":
            grid = kinematic_grid_segments(t, cfg.tolerance_m[t])
            forced = np.concatenate([forced, grid[: max(cfg.size[t] // 4 - 1, 0)]])  # at most a quarter of the vocabulary
            meta.setdefault("n_kinematic_grid_tokens", {})[AGENT_TYPES[t]] = int(len(forced) - 1)
        fill = cfg.synthetic_fill if source == "data" else 0.0
        n_main = max(cfg.size[t] - int(round(fill * cfg.size[t])), len(forced))
        upd = bar.update if bar else None
        if bar:
            bar.update(len(forced))
        picked, covered = kdisk_cluster(segment_corners(seg, t), cfg.tolerance_m[t], n_main - len(forced), seed=cfg.seed + t,
                                        progress=upd, init_centres=segment_corners(forced, t))
        tokens = np.concatenate([forced, seg[picked]])
        n_fill = cfg.size[t] - len(tokens)
        if fill > 0 and n_fill > 0:  # synthetic segments no data token covers
            syn = synthetic_segments(t, cfg.n_synthetic, seed=cfg.seed + 11 + t)
            extra, _ = kdisk_cluster(segment_corners(syn, t), cfg.tolerance_m[t], n_fill, seed=cfg.seed + 7 + t,
                                     progress=upd, init_centres=segment_corners(tokens, t))
            tokens = np.concatenate([tokens, syn[extra]])
            meta.setdefault("n_synthetic_fill_tokens", {})[AGENT_TYPES[t]] = int(len(extra))
        if bar is not None:
            bar.n = int(sum(len(x) for x in traj.values()) + len(tokens))
            bar.refresh()
        traj[t] = tokens
        name = AGENT_TYPES[t]
        meta["tolerance_m"][name] = float(cfg.tolerance_m[t])
        meta["source"][name] = source
        meta["n_segments"][name] = int(len(seg))
        meta["coverage"][name] = round(covered, 6)
    if bar is not None:
        bar.close()
    return MotionVocab.from_traj(traj, meta)
