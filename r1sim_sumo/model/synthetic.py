"""Synthetic vocabularies and scene batches with the tokens <-> model interface's shapes, for tests and
benchmarks of the policy without data (see ``/work/notes/TOKENS_MODEL_SPEC.md``, "Scene batch").

The scene is a grid of straight two-way roads (lane centres + road edges cut into 5 m map tokens); agents
start on lane centres heading along them and move by sampled motion tokens, so poses and tokens agree.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from r1sim_sumo.tokens.constants import FRAMES_PER_TOKEN, N_MAP_PTS, N_POSE, N_TOK, TOKEN_DT_S
from r1sim_sumo.tokens.matching import hindsight_speed

SEGMENT_LEN_M = 5.0  # [m] map token length
BOX_SIZES_M = ((4.8, 2.0), (2.0, 1.0), (1.0, 1.0))  # (length, width) per type


class SyntheticSceneBatch(NamedTuple):
    """Same fields, shapes and dtypes as ``r1sim_sumo.tokens.SceneBatch``."""

    agent_token: Tensor  # [B, A, 18] int64, -1 pad
    agent_token_valid: Tensor  # [B, A, 18] bool
    pose_xy: Tensor  # [B, A, 19, 2] float32 [m]
    pose_yaw: Tensor  # [B, A, 19] float32 [rad]
    pose_valid: Tensor  # [B, A, 19] bool
    agent_type: Tensor  # [B, A] int64
    agent_size: Tensor  # [B, A, 2] float32 (length, width) [m]
    agent_mask: Tensor  # [B, A] bool
    agent_desired_speed: Tensor  # [B, A] float32 [m/s] (hindsight over the poses; NaN without two valid poses)
    map_pts: Tensor  # [B, M, 11, 2] float32, own frame [m]
    map_pos: Tensor  # [B, M, 2] float32, world [m]
    map_yaw: Tensor  # [B, M] float32 [rad]
    map_kind: Tensor  # [B, M] int64
    map_speed: Tensor  # [B, M] float32 [m/s]
    map_tl: Tensor  # [B, M, 19] int64
    map_mask: Tensor  # [B, M] bool


def synthetic_vocab(sizes: tuple[int, ...] = (2048, 512, 512), seed: int = 0) -> list[Tensor]:
    """Per-type token trajectories ``[V, 6, 3]`` (x, y, yaw in the start frame) of constant speed and yaw
    rate motions; token 0 = standing still. Max speeds 30 / 10 / 3 m/s."""
    g = torch.Generator().manual_seed(seed)
    out = []
    t = torch.arange(FRAMES_PER_TOKEN, dtype=torch.float64) * 0.1  # [6] s
    for v, vmax in zip(sizes, (30.0, 10.0, 3.0), strict=False):
        speed = torch.rand(v, generator=g, dtype=torch.float64) * vmax  # [V] m/s
        rate = torch.randn(v, generator=g, dtype=torch.float64) * 0.3  # [V] rad/s
        yaw = rate[:, None] * t  # [V, 6]
        # exact integration of a unicycle with constant speed and yaw rate
        safe = torch.where(rate.abs() < 1e-6, torch.ones_like(rate), rate)[:, None]
        x = torch.where(rate.abs()[:, None] < 1e-6, speed[:, None] * t, speed[:, None] * torch.sin(yaw) / safe)
        y = torch.where(rate.abs()[:, None] < 1e-6, torch.zeros_like(yaw), speed[:, None] * (1 - torch.cos(yaw)) / safe)
        traj = torch.stack([x, y, yaw], -1).float()
        traj[0] = 0.0
        out.append(traj)
    return out


def _road_map(num_tokens: int, extent_m: float, g: torch.Generator):
    """A grid of roads inside ``[0, extent]^2`` cut into 5 m segments; returns per-token tensors."""
    pos, yaw, kind = [], [], []
    n_roads = max(2, int(math.sqrt(num_tokens * SEGMENT_LEN_M / (6 * extent_m))) + 1)
    offsets = torch.linspace(0.1 * extent_m, 0.9 * extent_m, n_roads).tolist()
    n_seg = int(extent_m // SEGMENT_LEN_M)
    lanes = []
    for c in offsets:
        for lateral, direction, k in ((-1.75, 0.0, 0), (1.75, math.pi, 0), (-3.5, 0.0, 1), (3.5, math.pi, 1), (0.0, 0.0, 0), (0.0, math.pi, 0)):
            lanes.append((c + lateral, direction, k, "h"))
            lanes.append((c + lateral, direction + math.pi / 2, k, "v"))
    for c, d, k, axis in lanes:
        s = torch.arange(n_seg, dtype=torch.float32) * SEGMENT_LEN_M
        if math.cos(d) < -0.5 or math.sin(d) < -0.5:
            s = s + SEGMENT_LEN_M
        xy = torch.stack([s, torch.full_like(s, c)], -1) if axis == "h" else torch.stack([torch.full_like(s, c), s], -1)
        pos.append(xy)
        yaw.append(torch.full((n_seg,), d))
        kind.append(torch.full((n_seg,), k))
    pos, yaw, kind = torch.cat(pos), torch.cat(yaw), torch.cat(kind)
    sel = torch.randperm(pos.shape[0], generator=g)[:num_tokens]
    return pos[sel], yaw[sel], kind[sel].long()


def synthetic_batch(
    vocab_traj: list[Tensor],
    num_scenes: int = 2,
    num_agents: int = 16,
    num_map_tokens: int = 200,
    extent_m: float = 300.0,
    seed: int = 0,
    vehicle_fraction: float = 0.8,
) -> SyntheticSceneBatch:
    """A padded batch of random but self-consistent scenes (poses = integration of the tokens).

    The last scene has its last agent and last map token padded out, and ~10% of agents appear late
    (invalid for their first steps), to exercise the masks.
    """
    g = torch.Generator().manual_seed(seed)
    B, A, M = num_scenes, num_agents, num_map_tokens
    out = {k: [] for k in SyntheticSceneBatch._fields}
    for b in range(B):
        mpos, myaw, mkind = _road_map(M, extent_m, g)
        m = mpos.shape[0]
        pts = torch.zeros(M, N_MAP_PTS, 2)
        pts[:m, :, 0] = torch.linspace(0, SEGMENT_LEN_M, N_MAP_PTS)
        out["map_pts"].append(pts)
        out["map_pos"].append(torch.cat([mpos, torch.zeros(M - m, 2)]))
        out["map_yaw"].append(torch.cat([myaw, torch.zeros(M - m)]))
        out["map_kind"].append(torch.cat([mkind, torch.zeros(M - m, dtype=torch.long)]))
        out["map_speed"].append(torch.where(torch.arange(M) < m, 13.9, 0.0))
        out["map_tl"].append(torch.randint(0, 4, (M, 1), generator=g).expand(M, N_POSE).clone() * (torch.rand(M, 1, generator=g) < 0.2))
        mask = torch.arange(M) < m
        if b == B - 1 and B > 1:
            mask[m - 1] = False
        out["map_mask"].append(mask)
        # agents start on random lane-centre tokens
        lane = torch.nonzero(mkind == 0).squeeze(-1)
        start = lane[torch.randint(0, lane.numel(), (A,), generator=g)]
        ty = torch.where(torch.rand(A, generator=g) < vehicle_fraction, 0, torch.randint(1, 3, (A,), generator=g))
        xy0 = mpos[start] + torch.rand(A, 1, generator=g) * SEGMENT_LEN_M * torch.stack([myaw[start].cos(), myaw[start].sin()], -1)
        tok = torch.stack([torch.randint(0, vocab_traj[int(t)].shape[0], (N_TOK,), generator=g) for t in ty])  # [A, 18]
        xy, yaw = torch.zeros(A, N_POSE, 2), torch.zeros(A, N_POSE)
        xy[:, 0], yaw[:, 0] = xy0, myaw[start]
        for k in range(N_TOK):
            end = torch.stack([vocab_traj[int(t)][int(i), -1] for t, i in zip(ty, tok[:, k], strict=True)])  # [A, 3]
            c, s = yaw[:, k].cos(), yaw[:, k].sin()
            xy[:, k + 1] = xy[:, k] + torch.stack([c * end[:, 0] - s * end[:, 1], s * end[:, 0] + c * end[:, 1]], -1)
            yaw[:, k + 1] = yaw[:, k] + end[:, 2]
        first = torch.where(torch.rand(A, generator=g) < 0.1, torch.randint(1, 6, (A,), generator=g), 0)  # late starts
        pv = torch.arange(N_POSE)[None] >= first[:, None]
        tv = pv[:, :-1] & pv[:, 1:]
        amask = torch.ones(A, dtype=torch.bool)
        if b == B - 1 and B > 1:
            amask[-1] = False
        out["agent_token"].append(torch.where(tv, tok, -1))
        out["agent_token_valid"].append(tv)
        out["pose_xy"].append(xy * pv[..., None])
        out["pose_yaw"].append(yaw * pv)
        out["pose_valid"].append(pv)
        out["agent_type"].append(ty.long())
        out["agent_size"].append(torch.tensor(BOX_SIZES_M)[ty])
        out["agent_mask"].append(amask)
        pos = xy.numpy()
        out["agent_desired_speed"].append(torch.from_numpy(hindsight_speed(pos[..., 0], pos[..., 1], pv.numpy(), TOKEN_DT_S)))
    return SyntheticSceneBatch(**{k: torch.stack(v) for k, v in out.items()})
