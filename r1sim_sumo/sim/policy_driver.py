"""Online use of the policy inside a simulator: every 0.5 s, the next motion token of every agent.

``PolicyDriver.plan(history, tl_state)`` takes the last 1.1 s (11 states at 10 Hz, the last one = now) of
every agent near the controlled ones, tokenizes it exactly as in training (rolling-matched history tokens,
map tokens of the whole network encoded once, current traffic-light states), runs one cached policy
step for all agents in one batch, samples a token per agent and returns the next 0.5 s as 10 Hz states
(:class:`Plan`), placed at each agent's *actual* current pose (not the matched one) so that controlled
vehicles never jump.

With ``memory=True`` (the SUMO controller's setting) the driver keeps each agent's per-layer features of its
last decisions (:class:`~r1sim_sumo.rollout.policy_state.PolicyState`, per agent id): an agent seen at the previous decision (0.5 s ago, at the
pose it now reports 0.5 s back) costs one policy step instead of three and attends to up to 2.5 s of its own
past, as in batched rollouts. Agents seen for the first time (or after a gap, or whose remembered pose does
not match the history: a reused id) are warmed up from their history tokens as in the stateless mode. The simulator adapters (``sim/sumo_controller.py``, ``sim/highway_vehicle.py``) own
stepping; this module only decides.

Frames: internal (metres, x east, y north, yaw radians CCW from +x, box centres).
"""

from __future__ import annotations

import copy
import hashlib
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from r1sim_sumo._memory import keep_freed_memory
from r1sim_sumo._threads import few_threads
from r1sim_sumo.rollout.kernel import carry_speed, retime_plan, token_frames
from r1sim_sumo.rollout.policy_state import PolicyState
from r1sim_sumo.rollout.samplers import Sampler, parse_sampler
from r1sim_sumo.scenario import DT_S as SIM_DT_S  # [s] one state of a plan
from r1sim_sumo.scenario import N_HISTORY_10HZ, N_WINDOW_10HZ, AgentTracks, MapPolylines
from r1sim_sumo.tokens.batch import TokenizedScene, collate
from r1sim_sumo.tokens.constants import CURRENT_POSE, STEPS_PER_TOKEN
from r1sim_sumo.tokens.map_tokens import tokenize_map
from r1sim_sumo.tokens.matching import match_agents

SPEED_CARRY = ("off", "gains", "both")
"""PolicyDriver(speed_carry=...): how a token's speed change is read (see its docstring)."""


@dataclass
class Plan:
    """The next 0.5 s of ``A`` agents at 10 Hz, frame 0 = now (their actual current pose).

    xy_m ``[A, 6, 2]``, yaw_rad ``[A, 6]``, speed_mps ``[A, 5]`` (speed over each 0.1 s step), token ``[A]``,
    entropy ``[A]`` [nats] of the policy's distribution (NaN unless the driver was made with ``record_entropy=True``),
    ok ``[A]`` the plan is usable (finite, agent valid).
    """

    xy_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray
    token: np.ndarray
    entropy: np.ndarray
    ok: np.ndarray


@dataclass
class _EncodedMap:
    """The map encoding a :class:`PolicyDriver` builds tile by tile and shares with its forks. Both fields live here,
    together, so that a fork encoding a tile writes it where the template and every other fork read it: until session
    57 a fork set the shared tile flags but kept the encoding to itself, and every later fork of the same template found
    the tiles marked done and drove with no map at all (highway-env episodes after the first of a process)."""

    encoded: np.ndarray  # [n_tiles] bool
    ctx: object = None  # MapContext or None


