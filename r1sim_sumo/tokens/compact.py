"""Compact token dataset: a tokenized dataset in a few LZMA-compressed files, small enough to copy anywhere.

``r1sim tokens build --data data/generated/default --out data/tokens/default`` tokenizes the ``train`` and
``val`` splits of a scenario dataset folder once (exact rolling matching with the given vocabulary) and writes

* ``manifest.json``: format version, vocabulary fingerprint, map crop radius, per split the scene count and
  the arrays (dtype, shape, byte offset and length in the split's ``.xz`` file);
* ``vocab.safetensors``: the motion vocabulary the tokens index;
* ``<split>.xz``: every array of the split, concatenated and LZMA-compressed;
* ``<split>.polylines.npz``: the geometry of each de-duplicated map as :class:`~r1sim_sumo.scenario.MapPolylines`
  (lanes and road edges, no signal states), for what needs the map itself rather than its tokens: the offroad part
  of the GRPO reward (:class:`CompactTokenDataset.polylines`). Folders built before session 38 have none.

What a scene keeps (all exact: float32 values are the dataset's own):

* per agent: matched tokens ``[18]`` (int16; -1 invalid), the *logged* boundary poses ``[19]`` (x, y [m], yaw
  [rad], states 0, 5, ..., 90 of the window, box centre) and their validity, type, length and width [m].
  The matched boundary poses are replayed from the tokens (:func:`~r1sim_sumo.tokens.matching.match_agents`
  with ``given_tokens``, the same float64 arithmetic), and the noised matching of training re-matches from the
  logged poses, exactly as :meth:`TokenizedDataset.noised` does from the scenario;
* per map (de-duplicated: every scene of a network shares one): the map tokens of the whole map;
* per scene: the map it uses and the traffic-light states of the signalised polylines at the 19 boundaries.

Windows of one recording overlap (2 s stride, 9 s windows), so the same logged poses recur in consecutive scenes;
LZMA finds those repeats. A scene is rebuilt on access (tokens, replayed poses, map crop of
:func:`~r1sim_sumo.tokens.batch.crop_map` with the manifest's radius) and equals the one
:class:`~r1sim_sumo.tokens.batch.TokenizedDataset` tokenizes from the scenario (``tests/test_compact_tokens.py``).
"""

from __future__ import annotations

import json
import lzma
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from r1sim_sumo.scenario import N_HISTORY_10HZ, AgentTracks, MapPolylines, ScenarioDataset
from r1sim_sumo.tokens.batch import (
    DEFAULT_MAP_RADIUS_M,
    TokenizedScene,
    _window,
    crop_map,
    mask_history_labels,
    tokenize_scenario,
)
from r1sim_sumo.tokens.constants import CURRENT_POSE, N_POSE, STEPS_PER_TOKEN
from r1sim_sumo.tokens.map_tokens import MapTokens, token_kinds, tokenize_map
from r1sim_sumo.tokens.matching import TokenizedAgents, match_agents
from r1sim_sumo.tokens.motion_vocab import MotionVocab

FORMAT_VERSION = 2
"""2 (session 41): map tokens of ending lanes are kind 2 (``map_tokens.ENDING_LANE``). Version-1 folders are read with
their map kinds re-derived from the kept map geometry (``<split>.polylines.npz``), as a rebuild would write them."""
READABLE_VERSIONS = (1, 2)
MANIFEST = "manifest.json"
VOCAB_FILE = "vocab.safetensors"
SPLITS = ("train", "val")
POLYLINES_SUFFIX = ".polylines.npz"


class CompactFormatError(ValueError):
    """A compact token dataset that cannot be read (the message names the file and what to do)."""


def _map_signature(scenario) -> str:
    m = scenario.map
    key = scenario.metadata.get("_map_key")
    return str(key) if key else f"{len(m.points_m)}:{float(np.asarray(m.points_m, np.float64).sum()):.6f}"


