"""The one simulation kernel: a closed-loop token step, a token's 10 Hz plan, and following a plan under a speed cap.

Every host runs on these three pieces (issue 17):

* :func:`token_step` — one cached policy step for all agents -> sampled token, the sampler's and the full-softmax
  log-probability, entropy [nats], ``K_t``, and the next boundary pose and validity. Used by the in-model engine
  (:func:`r1sim_sumo.rollout.engine.rollout`) and the SUMO-in-the-loop source
  (:mod:`r1sim_sumo.train.sumo_inloop`), whose ``host`` callback moves SUMO's vehicles along the token and reports
  the agents that vanished; :class:`StepRecorder` stacks the steps into a rollout record.
* :func:`token_frames` — a token placed at a pose -> its 6 frames at 10 Hz (frame 0 = the pose). Used by the
  SUMO-in-the-loop host and by the online :class:`~r1sim_sumo.sim.policy_driver.PolicyDriver` for its plans.
* :class:`PlanFollower` — where a vehicle stands along its current 0.5 s plan. It advances by the plan's own clock
  while it can drive the plan's speed, and by distance at ``v = min(plan speed, allowed speed)`` once a host's
  safety layer allowed less (then it lags behind the plan's timing); every new plan resets it. Used by the SUMO
  controller (position drive) and the highway-env coordinator, so both follow a plan the same way.

Frames: internal (metres, x east, y north, yaw radians CCW from +x, box centres); 10 Hz states; one token = 0.5 s
= :data:`~r1sim_sumo.tokens.constants.STEPS_PER_TOKEN` states.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from r1sim_sumo.geometry import wrap_angle
from r1sim_sumo.scenario import DT_S
from r1sim_sumo.sim.safety_filter import path_arc_length, path_curvature, point_along
from r1sim_sumo.tokens.constants import STEPS_PER_TOKEN, TOKEN_DT_S
from r1sim_sumo.tokens.matching import advance_pose, reconstruct_states

N_PLAN_FRAMES = STEPS_PER_TOKEN + 1  # 6 frames of a 0.5 s plan, frame 0 = now
_ON_TIME_M = 1e-9  # [m] a follower this close to the plan's clock position is on time


# ---------------------------------------------------------------------------- tokens -> poses


def token_frames(xy: torch.Tensor, yaw: torch.Tensor, token: torch.Tensor, vocab, agent_type: torch.Tensor):
    """The 6 states at 10 Hz of ``token`` placed at pose ``xy [..., 2]`` [m], ``yaw [...]`` [rad].

    :param token: ``[...]`` int64 token ids (negative = standing still); ``agent_type`` ``[...]`` selects the
        sub-vocabulary.
    :return: ``(xy [..., 6, 2], yaw [..., 6])``; frame 0 is the given pose, frame 5 the next boundary pose.
    """
    return reconstruct_states(xy, yaw, token.unsqueeze(-1), vocab, agent_type)


def retime_plan(xy: np.ndarray, yaw: np.ndarray, v0: np.ndarray, dt_s: float = DT_S):
    """The same paths driven with one constant acceleration from each vehicle's speed now: ``(xy, yaw, speed)``.

    A motion token fixes where a vehicle is after 0.5 s (it is matched and clustered by its end pose); its
    intermediate 10 Hz states come from its cluster's representative and need not start at the vehicle's speed (a
    token chosen for a vehicle at 2.6 m/s can run 4.2, 3.8, 3.4, 3.0, 2.6 m/s: a jump up, then braking). A simulator
    that executes those speeds step by step under its own acceleration limit (SUMO in the commands drive, the safety
    layer of the position drive) clips the jump but not the braking, and the vehicle loses speed at every decision.
    Here each path ``xy [A, F, 2]``, ``yaw [A, F]`` (frame 0 = now) is kept, and its frames are re-placed at the arc
    lengths ``s(t) = v0 t + a t^2 / 2`` with ``a`` chosen so that ``s`` reaches the path's end at the last frame; a
    vehicle that would have to reverse instead brakes uniformly to a stop exactly at the end. Speeds ``v0 [A]`` [m/s]
    (NaN = unknown: that path keeps its frames). Returns ``xy [A, F, 2]``, ``yaw [A, F]`` and the speed over each step
    ``[A, F - 1]`` [m/s].

    (Measured on the full-horizon drop-in, ``examples/full_horizon_runs.py``, commands drive: this profile gave more
    arrivals and speed than one that ends each plan at the token's mean speed, session 11.)
    """
    xy, yaw = np.asarray(xy, np.float64), np.asarray(yaw, np.float64)
    A, F = yaw.shape
    arc = path_arc_length(xy)  # [A, F]
    L = arc[:, -1]
    v = np.maximum(np.nan_to_num(np.asarray(v0, np.float64), nan=0.0), 0.0)
    T = dt_s * (F - 1)
    t = dt_s * np.arange(F)[None, :]  # [1, F]
    a = 2.0 * (L - v * T) / T**2  # [A] constant acceleration that covers L in T
    s = v[:, None] * t + 0.5 * a[:, None] * t * t
    stops = v + a * T < 0.0  # would have to reverse: brake at v^2 / (2 L) and stand at the end
    if stops.any():
        b = v[stops] ** 2 / np.maximum(2.0 * L[stops], 1e-9)
        tt = np.minimum(t, (v[stops] / np.maximum(b, 1e-9))[:, None])
        s[stops] = v[stops, None] * tt - 0.5 * b[:, None] * tt * tt
    s = np.clip(s, 0.0, L[:, None])
    s[:, -1] = L
    out_xy, out_yaw = xy.copy(), yaw.copy()
    for f in range(1, F):
        out_xy[:, f], out_yaw[:, f] = point_along(xy, yaw, arc, s[:, f])
    keep = ~np.isfinite(np.asarray(v0, np.float64))
    out_xy[keep], out_yaw[keep] = xy[keep], yaw[keep]
    speed = np.linalg.norm(np.diff(out_xy, axis=1), axis=-1) / dt_s  # [A, F - 1]
    return out_xy, out_yaw, speed


def carry_speed(xy: np.ndarray, travelled_m: np.ndarray, v0: np.ndarray, dt_s: float = DT_S,
                gains_only: bool = False) -> np.ndarray:
    """Paths ``xy [A, F, 2]`` (frame 0 = now, metres) stretched about frame 0 so that each covers its own length plus
    ``v0 T - travelled``: the speed change a token asks for is read against what the vehicle drove, not against its
    speed now (``T = dt_s (F - 1)``, ``travelled_m [A]`` the arc length the vehicle drove over the last ``T``,
    ``v0 [A]`` its speed now [m/s]; NaN in either keeps that path).

    A motion token is matched by its end pose, so the token that repeats a vehicle's last 0.5 s has that 0.5 s's mean
    speed. After a speed-up the speed now is above that mean; :func:`retime_plan` then drives the repeated token from
    the speed now and must brake to end where it ends: every decision after a speed-up gives half of it back. Stretched,
    the repeated token keeps the speed now, and a faster or slower token changes it by its own difference. A uniform
    stretch keeps every heading (and the path's shape); a path too short to stretch (< 0.05 m) is kept."""
    xy = np.asarray(xy, np.float64)
    T = dt_s * (xy.shape[1] - 1)
    L = path_arc_length(xy)[:, -1]
    extra = np.asarray(v0, np.float64) * T - np.asarray(travelled_m, np.float64)
    if gains_only:
        extra = np.maximum(extra, 0.0)
    ok = np.isfinite(extra) & (L >= 0.05)
    scale = np.where(ok, np.maximum(L + np.where(ok, extra, 0.0), 0.0) / np.maximum(L, 1e-9), 1.0)
    return xy[:, :1] + (xy - xy[:, :1]) * scale[:, None, None]


DECODINGS = ("central", "tokens")
"""How a closed loop turns a token into its 10 Hz states: ``central`` (the default: :func:`decode_frames`) or
``tokens`` (the token's own frames, :func:`token_frames`)."""


def decode_frames(xy: torch.Tensor, yaw: torch.Tensor, prev: torch.Tensor, token: torch.Tensor, vocab,
                  agent_type: torch.Tensor, decoding: str = "central"):
    """The 6 states at 10 Hz of ``token`` placed at pose ``xy [..., 2]`` [m], ``yaw [...]`` [rad], decoded.

    ``tokens``: the token's own frames (:func:`token_frames`), which belong to its cluster's representative: they end
    at the token's end pose but their speed profile need not start at the vehicle's speed.
    ``central``: the same path (same end pose) driven with one constant acceleration (:func:`retime_plan`) from the
    mean of the previous token's and this token's mean speeds, ``(L(prev) + L(token)) / (2 * 0.5 s)``: causal (both
    tokens are chosen when the segment is driven) and continuous across boundaries in expectation. ``prev [...]`` is
    the token that led to the pose (-1 unknown: the start speed is this token's mean speed). Measured on the
    learning curve's 25 held-out scenes with the session-11 nano (``python scripts/diag_rollout_decoding.py``): RMM
    0.8115 -> 0.8163, the linear-acceleration likelihood 0.528 -> 0.623; the boundary poses are unchanged.

    :return: ``(xy [..., 6, 2], yaw [..., 6])``; frame 0 is the given pose, frame 5 the next boundary pose.
    """
    if decoding not in DECODINGS:
        raise ValueError(f"decoding must be one of {DECODINGS}, got {decoding!r}")
    fxy, fyaw = token_frames(xy, yaw, token, vocab, agent_type)
    if decoding == "tokens":
        return fxy, fyaw
    lead = fyaw.shape[:-1]
    seg_xy = fxy.reshape(-1, N_PLAN_FRAMES, 2).double().cpu().numpy()  # retimed on the CPU (numpy), also for cuda
    seg_yaw = fyaw.reshape(-1, N_PLAN_FRAMES).double().cpu().numpy()
    length = path_arc_length(seg_xy)[:, -1]  # [n] [m]
    p_xy, _ = token_frames(torch.zeros_like(xy), torch.zeros_like(yaw), prev, vocab, agent_type)
    p_len = path_arc_length(p_xy.reshape(-1, N_PLAN_FRAMES, 2).double().cpu().numpy())[:, -1]
    p_len = np.where(prev.reshape(-1).cpu().numpy() >= 0, p_len, length)
    new_xy, new_yaw, _ = retime_plan(seg_xy, seg_yaw, (p_len + length) / (2.0 * TOKEN_DT_S), DT_S)
    return (torch.as_tensor(new_xy, dtype=fxy.dtype, device=fxy.device).reshape(*lead, N_PLAN_FRAMES, 2),
            torch.as_tensor(new_yaw, dtype=fyaw.dtype, device=fyaw.device).reshape(*lead, N_PLAN_FRAMES))


# ---------------------------------------------------------------------------- one closed-loop step


class LoopState(NamedTuple):
    """The closed loop's state at boundary pose ``k`` of ``S`` sequences x ``A`` agents.

    prev ``[S, A]`` int64 the token that led here (-1 none); xy ``[S, A, 2]`` [m]; yaw ``[S, A]`` [rad]; valid
    ``[S, A]`` bool.
    """

    prev: torch.Tensor
    xy: torch.Tensor
    yaw: torch.Tensor
    valid: torch.Tensor


class Replay(NamedTuple):
    """Agents that follow their matched log instead of the policy: mask ``[S, A]`` bool; token ``[S, A, 18]``
    (-1 invalid), pose_xy ``[S, A, 19, 2]``, pose_yaw ``[S, A, 19]``, pose_valid ``[S, A, 19]`` of the reference."""

    mask: torch.Tensor
    token: torch.Tensor
    pose_xy: torch.Tensor
    pose_yaw: torch.Tensor
    pose_valid: torch.Tensor


class TokenStep(NamedTuple):
    """One token step of every agent, ``[S, A]`` each.

    token: chosen token (-1 where the agent is not valid before and after the step); logp: the sampler's
    log-probability (truncated, tempered distribution), logp_full: the full softmax's (both 0 for agents not driven
    by the policy); entropy [nats] and k (``K_t``) of the sampler; ``state``: the loop state after the step
    (invalid agents keep their pose).
    """

    token: torch.Tensor
    logp: torch.Tensor
    logp_full: torch.Tensor
    entropy: torch.Tensor
    k: torch.Tensor
    state: LoopState


Host = Callable[[LoopState, torch.Tensor, torch.Tensor], torch.Tensor]


@torch.no_grad()
def token_step(policy, cache, k: int, state: LoopState, sampler, generator: torch.Generator | None, vocab,
               agent_type: torch.Tensor, drive: torch.Tensor, replay: Replay | None = None,
               host: Host | None = None) -> TokenStep:
    """One closed-loop step at boundary pose ``k``: policy step, sampling, next pose and validity.

    :param policy: the model (``step(cache, k, prev, xy, yaw, valid) -> logits [S, A, V]``); ``cache`` its
        ``RolloutCache`` (advanced by this call).
    :param sampler: a :class:`~r1sim_sumo.rollout.samplers.Sampler`; ``generator`` its random generator.
    :param agent_type: ``[S, A]`` int64; ``drive``: ``[S, A]`` bool, the agents the policy drives (only they stay
        valid, and only their log-probabilities are kept).
    :param replay: log-replay agents (their tokens, poses and validity come from the reference).
    :param host: a simulator in the loop: called as ``host(state, token, next_valid) -> alive`` with the state before
        the step, the sampled tokens and the validity after the step (``[S, A]``); it moves its vehicles along the tokens and returns ``[S, A]`` bool,
        False for agents it no longer has (they become invalid from this step: token -1, pose frozen).
    """
    logits = policy.step(cache, k, state.prev, state.xy, state.yaw, state.valid)  # [S, A, V]
    inputs = sampler.token_inputs(vocab, agent_type) if hasattr(sampler, "token_inputs") else {}
    out = sampler(logits.float(), generator, **inputs)
    tok = out.token
    nxt_valid = state.valid & drive
    if replay is not None:
        tok = torch.where(replay.mask, replay.token[:, :, k], tok)
        nxt_valid = torch.where(replay.mask, replay.pose_valid[:, :, k + 1], nxt_valid)
    if host is not None:
        nxt_valid = nxt_valid & host(state, tok, nxt_valid)
    nxt_xy, nxt_yaw = advance_pose(state.xy, state.yaw, tok, vocab, agent_type)
    if replay is not None:
        nxt_xy = torch.where(replay.mask[..., None], replay.pose_xy[:, :, k + 1], nxt_xy)
        nxt_yaw = torch.where(replay.mask, replay.pose_yaw[:, :, k + 1], nxt_yaw)
    tok = torch.where(nxt_valid & state.valid, tok, torch.full_like(tok, -1))
    nxt_xy = torch.where(nxt_valid[..., None], nxt_xy, state.xy)  # invalid agents do not move (token -1 = stand still)
    nxt_yaw = torch.where(nxt_valid, nxt_yaw, state.yaw)
    zero = torch.zeros_like(out.logp)
    return TokenStep(tok, torch.where(drive, out.logp, zero), torch.where(drive, out.logp_full, zero), out.entropy,
                     out.k, LoopState(tok, nxt_xy, nxt_yaw, nxt_valid))


class StepRecorder:
    """Collects :class:`TokenStep` s of one rollout loop and stacks them (``F`` steps).

    ``stack(vocab, agent_type)`` returns token, logp, logp_full, entropy, k ``[S, A, F]``; pose_xy ``[S, A, F+1, 2]``
    and pose_yaw / valid ``[S, A, F+1]`` (boundary poses from the start); xy_10hz ``[S, A, 5F+1, 2]`` and yaw_10hz
    ``[S, A, 5F+1]``: the 10 Hz states of the token chain from the start pose.
    """

    FIELDS = ("token", "logp", "logp_full", "entropy", "k")

    def __init__(self, start: LoopState):
        self.steps: list[TokenStep] = []
        self.start = start

    def append(self, step: TokenStep) -> None:
        self.steps.append(step)

    def stack(self, vocab, agent_type: torch.Tensor, decoding: str = "tokens") -> dict[str, torch.Tensor]:
        """The record; ``decoding`` (:data:`DECODINGS`) gives the 10 Hz states between boundary poses."""
        rec = {f: torch.stack([getattr(s, f) for s in self.steps], -1) for f in self.FIELDS}
        states = [self.start] + [s.state for s in self.steps]
        rec["pose_xy"] = torch.stack([s.xy for s in states], 2)  # [S, A, F+1, 2]
        rec["pose_yaw"] = torch.stack([s.yaw for s in states], 2)
        rec["valid"] = torch.stack([s.valid for s in states], -1)
        if decoding == "tokens":
            rec["xy_10hz"], rec["yaw_10hz"] = reconstruct_states(rec["pose_xy"][:, :, 0], rec["pose_yaw"][:, :, 0],
                                                                 rec["token"], vocab, agent_type)
            return rec
        tok = rec["token"]  # [S, A, F]
        prev = torch.cat([self.start.prev[..., None], tok[..., :-1]], -1)
        atype = agent_type[..., None].expand_as(tok)
        seg_xy, seg_yaw = decode_frames(rec["pose_xy"][:, :, :-1], rec["pose_yaw"][:, :, :-1], prev, tok, vocab, atype,
                                        decoding)  # [S, A, F, 6, 2]
        rec["xy_10hz"] = torch.cat([rec["pose_xy"][:, :, :1], seg_xy[..., 1:, :].flatten(2, 3)], 2)  # [S, A, 5F+1, 2]
        rec["yaw_10hz"] = torch.cat([rec["pose_yaw"][:, :, :1], seg_yaw[..., 1:].flatten(2, 3)], 2)
        return rec


# ---------------------------------------------------------------------------- following a plan


class FollowStep(NamedTuple):
    """Where each followed vehicle stands after one step: xy ``[n, 2]`` [m], yaw ``[n]`` [rad], speed ``[n]`` [m/s]
    driven over the step, v_plan ``[n]`` [m/s] the plan's own speed over the step, slowed ``[n]`` bool (drove slower
    than the plan)."""

    xy: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    v_plan: np.ndarray
    slowed: np.ndarray


class PlanFollower:
    """Per-slot progress of vehicles along their current 10 Hz plans (6 frames, frame 0 = where the plan starts).

    A host keeps one follower for all its vehicles, each in a slot (row) it chooses. Per step of ``dt_s`` [s]:

    * the plan's clock advances by ``dt_s``; its position is the plan interpolated in time between frames (past
      frame 5 the last segment is extrapolated, for hosts whose rate does not divide 0.5 s); ``v_plan`` is the plan's
      speed over the step (clock arc length covered / ``dt_s``);
    * a vehicle that is on time (at the clock's position) and allowed ``v_plan`` stands exactly on the clock's
      position; otherwise it advances by distance, ``v = min(v_plan, v_allowed)``, along the path, lagging the
      clock (until its next plan: :meth:`set_plans` resets progress and clock).

    Arrays ``[S, ...]`` per slot: xy ``[S, 6, 2]`` [m], yaw ``[S, 6]`` [rad], arc ``[S, 6]`` cumulative arc length [m],
    kappa ``[S]`` mean curvature [1/m], prog_m ``[S]`` progress along the path [m], clock_s ``[S]`` plan time [s].
    """

    def __init__(self, capacity: int = 64, frame_dt_s: float = DT_S):
        self.frame_dt_s = float(frame_dt_s)
        self.xy = np.zeros((0, N_PLAN_FRAMES, 2))
        self.yaw = np.zeros((0, N_PLAN_FRAMES))
        self.arc = np.zeros((0, N_PLAN_FRAMES))
        self.kappa = np.zeros(0)
        self.prog_m = np.zeros(0)
        self.clock_s = np.zeros(0)
        self.ensure(capacity)

    @property
    def capacity(self) -> int:
        return len(self.prog_m)

    def ensure(self, capacity: int) -> None:
        """Grow to at least ``capacity`` slots (existing slots keep their state)."""
        n = int(capacity) - self.capacity
        if n <= 0:
            return
        pad = lambda a: np.concatenate([a, np.zeros((n, *a.shape[1:]))])  # noqa: E731
        self.xy, self.yaw, self.arc = pad(self.xy), pad(self.yaw), pad(self.arc)
        self.kappa, self.prog_m, self.clock_s = pad(self.kappa), pad(self.prog_m), pad(self.clock_s)

    def set_plans(self, slots: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> None:
        """New plans ``xy [n, 6, 2]``, ``yaw [n, 6]`` for ``slots [n]``: progress and clock restart at frame 0."""
        slots = np.asarray(slots, np.int64)
        self.xy[slots] = np.asarray(xy, np.float64)
        self.yaw[slots] = np.asarray(yaw, np.float64)
        self.arc[slots] = path_arc_length(self.xy[slots])
        self.kappa[slots] = path_curvature(self.yaw[slots], self.arc[slots])
        self.prog_m[slots] = 0.0
        self.clock_s[slots] = 0.0

    def _clock(self, slots: np.ndarray, t_s: np.ndarray):
        """The plan's clock pose at time ``t_s [n]`` [s]: xy ``[n, 2]``, yaw ``[n]``, arc length ``[n]`` [m]."""
        u = t_s / self.frame_dt_s  # [n] frame (float)
        u = np.where(np.abs(u - np.round(u)) < 1e-9, np.round(u), u)  # clocks summed from 0.1 s steps hit frames exactly
        i0 = np.clip(np.floor(u + 1e-9).astype(np.int64), 0, N_PLAN_FRAMES - 2)  # segment
        f = u - i0  # > 1 extrapolates the last segment
        xy, yaw, arc = self.xy[slots], self.yaw[slots], self.arc[slots]
        r = np.arange(len(slots))
        p = xy[r, i0] + f[:, None] * (xy[r, i0 + 1] - xy[r, i0])
        h = yaw[r, i0] + f * wrap_angle(yaw[r, i0 + 1] - yaw[r, i0])
        s = arc[r, i0] + f * (arc[r, i0 + 1] - arc[r, i0])
        at = np.flatnonzero(f == 1.0)  # on frame 5 exactly: the frame itself, not an interpolation towards it
        p[at], h[at], s[at] = xy[at, -1], yaw[at, -1], arc[at, -1]
        return p, h, s

    def plan_speed(self, slots: np.ndarray, dt_s: float) -> np.ndarray:
        """The plan's speed [m/s] ``[n]`` over the next step of ``dt_s`` [s] (clock arc length covered / ``dt_s``)."""
        slots = np.asarray(slots, np.int64)
        t0 = self.clock_s[slots]
        return (self._clock(slots, t0 + dt_s)[2] - self._clock(slots, t0)[2]) / dt_s

    def follow(self, slots: np.ndarray, dt_s: float, v_allowed: np.ndarray | None = None,
               v_min: np.ndarray | None = None) -> FollowStep:
        """Advance ``slots [n]`` by one step of ``dt_s`` [s], at most at ``v_allowed [n]`` [m/s] (``None`` = the plan)
        and at least at ``v_min [n]`` [m/s] (``None``: no floor; a host keeps it <= ``v_allowed``), e.g. a plan that
        brakes harder than the vehicle can: the vehicle then runs ahead of the plan's clock along its path (past its
        last frame the last segment is extrapolated) until its next plan.

        :return: the poses to place the vehicles at (:class:`FollowStep`).
        """
        slots = np.asarray(slots, np.int64)
        t0 = self.clock_s[slots]
        _, _, s0 = self._clock(slots, t0)
        p, h, s1 = self._clock(slots, t0 + dt_s)
        v_plan = (s1 - s0) / dt_s
        prog = self.prog_m[slots]
        v = v_plan if v_allowed is None else np.minimum(v_plan, np.asarray(v_allowed, np.float64))
        if v_min is not None:
            v = np.maximum(v, np.asarray(v_min, np.float64))
        slowed = v < v_plan - 1e-9
        on_time = np.abs(prog - s0) < _ON_TIME_M
        off = slowed | (v > v_plan + 1e-9) | ~on_time
        prog_next = np.where(off, prog + v * dt_s, s1)
        if off.any():
            q, a = point_along(self.xy[slots[off]], self.yaw[slots[off]], self.arc[slots[off]], prog_next[off],
                               extrapolate=True)
            p, h = p.copy(), h.copy()
            p[off], h[off] = q, a
        self.prog_m[slots] = prog_next
        self.clock_s[slots] = t0 + dt_s
        return FollowStep(p, h, v, v_plan, slowed)