class PolicyDriver:
    """Decides the next 0.5 s of agents with a trained policy.

    :param policy: a loaded policy (``r1sim_sumo.load_policy()``), with ``.model`` and ``.vocab``.
    :param road_map: the network's map (static polylines; per-lane traffic-light states are passed to ``plan``).
    :param sampler: a :class:`Sampler` or spec string (``topk:5``, ``entropy:16,80``, ``greedy``...).
    :param seed: seed of the sampler's random generator (episodes reproduce).
    :param map_radius_m: unused (kept for compatibility): the whole network is encoded once and every agent
        attends to its nearest map tokens within the model's own radius.
    :param memory: keep per-agent features between consecutive decisions (see the module doc); ``plan`` must
        then be called exactly every 0.5 s of simulated time. ``reset()`` forgets them.
    :param map_cache_dir: folder where the encoded map is kept between runs (one file per network and map encoder,
        named by a hash of the map tokens and the encoder weights, so a changed network or checkpoint never reuses
        a stale one); ``None`` = no cache.
    :param lazy_map: on networks encoded in tiles (more than :data:`WHOLE_MAP_MAX_TOKENS` map tokens, tiles of
        :data:`TILE_M`), encode a tile only when an agent first comes near it (start-up then costs reading the map, not
        encoding it); ``False``: everything at start. Smaller networks are encoded whole at start.
    :param retime: drive each token's path at one constant acceleration from the agent's speed now
        (:func:`~r1sim_sumo.rollout.kernel.retime_plan`; the token's end pose is kept) instead of its representative's
        own 10 Hz frames, whose speeds need not start at the agent's speed. ``False``: the token's frames as they are.
    :param speed_carry: with ``retime``, first stretch each token's path by what the agent's speed now is above its
        mean speed over the last 0.5 s (:func:`~r1sim_sumo.rollout.kernel.carry_speed`): the token that repeats the
        last 0.5 s keeps the speed now instead of giving back half of a speed-up. ``gains``: only that; ``both``: also
        shorten it by what the speed now is below that mean (a slow-down is kept too); ``off`` (default): the token's
        end pose. The speed now is the host's (``history.speed_mps``): in SUMO's commands drive the front bumper's
        along its lane, up to a few per cent above the box centre's in a curve, which reads as a small speed-up at each
        decision there (the centre's own last-0.1 s displacement instead, tried in session 58, was noisier and gave
        more collision events in the position drive: docs/simulate/speed_carry_s58); in the position drive since
        session 59 the speed the controller moved the vehicle at along its last plan
        (``SumoController._speed_as_moved``).
    :param guidance: desired-speed guidance weight ``w >= 0`` (classifier-free guidance on the desired-speed input,
        as in Ho & Salimans 2022 and its use for language models): the tokens are drawn from
        ``log p(token | desired speed) + w * (log p(token | desired speed) - log p(token | desired speed unknown))``.
        The policy was trained with each agent's desired speed hidden 10% of the time (``desired_speed_drop_prob``), so
        it knows both distributions; ``w > 0`` strengthens what the desired speed changes (a car below it speeds up
        more readily, one above it slows). Costs a second policy step per decision (its own memory). ``0``: off.
        Needs a model with ``desired_speed_input``.
    """

    def __init__(self, policy, road_map: MapPolylines, sampler: Sampler | str = "topk:5", seed: int = 0,
                 map_radius_m: float = 60.0, device: str = "cpu", memory: bool = False,
                 map_cache_dir: str | Path | None = None, lazy_map: bool = True, retime: bool = True,
                 record_entropy: bool = False, guidance: float = 0.0, speed_carry: str = "off"):
        keep_freed_memory()  # decisions reuse the same few-MB temporaries: keep freed heap mapped (r1sim_sumo._memory)
        self.model = policy.model.eval().to(device)
        self.record_entropy = bool(record_entropy)
        self.retime = bool(retime)
        if speed_carry not in SPEED_CARRY:
            raise ValueError(f"speed_carry={speed_carry!r}: use one of {', '.join(SPEED_CARRY)}")
        if speed_carry != "off" and not self.retime:
            raise ValueError(f"speed_carry={speed_carry!r} stretches the retimed plans: it needs retime=True")
        self.speed_carry = speed_carry
        self.memory = bool(memory)
        self.state = PolicyState(self.model, device)  # per-agent memory (memory mode)
        self.guidance = float(guidance)
        if not (np.isfinite(self.guidance) and self.guidance >= 0.0):
            raise ValueError(f"guidance={guidance!r}: the desired-speed guidance weight must be a number >= 0 (0 = off)")
        if self.guidance and not self.model.config.desired_speed_input:
            raise ValueError(f"guidance={guidance!r}: this policy takes no desired speed (config desired_speed_input is "
                             "off), so there is nothing to guide; use guidance=0")
        self._state_free = PolicyState(self.model, device)  # the memory of the desired-speed-unknown pass (guidance)
        self.vocab = policy.vocab
        self.sampler = parse_sampler(sampler) if isinstance(sampler, str) else sampler
        self.generator = torch.Generator().manual_seed(int(seed))
        self.map_radius_m = float(map_radius_m)
        self.device = device
        self.map_tokens = tokenize_map(road_map, n_pose=N_WINDOW_10HZ // STEPS_PER_TOKEN + 1)
        self._no_map = self.map_tokens.select(np.zeros(0, np.int64))
        self.map_cache_file = None
        c = self.model.config
        whole = self.map_tokens.num_tokens <= WHOLE_MAP_MAX_TOKENS  # small networks: one tile, as the card's forward
        self._tiles = map_tiles(token_centres(self.map_tokens), halo_m=c.map_layers * c.map_radius_m + 1.0,
                                tile_m=math.inf if whole else None)
        self._tile_box = np.array([[*token_centres(self.map_tokens.select(core)).min(0),
                                    *token_centres(self.map_tokens.select(core)).max(0)] for core, _ in self._tiles])
        self._map = _EncodedMap(np.zeros(len(self._tiles), bool))  # shared with every fork (fork() copies the reference)
        if map_cache_dir is not None:
            self.map_cache_file = self._cache_path(map_cache_dir)
            self._map_ctx = self._load_cached()
        if self._map_ctx is None and (not lazy_map or len(self._tiles) <= 1):
            self._ensure_all()

    @property
    def _encoded(self) -> np.ndarray:
        """``[n_tiles]`` bool: the tiles already in :attr:`_map_ctx` (the driver's and its forks' one record)."""
        return self._map.encoded

    @property
    def _map_ctx(self):
        """The encoded map (``None`` until a first tile is encoded), shared by the driver and its forks."""
        return self._map.ctx

    @_map_ctx.setter
    def _map_ctx(self, ctx) -> None:
        self._map.ctx = ctx

    @property
    def tiles_encoded(self) -> tuple[int, int]:
        """(tiles encoded so far, tiles of the network)."""
        return int(self._encoded.sum()), len(self._tiles)

    def _ensure_all(self) -> None:
        self._encode_tiles(np.flatnonzero(~self._encoded))

    def ensure_map_near(self, xy: np.ndarray, reach_m: float) -> None:
        """Encode every tile with a token within ``reach_m`` [m] of the points ``xy [K, 2]`` [m] (not yet encoded)."""
        todo = np.flatnonzero(~self._encoded)
        if not len(todo) or not len(xy):
            return
        box = self._tile_box[todo]  # [n, 4] x0, y0, x1, y1
        p = np.asarray(xy, np.float64)[:, None, :]  # [K, 1, 2]
        dx = np.maximum(np.maximum(box[None, :, 0] - p[..., 0], p[..., 0] - box[None, :, 2]), 0.0)
        dy = np.maximum(np.maximum(box[None, :, 1] - p[..., 1], p[..., 1] - box[None, :, 3]), 0.0)
        need = ((dx * dx + dy * dy) <= reach_m * reach_m).any(0)  # [n]
        if need.any():
            self._encode_tiles(todo[need])

    @torch.no_grad()
    def _encode_tiles(self, which: np.ndarray) -> None:
        """Encode the tiles ``which`` (each with its halo) into the map context; stores the cache once complete."""
        if not len(which):
            return
        M = self.map_tokens.num_tokens
        whole = len(self._tiles) == 1
        for t in which:
            core, halo = self._tiles[t]
            ctx = self._encode_tokens(halo)
            if self._map_ctx is None:
                self._map_ctx = type(ctx)(ctx.feat.new_zeros((1, M, ctx.feat.shape[-1])), ctx.pose.new_zeros((1, M, 4)),
                                          ctx.tl.new_zeros((1, M, ctx.tl.shape[-1])), ctx.valid.new_zeros((1, M)))
            if whole:
                self._map_ctx = ctx
            else:
                keep = torch.from_numpy(np.searchsorted(halo, core)).to(self.device)  # rows of the core tokens in ctx
                at = torch.from_numpy(core).to(self.device)
                m = self._map_ctx
                m.feat[:, at], m.pose[:, at], m.tl[:, at], m.valid[:, at] = (ctx.feat[:, keep], ctx.pose[:, keep],
                                                                             ctx.tl[:, keep], ctx.valid[:, keep])
            self._encoded[t] = True
        if self._encoded.all() and self.map_cache_file is not None:
            self._store_cached()

    def _cache_path(self, cache_dir) -> Path:
        h = hashlib.sha256()
        for f in self.map_tokens.FIELDS:
            a = np.ascontiguousarray(getattr(self.map_tokens, f))
            h.update(f"{f}{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
        for k, v in self.model.state_dict().items():
            if k.startswith(("map_", "map.")):
                h.update(k.encode())
                h.update(v.detach().cpu().contiguous().numpy().tobytes())
        h.update(f"{TILE_M}{self.model.config!r}tiles{len(self._tiles)}".encode())  # tiled and whole differ at ties
        return Path(cache_dir) / f"map_{h.hexdigest()[:32]}.pt"

    def _load_cached(self):
        """The whole encoded map from the cache file, or ``None``."""
        path = self.map_cache_file
        if not path.is_file():
            return None
        try:
            d = torch.load(path, map_location=self.device, weights_only=True)
        except Exception:  # noqa: BLE001 - unreadable cache file: encode again and overwrite it
            return None
        from r1sim_sumo.model.policy import MapContext

        self._encoded[:] = True
        return MapContext(d["feat"], d["pose"], d["tl"], d["valid"])

    def _store_cached(self) -> None:
        ctx, path = self._map_ctx, self.map_cache_file
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".tmp{os.getpid()}")
            torch.save({"feat": ctx.feat, "pose": ctx.pose, "tl": ctx.tl, "valid": ctx.valid}, tmp)
            os.replace(tmp, path)
        except OSError:  # a read-only cache folder: the run goes on without caching
            pass

    def _encode_static_map(self):
        """The whole network's encoded map (every tile). The map encoder does not see traffic-light states (they
        enter the agent layers), so per decision only ``MapContext.tl`` changes.

        The map is encoded tile by tile (:func:`map_tiles`): map-to-map attention only reaches ``map_radius_m``
        per layer, so a tile encoded together with every token within ``map_layers x map_radius_m`` of it (its
        halo) gives its tokens the same features as encoding the whole network at once (up to ties in distance
        among the k nearest), at a cost linear in the number of tokens instead of quadratic. With ``lazy_map``
        a tile is encoded when an agent first comes within ``map_agent_radius_m`` of it."""
        self._ensure_all()
        return self._map_ctx

    @torch.no_grad()
    def _encode_tokens(self, idx: np.ndarray):
        """Encoded map context of the map tokens ``idx`` (sorted indices into ``self.map_tokens``)."""
        from r1sim_sumo.tokens.matching import TokenizedAgents

        empty = TokenizedAgents(
            token=np.full((0, 18), -1, np.int64), token_valid=np.zeros((0, 18), bool), pose_xy=np.zeros((0, 19, 2), np.float32),
            pose_yaw=np.zeros((0, 19), np.float32), pose_valid=np.zeros((0, 19), bool), agent_type=np.zeros(0, np.int64),
            length_m=np.zeros(0, np.float32), width_m=np.zeros(0, np.float32))
        tokens = self.map_tokens if len(idx) == self.map_tokens.num_tokens else self.map_tokens.select(idx)
        batch = collate([TokenizedScene(empty, tokens, np.zeros(0, str), np.zeros(0, np.int64), "map")]).to(self.device)
        return self.model.encode_map(batch)

    def _map_context(self, tl_state: np.ndarray | None, history: AgentTracks | None = None):
        """The cached map encoding with the current per-lane traffic-light states ``[L]`` (tiles near the agents of
        ``history`` encoded first)."""
        if history is not None and not self._encoded.all():
            ok = history.valid
            xy = np.stack([history.x_m[ok], history.y_m[ok]], -1)
            self.ensure_map_near(xy, self.model.config.map_agent_radius_m + MAP_REACH_MARGIN_M)
        ctx = self._map_ctx
        if tl_state is None or not len(tl_state):
            return ctx
        tl = torch.as_tensor(np.asarray(tl_state, np.int64)[self.map_tokens.polyline], device=self.device)  # [M]
        tl = tl.clamp(0, self.model.config.num_tl_states - 1)
        return ctx._replace(tl=tl.view(1, -1, 1).expand_as(ctx.tl))

    @torch.no_grad()
    def plan(self, history: AgentTracks, tl_state: np.ndarray | None = None, sides: np.ndarray | None = None,
             quantile: np.ndarray | None = None, carry: np.ndarray | None = None) -> Plan:
        """Next-0.5 s plan of every agent of ``history`` (``[A, <=11]`` states at 10 Hz, last = now).

        Agents not valid now get ``ok = False``; tl_state ``[L]`` int8 per map polyline (None = no signals).
        ``sides`` ``[A]`` int (+1 left, -1 right, 0 neither; None = either): the side an ``intent`` sampler may draw
        for each agent (the host's route: the side of the lane it must change to), ignored by other samplers.
        ``quantile`` ``[A]`` float in (0, 1) (None = the sampler's own): each agent's travel quantile for a
        ``median`` / ``quantile`` sampler (the drop-in's free-road quantile), ignored by other samplers.
        ``carry`` ``[A]`` bool (None = every agent): with ``speed_carry``, the agents whose plans it stretches (the
        drop-in's free-road vehicles); the others end at their token's end pose.
        Up to ``r1sim_sumo._threads.SMALL_ROWS`` agents the whole decision runs on one CPU thread (faster).
        """
        with few_threads(history.num_agents, self.device):
            return self._plan(history, tl_state, sides, quantile, carry)

    def _plan(self, history: AgentTracks, tl_state: np.ndarray | None, sides: np.ndarray | None = None,
              quantile: np.ndarray | None = None, carry: np.ndarray | None = None) -> Plan:
        A, T = history.num_agents, history.num_steps
        if T < 1:
            raise ValueError("PolicyDriver.plan: history needs at least the current state")
        # the last 1.1 s, right-aligned (a shorter history leaves the oldest states invalid), matched as the history
        # part of a training window; the window's future poses are invalid (padded_to)
        win = AgentTracks.empty(A, N_HISTORY_10HZ)
        win.ids, win.agent_type, win.length_m, win.width_m = history.ids, history.agent_type, history.length_m, history.width_m
        win.desired_speed_mps = history.desired_speed_mps  # the host's; unknown ones are estimated from the history
        n = min(T, N_HISTORY_10HZ)
        for f in (*AgentTracks.PER_STEP, "valid"):
            getattr(win, f)[:, N_HISTORY_10HZ - n:] = getattr(history, f)[:, T - n:]
        now_valid = win.valid[:, -1].copy()
        agents = match_agents(win, self.vocab).padded_to(N_WINDOW_10HZ // STEPS_PER_TOKEN + 1)
        scene = TokenizedScene(agents, self._no_map, np.asarray(history.ids).astype(str), np.arange(A), "online")
        batch = collate([scene]).to(self.device)
        ctx = self._map_context(tl_state, history)
        logits = self._logits(history, agents, batch, ctx)
        if self.guidance:
            free = self._logits(history, agents, _desired_unknown(batch), ctx, unknown_desired=True)
            guided = logits + self.guidance * (logits.log_softmax(-1) - free.log_softmax(-1))
            logits = torch.where(torch.isfinite(guided), guided, logits)  # ids invalid for a type stay at -inf
        inputs = getattr(self.sampler, "token_inputs", None)  # a stand-in sampler may read no token geometry
        extra = inputs(self.vocab, torch.from_numpy(np.asarray(history.agent_type, np.int64))[None]) if inputs else {}
        if "token_lateral" in extra and sides is not None:
            extra["sides"] = torch.as_tensor(np.asarray(sides, np.int64))[None]
        if "token_forward" in extra and quantile is not None:
            extra["quantile"] = torch.as_tensor(np.asarray(quantile, np.float32))[None]
        if self.record_entropy:
            out = self.sampler(logits.float(), self.generator, **extra)  # [1, A]
            token, entropy = out.token[0], out.entropy[0].numpy()
        else:  # the same draws without the full distribution's statistics (the drop-in's hot path)
            token, entropy = self.sampler.draw(logits.float(), self.generator, **extra)[0], np.full(A, np.nan, np.float32)
        # place the token at the actual current pose
        xy0 = torch.from_numpy(np.stack([history.x_m[:, -1], history.y_m[:, -1]], -1).astype(np.float32))
        yaw0 = torch.from_numpy(history.yaw_rad[:, -1].astype(np.float32))
        xy, yaw = token_frames(xy0, yaw0, token, self.vocab, torch.from_numpy(np.asarray(history.agent_type, np.int64)))
        xy, yaw = xy.numpy(), yaw.numpy()  # [A, 6, 2], [A, 6]
        if self.retime:  # the token's path at one constant acceleration from the speed now (see retime_plan)
            v_now = np.where(now_valid, history.speed_mps[:, -1], np.nan)
            if self.speed_carry != "off":  # read the token's speed change against the last 0.5 s driven (carry_speed)
                travelled = _travelled_last_token(history)
                if carry is not None:
                    travelled = np.where(np.asarray(carry, bool), travelled, np.nan)
                xy = carry_speed(xy, travelled, v_now, SIM_DT_S, self.speed_carry == "gains")
            xy, yaw, speed = retime_plan(xy, yaw, v_now, SIM_DT_S)
            xy, yaw = xy.astype(np.float32), yaw.astype(np.float32)
        else:
            speed = np.linalg.norm(np.diff(xy, axis=1), axis=-1) / SIM_DT_S  # [A, 5]
        ok = now_valid & np.isfinite(xy).all((1, 2)) & np.isfinite(yaw).all(1)
        return Plan(xy, yaw, speed.astype(np.float32), token.numpy(), entropy, ok)

    def _logits(self, history: AgentTracks, agents, batch, ctx, unknown_desired: bool = False) -> torch.Tensor:
        """Logits ``[1, A, V]`` of this decision; ``unknown_desired``: the guidance's pass (``batch`` already without
        desired speeds; in memory mode it keeps its own memory)."""
        if self.memory:
            return self._step_with_memory(history, agents, batch, ctx, unknown_desired)
        # one teacher-forced pass over token steps 0..2 (history tokens 0, 1 and "now"): the same logits as
        # init_rollout + step (the cached path is tested equal to the uncached one) with a third of the ops
        short = batch._replace(agent_token=batch.agent_token[:, :, : CURRENT_POSE + 1],
                               agent_token_valid=batch.agent_token_valid[:, :, : CURRENT_POSE + 1])
        return self.model(short, map_ctx=ctx, last_step_only=True)[:, :, -1]  # [1, A, V]

    def reset(self) -> None:
        """Forget every agent's remembered features (e.g. a new episode)."""
        self.state.reset()
        self._state_free.reset()

    def fork(self, seed: int) -> PolicyDriver:
        """A driver sharing this one's model, map tokens and encoded map, with its own sampler generator seeded by
        ``seed`` and its own (empty) memory."""
        drv = copy.copy(self)
        drv.generator = torch.Generator().manual_seed(int(seed))
        drv.state = PolicyState(self.model, self.device)
        drv._state_free = PolicyState(self.model, self.device)
        return drv

    @property
    def wants_desired_speed(self) -> bool:
        """The policy takes each agent's desired speed (``AgentTracks.desired_speed_mps`` of the history)."""
        return bool(self.model.config.desired_speed_input)

    @property
    def last_known(self) -> int:
        """Agents whose remembered features the last plan reused (memory mode)."""
        return self.state.last_known

    def _step_with_memory(self, history: AgentTracks, agents, batch, ctx, unknown_desired: bool = False) -> torch.Tensor:
        """Logits ``[1, A, V]`` of the current step through :class:`~r1sim_sumo.rollout.policy_state.PolicyState`
        (``unknown_desired``: the guidance's pass, with its own memory and fresh agents warmed up without desired
        speeds too)."""
        ids = [str(v) for v in history.ids]
        now_xy = np.stack([history.x_m[:, -1], history.y_m[:, -1]], -1)  # [A, 2]
        back = history.num_steps - 1 - STEPS_PER_TOKEN  # index of the state 0.5 s ago
        if back < 0:
            back_xy, back_ok = np.zeros_like(now_xy), np.zeros(len(ids), bool)
        else:
            back_xy = np.stack([history.x_m[:, back], history.y_m[:, back]], -1)
            back_ok = history.valid[:, back:].all(1)

        def warm_up(fresh: np.ndarray):
            scene = TokenizedScene(agents.select(fresh), self._no_map, np.asarray(ids)[fresh], fresh, "warm-up")
            b = collate([scene]).to(self.device)
            return _desired_unknown(b) if unknown_desired else b

        state = self._state_free if unknown_desired else self.state
        return state.step(ids, now_xy, back_xy, back_ok, batch, warm_up, ctx)


def _travelled_last_token(history: AgentTracks) -> np.ndarray:
    """Arc length [m] each agent drove over the last 0.5 s (its last 6 states at 10 Hz), NaN where one is invalid."""
    n = STEPS_PER_TOKEN + 1
    if history.x_m.shape[1] < n:
        return np.full(history.x_m.shape[0], np.nan)
    xy = np.stack([history.x_m[:, -n:], history.y_m[:, -n:]], -1).astype(np.float64)
    d = np.linalg.norm(np.diff(xy, axis=1), axis=-1).sum(1)
    return np.where(history.valid[:, -n:].all(1), d, np.nan)


def _desired_unknown(batch):
    """``batch`` with every agent's desired speed unknown (NaN: the model adds nothing for it), as in the 10% of
    training samples whose desired speed was hidden."""
    return batch._replace(agent_desired_speed=torch.full_like(batch.agent_desired_speed, float("nan")))


TILE_M = 250.0  # [m] side of a map tile encoded at once (with its halo) on large networks
# Networks of up to this many map tokens are encoded at once, as a whole-scene forward does (the bundled networks have
# 772-5,796; a 46 lane-km city grid over 20,000). Tiles give the same features up to exact distance ties among a token's
# k nearest neighbours, which torch's top-k breaks differently on rows of another length; on the bundled networks that
# changed 8-64% of the map tokens' features (by up to 1.85; scripts/diag_map_tiles.py), and game/ramp's commands drive delivered more vehicles with the
# whole map on 7 of 8 seeds (0.959 vs 0.946 of native's arrivals; session 48, docs/simulate/lane_speed_s48).
WHOLE_MAP_MAX_TOKENS = 10_000
MAP_REACH_MARGIN_M = 5.0  # [m] tiles within the map-to-agent radius plus this of an agent are encoded before it plans


def default_map_cache_dir() -> Path:
    """``$R1SIM_CACHE_DIR/maps``, else ``$XDG_CACHE_HOME/r1sim_sumo/maps``, else ``~/.cache/r1sim_sumo/maps``."""
    if os.environ.get("R1SIM_CACHE_DIR"):
        return Path(os.environ["R1SIM_CACHE_DIR"]) / "maps"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "r1sim_sumo" / "maps"


def token_centres(tokens) -> np.ndarray:
    """World position [m] ``[M, 2]`` of each map token's middle point (as the model's map encoder places it)."""
    mid = tokens.pts[:, tokens.pts.shape[1] // 2].astype(np.float64)  # [M, 2] own frame
    c, s = np.cos(tokens.yaw.astype(np.float64)), np.sin(tokens.yaw.astype(np.float64))
    return tokens.pos.astype(np.float64) + np.stack([mid[:, 0] * c - mid[:, 1] * s, mid[:, 0] * s + mid[:, 1] * c], -1)


def map_tiles(xy: np.ndarray, halo_m: float, tile_m: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Square tiles of side ``tile_m`` [m] (default :data:`TILE_M`) over points ``xy [M, 2]``: per non-empty tile ``(core, halo)``, the
    sorted indices of its points and of every point within ``halo_m`` [m] (per axis) of the tile (core included).
    A uniform grid: each point is binned once and each tile looks at its neighbouring bins only."""
    tile_m = TILE_M if tile_m is None else float(tile_m)
    if len(xy) == 0:
        return []
    lo = xy.min(0)
    cell = np.floor((xy - lo) / tile_m).astype(np.int64)  # [M, 2]
    span = cell.max(0) + 1
    if span[0] * span[1] == 1:
        return [(np.arange(len(xy)), np.arange(len(xy)))]
    key = cell[:, 0] * span[1] + cell[:, 1]
    order = np.argsort(key, kind="stable")
    keys, starts = np.unique(key[order], return_index=True)
    bins = dict(zip(keys.tolist(), np.split(order, starts[1:]), strict=True))
    reach = int(np.ceil(halo_m / tile_m))
    tiles = []
    for k, core in bins.items():
        cx, cy = divmod(k, int(span[1]))
        near = [bins[(cx + i) * span[1] + cy + j] for i in range(-reach, reach + 1) for j in range(-reach, reach + 1)
                if 0 <= cx + i < span[0] and 0 <= cy + j < span[1] and (cx + i) * span[1] + cy + j in bins]
        cand = np.concatenate(near)
        x0, y0 = lo + np.array([cx, cy]) * tile_m
        p = xy[cand]
        inside = ((p[:, 0] >= x0 - halo_m) & (p[:, 0] <= x0 + tile_m + halo_m)
                  & (p[:, 1] >= y0 - halo_m) & (p[:, 1] <= y0 + tile_m + halo_m))
        tiles.append((np.sort(core), np.sort(cand[inside])))
    return tiles