def _scene_record(scenario, vocab: MotionVocab, map_radius_m: float) -> tuple[dict, TokenizedScene]:
    """Tokenize one scenario; return its per-agent arrays + signal states and the tokenized scene (for checks)."""
    scene = tokenize_scenario(scenario, vocab, map_radius_m=None)
    start = int(scenario.current_index) - (N_HISTORY_10HZ - 1)
    tracks = _window(scenario.agents, start).select(np.asarray(scene.agent_index))
    b = np.arange(N_POSE) * STEPS_PER_TOKEN
    tl_tab = np.asarray(scenario.map.tl_state)
    sig = np.flatnonzero(tl_tab.any(1)) if tl_tab.ndim == 2 and tl_tab.shape[1] else np.zeros(0, np.int64)
    cols = start + STEPS_PER_TOKEN * np.arange(N_POSE)
    tl = np.zeros((len(sig), N_POSE), np.int8)
    ok = (cols >= 0) & (cols < (tl_tab.shape[1] if tl_tab.ndim == 2 else 0))
    if len(sig):
        tl[:, ok] = tl_tab[sig][:, cols[ok]]
    a = scene.agents
    rec = {
        "token": a.token.astype(np.int16), "gt_x": np.asarray(tracks.x_m, np.float32)[:, b],
        "gt_y": np.asarray(tracks.y_m, np.float32)[:, b], "gt_yaw": np.asarray(tracks.yaw_rad, np.float32)[:, b],
        "gt_valid": np.asarray(tracks.valid, bool)[:, b], "agent_type": a.agent_type.astype(np.int8),
        "length_m": a.length_m.astype(np.float32), "width_m": a.width_m.astype(np.float32),
        "sig_polyline": sig.astype(np.int32), "sig_tl": tl,
        # per scene: tokens before this index are not labels (policy-driven history, r1sim_sumo.data.policy_history)
        "label_from": np.asarray([int(scenario.metadata.get("label_from_token", 0))], np.int8),
        # per agent: the simulator's desired speed [m/s], NaN unknown (then matching estimates it in hindsight)
        "desired_speed_mps": (np.full(len(a.agent_type), np.nan, np.float32) if tracks.desired_speed_mps is None
                              else np.asarray(tracks.desired_speed_mps, np.float32)),
    }
    return rec, scene


def _tokenize_range(args) -> tuple[list[dict], list[str], dict[str, tuple[MapTokens, MapPolylines]]]:
    """Worker: tokenize scenes ``lo..hi-1`` of a split folder; per-scene records, map signatures and the maps (their
    tokens and their geometry without signal states)."""
    folder, vocab_path, lo, hi, map_radius_m = args
    vocab = MotionVocab.load(vocab_path)
    ds = ScenarioDataset(folder, cache_shards=2)
    recs, sigs, maps = [], [], {}
    for i in range(lo, hi):
        sc = ds[i]
        key = _map_signature(sc)
        if key not in maps:
            geometry = replace(sc.map, tl_state=np.zeros((sc.map.num_polylines, 0), np.int8))
            maps[key] = (tokenize_map(sc.map, n_pose=N_POSE, first_step=0), geometry)
        recs.append(_scene_record(sc, vocab, map_radius_m)[0])
        sigs.append(key)
    return recs, sigs, maps


POLYLINE_FIELDS = ("points_m", "start", "kind", "lane_id", "speed_limit_mps", "width_m", "successors")


def _write_polylines(path: Path, maps: list[MapPolylines]) -> None:
    """Map ``k``'s geometry as arrays ``<field>_<k>`` of one compressed ``.npz`` (no pickled objects)."""
    arrays = {f"{f}_{k}": np.asarray(getattr(m, f), str if f == "lane_id" else None)
              for k, m in enumerate(maps) for f in POLYLINE_FIELDS}
    np.savez_compressed(path, num_maps=np.asarray(len(maps)), **arrays)


def _read_polylines(path: Path) -> list[MapPolylines]:
    with np.load(path, allow_pickle=False) as z:
        n = int(z["num_maps"])
        out = []
        for k in range(n):
            f = {name: z[f"{name}_{k}"] for name in POLYLINE_FIELDS}
            out.append(MapPolylines(tl_state=np.zeros((len(f["kind"]), 0), np.int8), **f))
    return out


