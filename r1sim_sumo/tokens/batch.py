"""Tokenized scenes and padded batches for the policy model; an on-the-fly tokenizing Dataset with a cache.

``tokenize_scenario`` takes the 91-state window around ``scenario.current_index`` (11 history + 80 future
states; states outside the scenario, e.g. the future of a live simulator state, are invalid), matches the
agents to motion tokens, tokenizes the map and crops it to ``map_radius_m`` around the agents valid at the
current step. ``collate`` pads scenes into a :class:`SceneBatch` of torch tensors.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch.utils.data import Dataset

from r1sim_sumo.scenario import N_HISTORY_10HZ, AgentTracks, Scenario, ScenarioDataset
from r1sim_sumo.tokens.constants import CURRENT_POSE, N_POSE, N_WINDOW, STEPS_PER_TOKEN
from r1sim_sumo.tokens.map_tokens import MapTokens, tokenize_map
from r1sim_sumo.tokens.matching import TokenizedAgents, match_agents
from r1sim_sumo.tokens.motion_vocab import MotionVocab

DEFAULT_MAP_RADIUS_M = 150.0
CACHE_FORMAT_VERSION = 2  # 2: agents' desired speeds


@dataclass
class TokenizedScene:
    """One tokenized scene (numpy): agents (``A``), map tokens (``M``), agent ids and the scenario id.

    ``agent_index`` ``[A]`` maps each kept agent back to its row in ``scenario.agents`` (agents with no
    valid boundary pose in the window are dropped).
    """

    agents: TokenizedAgents
    map: MapTokens
    agent_ids: np.ndarray
    agent_index: np.ndarray
    scenario_id: str = ""

    def to_arrays(self) -> dict[str, np.ndarray]:
        out = {f"agents/{f}": getattr(self.agents, f) for f in TokenizedAgents.FIELDS}
        out["agents/desired_speed_mps"] = self.agents.desired_speed()
        if self.agents.target is not None:  # separate labels (masked policy-driven history)
            out["agents/target"] = self.agents.target
        out.update({f"map/{f}": getattr(self.map, f) for f in MapTokens.FIELDS})
        out["agent_ids"] = np.asarray(self.agent_ids).astype(str)
        out["agent_index"] = np.asarray(self.agent_index, np.int64)
        out["scenario_id"] = np.array(self.scenario_id)
        return out

    @classmethod
    def from_arrays(cls, z, source: str = "") -> TokenizedScene:
        try:
            return cls(
                agents=TokenizedAgents(**{f: z[f"agents/{f}"] for f in TokenizedAgents.FIELDS},
                                       desired_speed_mps=z["agents/desired_speed_mps"],
                                       target=z["agents/target"] if "agents/target" in z else None),
                map=MapTokens(**{f: z[f"map/{f}"] for f in MapTokens.FIELDS}),
                agent_ids=z["agent_ids"], agent_index=z["agent_index"], scenario_id=str(z["scenario_id"]),
            )
        except KeyError as exc:
            raise ValueError(f"{source}: tokenized scene misses field {exc}; delete the cache and rebuild it") from exc


class SceneBatch(NamedTuple):
    """``B`` scenes padded to ``A`` agents and ``M`` map tokens (torch). World frame, metres, radians."""

    agent_token: torch.Tensor  # [B, A, 18] int64, -1 pad / invalid
    agent_token_valid: torch.Tensor  # [B, A, 18] bool
    pose_xy: torch.Tensor  # [B, A, 19, 2] float32 matched boundary positions [m]
    pose_yaw: torch.Tensor  # [B, A, 19] float32 [rad]
    pose_valid: torch.Tensor  # [B, A, 19] bool
    agent_type: torch.Tensor  # [B, A] int64 0 vehicle / 1 cyclist / 2 pedestrian (0 in padding)
    agent_size: torch.Tensor  # [B, A, 2] float32 (length, width) [m]
    agent_mask: torch.Tensor  # [B, A] bool, a real agent
    agent_desired_speed: torch.Tensor  # [B, A] float32 desired (free-road) speed [m/s], NaN unknown / padding
    map_pts: torch.Tensor  # [B, M, 11, 2] float32, token frame [m]
    map_pos: torch.Tensor  # [B, M, 2] float32 world start [m]
    map_yaw: torch.Tensor  # [B, M] float32 [rad]
    map_kind: torch.Tensor  # [B, M] int64 0 lane centre / 1 road edge
    map_speed: torch.Tensor  # [B, M] float32 speed limit [m/s]
    map_tl: torch.Tensor  # [B, M, 19] int64 traffic-light state per boundary
    map_mask: torch.Tensor  # [B, M] bool, a real map token

    def to(self, device) -> SceneBatch:
        return SceneBatch(*(t.to(device) for t in self))


def _window(tracks: AgentTracks, start: int) -> AgentTracks:
    """States ``start .. start+90`` of the tracks; steps outside the tracks are invalid zeros."""
    T = tracks.num_steps
    if start >= 0 and start + N_WINDOW <= T:
        return tracks.slice_steps(start, start + N_WINDOW)
    out = AgentTracks.empty(tracks.num_agents, N_WINDOW)
    for f in ("ids", "agent_type", "length_m", "width_m", "desired_speed_mps"):
        setattr(out, f, getattr(tracks, f))
    lo, hi = max(start, 0), min(start + N_WINDOW, T)
    for f in (*AgentTracks.PER_STEP, "valid"):
        if hi > lo:
            getattr(out, f)[:, lo - start:hi - start] = getattr(tracks, f)[:, lo:hi]
    return out


def crop_map(scene: TokenizedScene, radius_m: float = DEFAULT_MAP_RADIUS_M) -> TokenizedScene:
    """Keep the map tokens within ``radius_m`` of any agent valid at the current pose (or, if none is,
    of any valid boundary pose)."""
    a = scene.agents
    cur = a.pose_valid[:, CURRENT_POSE] if a.pose_valid.shape[1] > CURRENT_POSE else np.zeros(a.num_agents, bool)
    centres = a.pose_xy[cur, CURRENT_POSE] if cur.any() else a.pose_xy[a.pose_valid]
    keep = scene.map.within(centres, radius_m)
    return TokenizedScene(a, scene.map.select(keep), scene.agent_ids, scene.agent_index, scene.scenario_id)


def crop_map_to_reach(scene: TokenizedScene, reach_m: float) -> TokenizedScene:
    """Keep only the map tokens whose middle point lies within ``reach_m`` [m] of a valid boundary pose of the
    token steps (the agent nodes a training forward runs on). With ``reach_m`` >=
    :func:`r1sim_sumo.model.packed.reach_radius_m` (map-to-agent radius + one map radius per map layer) no
    logit of the model changes: the dropped tokens are outside every node's receptive field. Training batches
    shrink accordingly (the rollout path keeps the whole crop)."""
    a, m = scene.agents, scene.map
    n_tok = a.token.shape[1]
    pv = a.pose_valid[:, :n_tok]
    if not m.num_tokens or not pv.any():
        return scene
    mid = m.world_points()[:, m.pts.shape[1] // 2].astype(np.float64)  # [M, 2] the point the model's neighbour search uses
    dist, _ = cKDTree(a.pose_xy[:, :n_tok][pv].astype(np.float64)).query(mid, distance_upper_bound=float(reach_m))
    keep = np.isfinite(dist)
    return TokenizedScene(a, m.select(keep), scene.agent_ids, scene.agent_index, scene.scenario_id)


def mask_history_labels(agents: TokenizedAgents, label_from: int) -> TokenizedAgents:
    """Set the labels (``target``; the tokens themselves when there is none) of tokens ``< label_from`` to -1, ignored by
    the losses: a window whose history another driver made (:mod:`r1sim_sumo.data.policy_history`, metadata
    ``label_from_token``) trains only on its future. ``label_from`` 0 changes nothing. In place; returns ``agents``."""
    if label_from > 0:
        agents.target = np.array(agents.token if agents.target is None else agents.target, np.int64, copy=True)
        agents.target[:, :label_from] = -1
    return agents


def tokenize_scenario(scenario: Scenario, vocab: MotionVocab, map_radius_m: float | None = DEFAULT_MAP_RADIUS_M) -> TokenizedScene:
    """Tokenize the 91-state window (11 history + 80 future) around ``scenario.current_index``.

    :param map_radius_m: crop map tokens to this distance [m] from the agents at the current step;
        ``None`` keeps the whole map.
    """
    start = int(scenario.current_index) - (N_HISTORY_10HZ - 1)
    tracks = _window(scenario.agents, start)
    keep = np.flatnonzero(tracks.valid[:, ::STEPS_PER_TOKEN].any(1))
    agents = mask_history_labels(match_agents(tracks.select(keep), vocab), int(scenario.metadata.get("label_from_token", 0)))
    mp = tokenize_map(scenario.map, n_pose=N_POSE, first_step=start)
    sid = str(scenario.metadata.get("scenario_id", scenario.metadata.get("_path", "")))
    scene = TokenizedScene(agents, mp, np.asarray(scenario.agents.ids)[keep].astype(str), keep.astype(np.int64), sid)
    return crop_map(scene, map_radius_m) if map_radius_m is not None else scene


def collate(scenes: list[TokenizedScene]) -> SceneBatch:
    """Pad scenes into a :class:`SceneBatch` (agents to the largest ``A``, map tokens to the largest ``M``)."""
    if not scenes:
        raise ValueError("collate: empty list of scenes")
    B = len(scenes)
    A = max(max(s.agents.num_agents for s in scenes), 1)
    M = max(max(s.map.num_tokens for s in scenes), 1)
    n_tok = scenes[0].agents.token.shape[1]
    n_pose = scenes[0].agents.pose_valid.shape[1]
    n_pts = scenes[0].map.pts.shape[1] if scenes[0].map.num_tokens else 11
    out = {
        "agent_token": np.full((B, A, n_tok), -1, np.int64), "agent_token_valid": np.zeros((B, A, n_tok), bool),
        "pose_xy": np.zeros((B, A, n_pose, 2), np.float32), "pose_yaw": np.zeros((B, A, n_pose), np.float32),
        "pose_valid": np.zeros((B, A, n_pose), bool), "agent_type": np.zeros((B, A), np.int64),
        "agent_size": np.zeros((B, A, 2), np.float32), "agent_mask": np.zeros((B, A), bool),
        "agent_desired_speed": np.full((B, A), np.nan, np.float32),
        "map_pts": np.zeros((B, M, n_pts, 2), np.float32), "map_pos": np.zeros((B, M, 2), np.float32),
        "map_yaw": np.zeros((B, M), np.float32), "map_kind": np.zeros((B, M), np.int64),
        "map_speed": np.zeros((B, M), np.float32), "map_tl": np.zeros((B, M, n_pose), np.int64),
        "map_mask": np.zeros((B, M), bool),
    }
    for b, s in enumerate(scenes):
        a, m = s.agents, s.map
        if a.token.shape[1] != n_tok:
            raise ValueError(f"collate: scene {b} has {a.token.shape[1]} tokens per agent, scene 0 has {n_tok}")
        n, k = a.num_agents, m.num_tokens
        out["agent_token"][b, :n] = a.token
        out["agent_token_valid"][b, :n] = a.token_valid
        out["pose_xy"][b, :n] = a.pose_xy
        out["pose_yaw"][b, :n] = a.pose_yaw
        out["pose_valid"][b, :n] = a.pose_valid
        out["agent_type"][b, :n] = a.agent_type
        out["agent_size"][b, :n] = np.stack([a.length_m, a.width_m], -1)
        out["agent_mask"][b, :n] = True
        out["agent_desired_speed"][b, :n] = a.desired_speed()
        out["map_pts"][b, :k] = m.pts
        out["map_pos"][b, :k] = m.pos
        out["map_yaw"][b, :k] = m.yaw
        out["map_kind"][b, :k] = m.kind
        out["map_speed"][b, :k] = m.speed_limit_mps
        out["map_tl"][b, :k] = m.tl
        out["map_mask"][b, :k] = True
    return SceneBatch(**{k: torch.from_numpy(v) for k, v in out.items()})


class TokenizedDataset(Dataset):
    """``torch.utils.data.Dataset`` of :class:`TokenizedScene` over a ScenarioDataset folder, tokenized on the fly.

    :param data: a dataset folder (``manifest.json`` + shards) or a :class:`ScenarioDataset`.
    :param vocab: the motion vocabulary.
    :param map_radius_m: map crop radius [m] (``None``: whole map).
    :param cache_dir: optional folder of precomputed scenes (``scene-XXXXXXXX.npz``, no pickle) with a
        ``cache.json`` recording the vocabulary fingerprint and the crop radius; missing scenes are written
        on first access (atomically). A cache built with another vocabulary or radius is refused.

    Use ``DataLoader(ds, batch_size=..., collate_fn=collate)``.
    """

    def __init__(self, data, vocab: MotionVocab, map_radius_m: float | None = DEFAULT_MAP_RADIUS_M,
                 cache_dir: str | os.PathLike | None = None):
        self.data = data if isinstance(data, ScenarioDataset) else ScenarioDataset(data)
        self.vocab = vocab
        self.map_radius_m = map_radius_m
        self.cache_dir = Path(cache_dir) if cache_dir is not None else None
        if self.cache_dir is not None:
            self._check_cache()

    def __len__(self) -> int:
        return len(self.data)

    def _cache_info(self) -> dict:
        return {"format_version": CACHE_FORMAT_VERSION, "vocab_fingerprint": self.vocab.fingerprint(),
                "map_radius_m": self.map_radius_m, "num_scenarios": len(self.data), "data": str(self.data.root)}

    def _check_cache(self) -> None:
        info_path = self.cache_dir / "cache.json"
        info = self._cache_info()
        if info_path.exists():
            old = json.loads(info_path.read_text())
            for k in ("format_version", "vocab_fingerprint", "map_radius_m", "num_scenarios"):
                if old.get(k) != info[k]:
                    raise ValueError(f"{info_path}: field '{k}' is {old.get(k)!r} but this dataset needs {info[k]!r}; "
                                     f"use another cache_dir or delete this one")
        else:
            self.cache_dir.mkdir(parents=True, exist_ok=True)
            info_path.write_text(json.dumps(info, indent=2))

    def _path(self, i: int) -> Path:
        return self.cache_dir / f"scene-{i:08d}.npz"

    def __getitem__(self, i: int) -> TokenizedScene:
        if i < 0:
            i += len(self)
        if self.cache_dir is not None and self._path(i).exists():
            with np.load(self._path(i), allow_pickle=False) as z:
                return TokenizedScene.from_arrays(z, source=str(self._path(i)))
        scene = tokenize_scenario(self.data[i], self.vocab, self.map_radius_m)
        if not scene.scenario_id:
            scene.scenario_id = f"{self.data.root.name}/{i}"
        if self.cache_dir is not None:
            self._write(i, scene)
        return scene

    def noised(self, i: int, noise_top_k: int, rng: np.random.Generator,
               speed_tol_mps: float | tuple[float, float] | None = None) -> TokenizedScene:
        """Scene ``i`` with its agents re-matched by noised rolling matching (:func:`match_agents` with
        ``noise_top_k`` and ``noise_speed_tol_mps=speed_tol_mps``; same agents, map tokens as cached): ``agents.token``
        holds the drawn (input) tokens and ``agents.target`` the recovering labels. Validation stays exact."""
        scene = self[i]
        sc = self.data[i]
        tracks = _window(sc.agents, int(sc.current_index) - (N_HISTORY_10HZ - 1)).select(np.asarray(scene.agent_index))
        scene.agents = mask_history_labels(match_agents(tracks, self.vocab, noise_top_k, rng,
                                                        noise_speed_tol_mps=speed_tol_mps),
                                           int(sc.metadata.get("label_from_token", 0)))
        return scene

    def _write(self, i: int, scene: TokenizedScene) -> None:
        fd, tmp = tempfile.mkstemp(prefix=f"scene-{i:08d}.", suffix=".tmp.npz", dir=self.cache_dir)
        os.close(fd)
        try:
            np.savez(tmp, **scene.to_arrays())
            os.replace(tmp, self._path(i))
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    def precompute(self, progress: bool = True) -> int:
        """Tokenize every missing scene into the cache; returns the number written."""
        if self.cache_dir is None:
            raise ValueError("TokenizedDataset.precompute: no cache_dir given")
        todo = [i for i in range(len(self)) if not self._path(i).exists()]
        it = todo
        if progress:
            from tqdm import tqdm

            it = tqdm(todo, desc="tokenize", unit="scn")
        for i in it:
            self[i]
        return len(todo)
