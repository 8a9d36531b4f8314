"""Rolling matching of agent tracks to motion tokens, and 10 Hz state reconstruction from tokens.

Rolling matching (SMART): token ``k`` is placed at the previously MATCHED boundary pose ``k`` (not the
ground truth); the chosen token minimises the mean distance between its end-frame box corners placed
there and the ground-truth box corners at boundary ``k+1`` (both with the type's fixed box size,
:data:`~r1sim_sumo.tokens.motion_vocab.BOX_SIZE_M`); the matched pose ``k+1`` is the token's end pose
placed at matched pose ``k``. Matching errors therefore do not accumulate: each step corrects the drift
of the previous ones. Where an agent (re)appears, i.e. it is valid at boundary ``k`` but not at ``k-1``,
its matched pose is the ground-truth pose.

Boundaries are the states ``0, 5, 10, ...`` of the tracks (``N_POSE = 19`` for a 91-state window).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from r1sim_sumo.geometry import box_corners, wrap_angle
from r1sim_sumo.scenario import DT_S, AgentTracks
from r1sim_sumo.tokens.motion_vocab import BOX_SIZE_M, STEPS, TYPES, MotionVocab


@dataclass
class TokenizedAgents:
    """Matched tokens and boundary poses of ``A`` agents (numpy); world frame, box centres.

    :param token: int64 ``[A, n_tok]`` token ids into the agent's type vocabulary; -1 where invalid.
    :param token_valid: bool ``[A, n_tok]``, both boundary poses of the token valid.
    :param pose_xy: float32 ``[A, n_pose, 2]`` matched boundary positions [m] (0 where invalid).
    :param pose_yaw: float32 ``[A, n_pose]`` matched boundary headings [rad].
    :param pose_valid: bool ``[A, n_pose]``, the state at boundary index ``5k`` is valid.
    :param agent_type: int64 ``[A]``; ``length_m``, ``width_m``: float32 ``[A]`` true box size [m].
    :param target: only from noised matching (``noise_top_k > 1``): int64 ``[A, n_tok]``, the *nearest* token
        from each (noised) start pose, i.e. the token that best recovers towards the log; the training target
        while ``token`` (the drawn one) is the input. Not saved in caches.
    :param desired_speed_mps: float32 ``[A]``, each driver's desired (free-road) speed [m/s], NaN = unknown: what
        the simulator reports (:attr:`AgentTracks.desired_speed_mps`) or else :func:`hindsight_speed` of the window.
    """

    token: np.ndarray
    token_valid: np.ndarray
    pose_xy: np.ndarray
    pose_yaw: np.ndarray
    pose_valid: np.ndarray
    agent_type: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray
    target: np.ndarray | None = None
    desired_speed_mps: np.ndarray | None = None

    FIELDS = ("token", "token_valid", "pose_xy", "pose_yaw", "pose_valid", "agent_type", "length_m", "width_m")

    def desired_speed(self) -> np.ndarray:
        """``[A]`` float32 desired speeds [m/s], NaN where unknown (also when none were given)."""
        if self.desired_speed_mps is None:
            return np.full(self.num_agents, np.nan, np.float32)
        return np.asarray(self.desired_speed_mps, np.float32)

    @property
    def num_agents(self) -> int:
        return int(len(self.agent_type))

    def select(self, idx) -> TokenizedAgents:
        """Subset of agents by index array or boolean mask."""
        return TokenizedAgents(**{f: getattr(self, f)[idx] for f in self.FIELDS},
                               target=None if self.target is None else self.target[idx],
                               desired_speed_mps=None if self.desired_speed_mps is None else self.desired_speed_mps[idx])

    def padded_to(self, n_pose: int) -> TokenizedAgents:
        """The same agents with ``n_pose`` boundary poses (``n_pose - 1`` tokens): the later ones invalid (token -1,
        pose 0), exactly what matching a longer window whose extra states are invalid gives."""
        have = self.pose_valid.shape[1]
        if n_pose < have:
            raise ValueError(f"TokenizedAgents.padded_to: {n_pose} poses is fewer than the {have} it holds")
        A, extra = self.num_agents, n_pose - have

        def pad(a: np.ndarray, fill) -> np.ndarray:
            return np.concatenate([a, np.full((A, extra, *a.shape[2:]), fill, a.dtype)], 1)

        return TokenizedAgents(pad(self.token, -1), pad(self.token_valid, False), pad(self.pose_xy, 0.0),
                               pad(self.pose_yaw, 0.0), pad(self.pose_valid, False), self.agent_type, self.length_m,
                               self.width_m, None if self.target is None else pad(self.target, -1), self.desired_speed_mps)


def hindsight_speed(x_m: np.ndarray, y_m: np.ndarray, valid: np.ndarray, dt_s: float = 0.5) -> np.ndarray:
    """Each agent's highest speed [m/s] over its track: the largest displacement between consecutive valid states
    ``dt_s`` apart (token boundaries: 0.5 s), divided by ``dt_s``. ``x_m, y_m, valid``: ``[A, P]``. NaN for an
    agent with no two consecutive valid states.

    The training estimate of a driver's desired speed when the data does not record it: over a 9 s window a
    driver on a free road reaches its desired speed; one in a queue reaches less (and the policy learns that).
    """
    v = np.hypot(np.diff(x_m, axis=1), np.diff(y_m, axis=1)) / dt_s  # [A, P-1]
    ok = valid[:, 1:] & valid[:, :-1]
    out = np.where(ok, v, -np.inf).max(1, initial=-np.inf)
    return np.where(np.isfinite(out), out, np.nan).astype(np.float32)


def desired_speeds(tracks: AgentTracks, gx: np.ndarray, gy: np.ndarray, gv: np.ndarray, dt_s: float) -> np.ndarray:
    """``[A]`` desired speeds [m/s]: the simulator's (``tracks.desired_speed_mps``) where known, else the
    :func:`hindsight_speed` of the boundary poses ``gx, gy, gv [A, P]``."""
    est = hindsight_speed(gx, gy, gv, dt_s)
    if tracks.desired_speed_mps is None:
        return est
    given = np.asarray(tracks.desired_speed_mps, np.float32)
    return np.where(np.isfinite(given), given, est).astype(np.float32)


PREFILTER_K = 16  # candidates kept by the squared-distance prefilter before the exact mean-corner distance


TREE_MIN_ROWS = 64  # agents per token step from which the prefilter queries a k-d tree instead of one matmul + top-k


def _corner_tree(end_corners: torch.Tensor):
    """``scipy.spatial.cKDTree`` over the tokens' end corners flattened to 8-d vectors [m], built once per table
    (kept on the tensor): its Euclidean order is the order of the summed squared corner distances the matmul ranks by.
    About 1.5-4x faster than the matmul + top-k from 64 agents over 3,720 tokens (drop-in decisions), equal below."""
    tree = getattr(end_corners, "_r1sim_kdtree", None)
    if tree is None:
        from scipy.spatial import cKDTree

        tree = cKDTree(end_corners.flatten(1).double().numpy())
        end_corners._r1sim_kdtree = tree
    return tree


def speed_band(speed_tol_mps: float | tuple[float, float] | list[float]) -> tuple[float, float]:
    """``(below, above)`` [m/s] from a noise speed tolerance: a number ``t`` is the symmetric band ``(t, t)``; a
    pair is ``(below, above)``: a drawn token may be up to ``below`` slower and ``above`` faster than the nearest
    (e.g. ``(1.0, 0.0)``: slower-only noise, whose recovering labels speed the chain back up). Both >= 0."""
    if isinstance(speed_tol_mps, (tuple, list)):
        if len(speed_tol_mps) != 2:
            raise ValueError(f"noise speed band {speed_tol_mps!r}: give one number or a pair [below, above] in m/s")
        below, above = float(speed_tol_mps[0]), float(speed_tol_mps[1])
    else:
        below = above = float(speed_tol_mps)
    if not (below >= 0.0 and above >= 0.0):
        raise ValueError(f"noise speed band {speed_tol_mps!r}: both bounds must be >= 0 [m/s]")
    return below, above


def _nearest_token(gt_c, end_corners, end_sq, noise_top_k: int = 1, rng: np.random.Generator | None = None,
                   end_speed: torch.Tensor | None = None,
                   speed_tol_mps: float | tuple[float, float] | None = None):
    """argmin over the vocabulary of the mean corner distance ``[a]`` between ``gt_c [a, 4, 2]`` and
    ``end_corners [V, 4, 2]``. One matmul (``addmm``; a k-d tree from ``TREE_MIN_ROWS`` agents on) ranks all tokens
    by *squared* corner distance; the exact mean Euclidean corner distance is then evaluated on the ``PREFILTER_K``
    best (the two orders agree on the
    nearest token except for near-ties far below the vocabulary tolerance). Returns ``(chosen, nearest)``: with
    ``noise_top_k > 1`` ``chosen`` is drawn uniformly (``rng``) from the ``noise_top_k`` nearest (noised matching,
    see :func:`match_agents`), else it is the nearest. With ``speed_tol_mps`` (and ``end_speed [V]``, each token's
    mean speed [m/s]) the draw is only among those of the ``noise_top_k`` nearest whose mean speed is within
    ``speed_tol_mps`` of the nearest token's (the nearest itself always is); a pair ``(below, above)`` [m/s] allows
    ``below`` slower and ``above`` faster (see :func:`speed_band`)."""

    g = gt_c.flatten(1)  # [a, 8]
    k = min(PREFILTER_K, end_corners.shape[0])
    if len(g) >= TREE_MIN_ROWS:  # a k-d tree over the 8-d end-corner vectors: the same ranking, O(a log V)
        _, cand = _corner_tree(end_corners).query(g.double().numpy(), k=k)
        cand = torch.from_numpy(np.asarray(cand, np.int64).reshape(len(g), k))
    else:
        # squared corner distance less |g|^2, a per-row constant that does not change the ranking: one fused pass
        sq = torch.addmm(end_sq[None], g, end_corners.flatten(1).T, alpha=-2.0)  # [a, V]
        cand = sq.topk(k, dim=1, largest=False).indices  # [a, k]
    d = (end_corners[cand] - gt_c[:, None]).square().sum(-1).sqrt().mean(-1)  # [a, k]
    nearest = cand.gather(1, d.argmin(1, keepdim=True)).squeeze(1).numpy()
    if noise_top_k > 1:
        n = min(int(noise_top_k), k)
        if speed_tol_mps is None:
            order = d.argsort(1)[:, :n]  # [a, n] nearest first
            pick = torch.from_numpy(rng.integers(0, n, size=len(order)))[:, None]
            return cand.gather(1, order.gather(1, pick)).squeeze(1).numpy(), nearest
        below, above = speed_band(speed_tol_mps)
        dv = end_speed[cand] - end_speed[torch.from_numpy(nearest)][:, None]  # [a, k] candidate minus nearest [m/s]
        far = (dv < -below) | (dv > above)
        dd = d.masked_fill(far, float("inf"))
        order = dd.argsort(1)[:, :n]  # [a, n] nearest eligible first (the nearest token is eligible)
        m = torch.isfinite(dd.gather(1, order)).sum(1)  # [a] eligible among them, >= 1
        pick = (torch.from_numpy(rng.random(len(order))) * m).long().clamp_max(m - 1)[:, None]
        return cand.gather(1, order.gather(1, pick)).squeeze(1).numpy(), nearest
    return nearest, nearest


def _end_tables(vocab: MotionVocab) -> tuple[dict, dict, dict]:
    """Per agent type: the tokens' end corners ``[V, 4, 2]`` (float32 tensor), end poses ``[V, 3]`` (x, y [m], yaw
    [rad], float64) and squared corner norms ``[V]``; computed once per vocabulary object (every decision of a
    drop-in run and every training scene match against the same vocabulary)."""
    cached = getattr(vocab, "_match_end_tables", None)
    if cached is None:
        end_corners = {t: torch.from_numpy(vocab.corners[t][:, -1]) for t in TYPES}
        end_pose = {t: vocab.traj[t][:, -1].astype(np.float64) for t in TYPES}
        end_sq = {t: end_corners[t].flatten(1).square().sum(-1) for t in TYPES}
        cached = (end_corners, end_pose, end_sq)
        object.__setattr__(vocab, "_match_end_tables", cached)
    return cached


def match_agents(tracks: AgentTracks, vocab: MotionVocab, noise_top_k: int = 1,
                 rng: np.random.Generator | None = None, given_tokens: np.ndarray | None = None,
                 boundary_only: bool = False,
                 noise_speed_tol_mps: float | tuple[float, float] | None = None) -> TokenizedAgents:
    """Rolling-match all agents (vectorised over agents, a loop over the token steps only).

    :param tracks: ``[A, T]`` tracks at 10 Hz; boundaries at states ``0, 5, ...``: ``n_pose = (T-1)//5 + 1``
        (19 for the standard 91-state window), ``n_tok = n_pose - 1``.
    :param noise_top_k: 1 = exact matching (argmin). ``> 1``: noised matching for training (SMART's remedy for
        exposure bias): each token is drawn uniformly from the ``noise_top_k`` nearest, and because matching rolls
        from the previously *matched* pose, the chain wanders slightly off the logged track and is steered back;
        ``target`` holds the nearest (recovering) token from each noised start pose. Trained with the drawn tokens
        as inputs and ``target`` as labels, the model sees slightly-off states and the tokens that recover from
        them, as in its own rollouts, while its labels stay exact.
    :param rng: numpy generator for the noise (required when ``noise_top_k > 1``).
    :param noise_speed_tol_mps: noised matching that keeps the speed: each token is drawn only among those of the
        ``noise_top_k`` nearest whose mean speed is within this many m/s of the nearest one's, so the noise moves
        the chain sideways and turns it but does not make it speed up and then recover (with free speed noise a
        speed-up between two input tokens is mostly noise that the next label takes back: the inputs' speed trend
        and the labels' are anti-correlated, -0.22 on data/tokens/ext: scripts/noise_speed_trend.py, session 28). ``None``: free noise.
        A pair ``(below, above)`` [m/s] makes the band asymmetric (:func:`speed_band`).
    :param given_tokens: int ``[A, n_tok]``: replay these tokens instead of choosing them (the matched poses of a
        stored tokenization, :mod:`r1sim_sumo.tokens.compact`); the same arithmetic, so the same poses.
    :param boundary_only: ``tracks`` hold only the boundary states (one step per token) instead of 10 Hz.
    :return: :class:`TokenizedAgents`.
    """
    A, T = tracks.num_agents, tracks.num_steps
    if noise_top_k > 1 and rng is None:
        raise ValueError("match_agents: noise_top_k > 1 needs rng (a numpy Generator)")
    if noise_top_k > PREFILTER_K:
        raise ValueError(f"match_agents: noise_top_k {noise_top_k} is above the {PREFILTER_K} prefiltered candidates")
    if T < 1:
        raise ValueError(f"match_agents: tracks have no steps (shape {tracks.valid.shape})")
    stride = 1 if boundary_only else STEPS
    n_pose = (T - 1) // stride + 1
    n_tok = n_pose - 1
    b = np.arange(n_pose) * stride
    gx = np.asarray(tracks.x_m, np.float64)[:, b]  # [A, P]
    gy = np.asarray(tracks.y_m, np.float64)[:, b]
    gyaw = np.asarray(tracks.yaw_rad, np.float64)[:, b]
    gv = np.asarray(tracks.valid, bool)[:, b]
    atype = np.asarray(tracks.agent_type, np.int64)
    if A and not np.isin(atype, TYPES).all():
        raise ValueError("match_agents: agent_type values must be 0/1/2 (vehicle/cyclist/pedestrian)")

    px, py, pyaw = np.zeros((A, n_pose)), np.zeros((A, n_pose)), np.zeros((A, n_pose))
    px[:, 0], py[:, 0], pyaw[:, 0] = gx[:, 0], gy[:, 0], gyaw[:, 0]
    token = np.full((A, n_tok), -1, np.int64)
    target = np.full((A, n_tok), -1, np.int64)
    token_valid = gv[:, :-1] & gv[:, 1:]  # [A, n_tok]
    end_corners, end_pose, end_sq = _end_tables(vocab)
    end_speed = {t: torch.from_numpy(np.hypot(end_pose[t][:, 0], end_pose[t][:, 1]) / (STEPS * DT_S))  # [V] [m/s]
                 if noise_speed_tol_mps is not None else None for t in TYPES}

    for k in range(n_tok):
        new = gv[:, k + 1] & ~gv[:, k]  # (re)appearing agents start from the ground truth
        px[new, k + 1], py[new, k + 1], pyaw[new, k + 1] = gx[new, k + 1], gy[new, k + 1], gyaw[new, k + 1]
        for t in TYPES:
            sel = np.flatnonzero(token_valid[:, k] & (atype == t))
            if not len(sel):
                continue
            c, s = np.cos(pyaw[sel, k]), np.sin(pyaw[sel, k])  # [a]
            if given_tokens is None:
                dx, dy = gx[sel, k + 1] - px[sel, k], gy[sel, k + 1] - py[sel, k]
                lx, ly = c * dx + s * dy, -s * dx + c * dy  # GT end pose in the matched start frame
                lyaw = wrap_angle(gyaw[sel, k + 1] - pyaw[sel, k])
                gt_c = torch.from_numpy(box_corners(lx, ly, lyaw, *BOX_SIZE_M[t]).astype(np.float32))  # [a, 4, 2]
                tok, best = _nearest_token(gt_c, end_corners[t], end_sq[t], noise_top_k, rng, end_speed[t],
                                           noise_speed_tol_mps)
            else:
                tok = best = np.asarray(given_tokens[sel, k], np.int64)
            ex, ey, eyaw = end_pose[t][tok].T  # [a]
            px[sel, k + 1] = px[sel, k] + c * ex - s * ey
            py[sel, k + 1] = py[sel, k] + s * ex + c * ey
            pyaw[sel, k + 1] = wrap_angle(pyaw[sel, k] + eyaw)
            token[sel, k] = tok
            target[sel, k] = best

    pose_xy = np.stack([px, py], -1)
    pose_xy[~gv] = 0.0
    pyaw[~gv] = 0.0
    return TokenizedAgents(
        token=token, token_valid=token_valid, pose_xy=pose_xy.astype(np.float32), pose_yaw=pyaw.astype(np.float32),
        pose_valid=gv, agent_type=atype, length_m=np.asarray(tracks.length_m, np.float32),
        width_m=np.asarray(tracks.width_m, np.float32), target=target if noise_top_k > 1 else None,
        desired_speed_mps=desired_speeds(tracks, gx, gy, gv, STEPS * DT_S),  # boundary poses are 0.5 s apart
    )


def _token_traj(tokens, agent_type, vocab: MotionVocab, like):
    """Gather token trajectories ``[..., n, 6, 3]`` for tokens ``[..., n]`` of agents of type ``[...]``."""
    traj_tab = vocab.torch_tables(device=like.device, dtype=like.dtype)[0]  # [3, V_max, 6, 3]
    tok = tokens.long().clamp(0, traj_tab.shape[1] - 1)  # -1 (invalid) -> token 0 = standing still
    typ = torch.as_tensor(agent_type, device=tok.device).long()[..., None].expand_as(tok)
    return traj_tab[typ, tok]


def reconstruct_states(pose_xy0, yaw0, tokens, vocab: MotionVocab, agent_type):
    """10 Hz states from a start pose and a token sequence (torch, batched over leading dims ``[...]``).

    :param pose_xy0: ``[..., 2]`` start position [m] (world frame, box centre); its dtype/device are used.
    :param yaw0: ``[...]`` start heading [rad].
    :param tokens: int ``[..., n]`` token ids; negative ids (invalid) are treated as token 0 (standing still).
    :param agent_type: int ``[...]`` 0/1/2, selects the sub-vocabulary.
    :return: ``(xy [..., 5n+1, 2], yaw [..., 5n+1])``; index 0 is the start pose, ``5k`` the boundary poses.
    """
    xy0 = torch.as_tensor(pose_xy0)
    yaw0 = torch.as_tensor(yaw0, dtype=xy0.dtype, device=xy0.device)
    tokens = torch.as_tensor(tokens, device=xy0.device)
    tr = _token_traj(tokens, agent_type, vocab, xy0)  # [..., n, 6, 3]
    n = tokens.shape[-1]
    end_yaw = tr[..., -1, 2]  # [..., n]
    start_yaw = yaw0[..., None] + torch.cumsum(end_yaw, -1) - end_yaw  # [..., n] heading at each token start
    c, s = torch.cos(start_yaw)[..., None], torch.sin(start_yaw)[..., None]  # [..., n, 1]
    fx = c * tr[..., 1:, 0] - s * tr[..., 1:, 1]  # [..., n, 5] frames 1..5 rotated to the world heading
    fy = s * tr[..., 1:, 0] + c * tr[..., 1:, 1]
    sx = xy0[..., 0:1] + torch.cumsum(fx[..., -1], -1) - fx[..., -1]  # [..., n] token start positions
    sy = xy0[..., 1:2] + torch.cumsum(fy[..., -1], -1) - fy[..., -1]
    x = (sx[..., None] + fx).flatten(-2)  # [..., 5n]
    y = (sy[..., None] + fy).flatten(-2)
    yaw = (start_yaw[..., None] + tr[..., 1:, 2]).flatten(-2)
    x = torch.cat([xy0[..., 0:1], x], -1)
    y = torch.cat([xy0[..., 1:2], y], -1)
    yaw = wrap_angle(torch.cat([yaw0[..., None], yaw], -1))
    assert x.shape[-1] == STEPS * n + 1
    return torch.stack([x, y], -1), yaw


def advance_pose(pose_xy, yaw, token, vocab: MotionVocab, agent_type):
    """Boundary pose after one token (torch, batched): ``(xy [..., 2], yaw [...])``; token -1 = standing still."""
    xy = torch.as_tensor(pose_xy)
    yaw = torch.as_tensor(yaw, dtype=xy.dtype, device=xy.device)
    end = _token_traj(torch.as_tensor(token, device=xy.device)[..., None], agent_type, vocab, xy)[..., 0, -1, :]  # [..., 3]
    c, s = torch.cos(yaw), torch.sin(yaw)
    nx = xy[..., 0] + c * end[..., 0] - s * end[..., 1]
    ny = xy[..., 1] + s * end[..., 0] + c * end[..., 1]
    return torch.stack([nx, ny], -1), wrap_angle(yaw + end[..., 2])