def build_compact(data: str | os.PathLike, vocab: MotionVocab, out: str | os.PathLike, splits=SPLITS,
                  map_radius_m: float = DEFAULT_MAP_RADIUS_M, preset: int = 9, workers: int = 2,
                  progress: bool = True) -> dict:
    """Tokenize ``data/<split>`` for each split into the compact format under ``out``; returns the manifest.

    :param data: a dataset folder written by ``r1sim dataset build`` (``train/``, ``val/`` sub-folders).
    :param preset: LZMA preset (9 = smallest; building is dominated by tokenizing, not compressing).
    :param workers: processes tokenizing contiguous chunks of scenes (results are identical for any count).
    """
    import multiprocessing as mp

    from tqdm import tqdm

    data, out = Path(data), Path(out)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out}: output folder is not empty; choose another --out or delete it")
    for split in splits:
        if not (data / split / "manifest.json").exists():
            raise FileNotFoundError(f"{data / split}: no dataset split here (manifest.json missing); build it with "
                                    f"`r1sim dataset build --out {data}`")
    out.mkdir(parents=True, exist_ok=True)
    vocab.save(out / VOCAB_FILE)
    manifest = {"format_version": FORMAT_VERSION, "vocab_fingerprint": vocab.fingerprint(),
                "map_radius_m": map_radius_m, "source": str(data), "splits": {}}
    for split in splits:
        n = len(ScenarioDataset(data / split))
        chunk = 256
        jobs = [(str(data / split), str(out / VOCAB_FILE), lo, min(n, lo + chunk), map_radius_m) for lo in range(0, n, chunk)]
        bar = tqdm(total=n, desc=f"tokens {split}", unit="scn", disable=not progress)
        maps: dict[str, int] = {}
        map_arrays: list[MapTokens] = []
        map_geometry: list[MapPolylines] = []
        recs, map_of = [], []
        pool = mp.get_context("spawn").Pool(int(workers)) if workers > 1 else None
        try:
            results = pool.imap(_tokenize_range, jobs) if pool else map(_tokenize_range, jobs)
            for r, sigs, mtab in results:  # in job order: the output does not depend on the worker count
                for key in sigs:
                    if key not in maps:
                        maps[key] = len(map_arrays)
                        map_arrays.append(mtab[key][0])
                        map_geometry.append(mtab[key][1])
                    map_of.append(maps[key])
                recs += r
                bar.update(len(r))
        finally:
            if pool:
                pool.close()
                pool.join()
        bar.close()
        arrays = {k: np.concatenate([r[k] for r in recs]) for k in recs[0]} if recs else {}
        arrays["n_agents"] = np.asarray([len(r["agent_type"]) for r in recs], np.int32)
        arrays["n_sig"] = np.asarray([len(r["sig_polyline"]) for r in recs], np.int32)
        arrays["map_of_scene"] = np.asarray(map_of, np.int32)
        arrays["map_n_tokens"] = np.asarray([m.num_tokens for m in map_arrays], np.int32)
        for f in ("pts", "pos", "yaw", "kind", "speed_limit_mps", "polyline"):
            arrays[f"map_{f}"] = np.concatenate([getattr(m, f) for m in map_arrays])
        arrays["map_kind"] = arrays["map_kind"].astype(np.int8)
        arrays["map_polyline"] = arrays["map_polyline"].astype(np.int32)
        manifest["splits"][split] = {"num_scenes": n, "num_maps": len(map_arrays),
                                     "arrays": _write_xz(out / f"{split}.xz", arrays, preset)}
        _write_polylines(out / f"{split}{POLYLINES_SUFFIX}", map_geometry)
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1))
    return manifest


def _write_xz(path: Path, arrays: dict[str, np.ndarray], preset: int) -> dict:
    index, off = {}, 0
    comp = lzma.LZMACompressor(preset=preset)
    with open(path, "wb") as f:
        for name, a in arrays.items():
            a = np.ascontiguousarray(a)
            raw = a.tobytes()
            index[name] = {"dtype": a.dtype.str, "shape": list(a.shape), "offset": off, "nbytes": len(raw)}
            off += len(raw)
            f.write(comp.compress(raw))
        f.write(comp.flush())
    return index


class CompactTokenDataset:
    """One split of a compact token dataset, held in memory; items are :class:`TokenizedScene` (map cropped to
    the manifest's radius), ``noised(i, k, rng)`` re-matches from the logged boundary poses. Loading
    decompresses the split once (seconds)."""

    def __init__(self, root: str | os.PathLike, split: str = "train"):
        self.root = Path(root)
        man_path = self.root / MANIFEST
        try:
            man = json.loads(man_path.read_text())
        except FileNotFoundError:
            raise CompactFormatError(f"{man_path}: not found; build the compact dataset with `r1sim tokens build "
                                     f"--data <dataset folder> --out {self.root}`") from None
        if man.get("format_version") not in READABLE_VERSIONS:
            raise CompactFormatError(f"{man_path}: field 'format_version' is {man.get('format_version')!r}, this package "
                                     f"reads {list(READABLE_VERSIONS)}; rebuild it with `r1sim tokens build`")
        if split not in man.get("splits", {}):
            raise CompactFormatError(f"{man_path}: no split {split!r} (has {sorted(man.get('splits', {}))})")
        self.vocab = MotionVocab.load(self.root / VOCAB_FILE)
        if self.vocab.fingerprint() != man["vocab_fingerprint"]:
            raise CompactFormatError(f"{self.root / VOCAB_FILE}: vocabulary fingerprint differs from the manifest's "
                                     "'vocab_fingerprint'; the folder was mixed from two builds, rebuild it")
        self.split, self.map_radius_m = split, man["map_radius_m"]
        info = man["splits"][split]
        raw = lzma.decompress((self.root / f"{split}.xz").read_bytes())
        self.a = {}
        for name, d in info["arrays"].items():
            buf = raw[d["offset"]: d["offset"] + d["nbytes"]]
            if len(buf) != d["nbytes"]:
                raise CompactFormatError(f"{self.root / (split + '.xz')}: array {name!r} truncated; rebuild the dataset")
            self.a[name] = np.frombuffer(buf, dtype=np.dtype(d["dtype"])).reshape(d["shape"])
        self.n = int(info["num_scenes"])
        self.agent_off = np.concatenate([[0], np.cumsum(self.a["n_agents"])])
        self.sig_off = np.concatenate([[0], np.cumsum(self.a["n_sig"])])
        self.map_off = np.concatenate([[0], np.cumsum(self.a["map_n_tokens"])])
        self._polylines: list[MapPolylines] | None = None
        if man["format_version"] < 2:
            self.a["map_kind"] = self._map_kinds_from_geometry()

    def _map_kinds_from_geometry(self) -> np.ndarray:
        """``map_kind`` as this version's tokenizer writes it (ending lanes kind 2), from each map's kept geometry."""
        path = self.root / f"{self.split}{POLYLINES_SUFFIX}"
        if not path.exists():
            raise CompactFormatError(f"{path}: not found, and {self.root / MANIFEST} is format_version 1, whose map "
                                     "kinds do not mark ending lanes; rebuild the folder with `r1sim tokens build "
                                     f"--data <dataset folder> --out {self.root}`")
        maps = self._polylines = _read_polylines(path)
        kind = np.array(self.a["map_kind"], np.int8)
        for k, geometry in enumerate(maps):
            lo, hi = self.map_off[k], self.map_off[k + 1]
            kind[lo:hi] = token_kinds(geometry)[self.a["map_polyline"][lo:hi].astype(np.int64)]
        return kind

    @staticmethod
    def has_split(root: str | os.PathLike, split: str) -> bool:
        try:
            return split in json.loads((Path(root) / MANIFEST).read_text()).get("splits", {})
        except FileNotFoundError:
            return False

    def __len__(self) -> int:
        return self.n

    def _logged(self, i: int):
        """Per-agent logged boundary poses of scene ``i`` as a 19-step :class:`AgentTracks`-like object."""
        lo, hi = self.agent_off[i], self.agent_off[i + 1]
        A = int(hi - lo)
        t = AgentTracks.empty(A, N_POSE)
        t.x_m[:], t.y_m[:], t.yaw_rad[:] = self.a["gt_x"][lo:hi], self.a["gt_y"][lo:hi], self.a["gt_yaw"][lo:hi]
        t.valid[:] = self.a["gt_valid"][lo:hi]
        t.agent_type = self.a["agent_type"][lo:hi].astype(np.int64)
        t.length_m, t.width_m = self.a["length_m"][lo:hi].copy(), self.a["width_m"][lo:hi].copy()
        if "desired_speed_mps" in self.a:  # datasets built before session 17 have none: hindsight estimate
            t.desired_speed_mps = self.a["desired_speed_mps"][lo:hi].copy()
        return t, lo, hi

    def _map(self, i: int) -> MapTokens:
        k = int(self.a["map_of_scene"][i])
        lo, hi = self.map_off[k], self.map_off[k + 1]
        tl = np.zeros((int(hi - lo), N_POSE), np.int64)
        s0, s1 = self.sig_off[i], self.sig_off[i + 1]
        poly = self.a["map_polyline"][lo:hi].astype(np.int64)
        if s1 > s0:  # signal states of the scene's signalised polylines -> their tokens
            row = np.full(int(poly.max()) + 1, -1)
            row[self.a["sig_polyline"][s0:s1]] = np.arange(s1 - s0)
            r = row[poly]
            tl[r >= 0] = self.a["sig_tl"][s0:s1][r[r >= 0]]
        return MapTokens(pts=self.a["map_pts"][lo:hi], pos=self.a["map_pos"][lo:hi], yaw=self.a["map_yaw"][lo:hi],
                         kind=self.a["map_kind"][lo:hi].astype(np.int64), speed_limit_mps=self.a["map_speed_limit_mps"][lo:hi],
                         tl=tl, polyline=poly)

    def polylines(self, i: int) -> MapPolylines:
        """Scene ``i``'s map geometry (:class:`MapPolylines`: lanes and road edges in the scenes' world frame, no
        signal states), read once from ``<split>.polylines.npz``; what the GRPO reward's offroad check needs."""
        if self._polylines is None:
            path = self.root / f"{self.split}{POLYLINES_SUFFIX}"
            if not path.exists():
                raise CompactFormatError(f"{path}: not found (the folder was built before maps were kept with the "
                                         f"tokens); rebuild it with `r1sim tokens build --data <dataset folder> --out "
                                         f"{self.root}`, or set reward.offroad: false")
            self._polylines = _read_polylines(path)
        return self._polylines[int(self.a["map_of_scene"][i])]

    def _scene(self, i: int, agents: TokenizedAgents) -> TokenizedScene:
        A = agents.num_agents
        scene = TokenizedScene(agents, self._map(i), np.arange(A).astype(str), np.arange(A, dtype=np.int64),
                               f"{self.root.name}/{self.split}/{i}")
        return crop_map(scene, self.map_radius_m) if self.map_radius_m is not None else scene

    def label_from(self, i: int) -> int:
        """Tokens of scene ``i`` before this index are inputs only, not labels (0 for datasets built before the field)."""
        lf = self.a.get("label_from")
        return int(lf[i]) if lf is not None else 0

    def __getitem__(self, i: int) -> TokenizedScene:
        if i < 0:
            i += self.n
        if not 0 <= i < self.n:
            raise IndexError(f"scene {i} out of range for {self.n} scenes of {self.root}/{self.split}")
        t, lo, hi = self._logged(i)
        given = self.a["token"][lo:hi].astype(np.int64)
        return self._scene(i, mask_history_labels(match_agents(t, self.vocab, given_tokens=given, boundary_only=True), self.label_from(i)))

    def noised(self, i: int, noise_top_k: int, rng: np.random.Generator,
               speed_tol_mps: float | tuple[float, float] | None = None) -> TokenizedScene:
        """Scene ``i`` re-matched by noised rolling matching from the logged poses (see
        :meth:`r1sim_sumo.tokens.batch.TokenizedDataset.noised`; ``speed_tol_mps``: noise that keeps the speed, see
        :func:`~r1sim_sumo.tokens.matching.match_agents`); the map crop is the exact scene's."""
        t, lo, hi = self._logged(i)
        # the exact scene's crop needs its matched poses only up to "now": replay the history tokens alone
        head = t.slice_steps(0, CURRENT_POSE + 1)
        exact = match_agents(head, self.vocab, given_tokens=self.a["token"][lo:hi, :CURRENT_POSE].astype(np.int64),
                             boundary_only=True)
        if not exact.pose_valid[:, CURRENT_POSE].any():  # crop_map then uses every valid pose: replay all
            exact = self[i].agents
        crop = self._scene(i, exact).map
        agents = mask_history_labels(match_agents(t, self.vocab, noise_top_k, rng, boundary_only=True,
                                                  noise_speed_tol_mps=speed_tol_mps), self.label_from(i))
        A = agents.num_agents
        return TokenizedScene(agents, crop, np.arange(A).astype(str), np.arange(A, dtype=np.int64),
                              f"{self.root.name}/{self.split}/{i}")


class JoinedTokenDatasets:
    """Several compact token datasets of one vocabulary read as one: scene ``i`` of the join is scene ``i`` of the
    first, then the second continues, and so on (a training run samples uniformly over all their scenes)."""

    def __init__(self, parts: list[CompactTokenDataset]):
        if not parts:
            raise ValueError("JoinedTokenDatasets: no datasets given")
        fp = parts[0].vocab.fingerprint()
        for p in parts[1:]:
            if p.vocab.fingerprint() != fp:
                raise CompactFormatError(f"{p.root}: built with another vocabulary than {parts[0].root}; rebuild it with "
                                         f"`r1sim tokens build ... --vocab {parts[0].root / VOCAB_FILE}`")
        self.parts, self.vocab = parts, parts[0].vocab
        self.offsets = np.concatenate([[0], np.cumsum([len(p) for p in parts])])

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def _locate(self, i: int) -> tuple[CompactTokenDataset, int]:
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(f"scene {i} out of range for {len(self)} joined scenes")
        k = int(np.searchsorted(self.offsets, i, side="right") - 1)
        return self.parts[k], i - int(self.offsets[k])

    def __getitem__(self, i: int) -> TokenizedScene:
        part, j = self._locate(i)
        return part[j]

    def noised(self, i: int, noise_top_k: int, rng: np.random.Generator,
               speed_tol_mps: float | tuple[float, float] | None = None) -> TokenizedScene:
        part, j = self._locate(i)
        return part.noised(j, noise_top_k, rng, speed_tol_mps)
