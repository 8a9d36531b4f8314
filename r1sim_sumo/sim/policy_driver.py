"""Online use of the policy inside a simulator: every 0.5 s, the next motion token of every agent.

``PolicyDriver.plan(history, tl_state)`` takes the last 1.1 s (11 states at 10 Hz, the last one = now) of
every agent near the controlled ones, tokenizes it exactly as in training (rolling-matched history tokens,
map tokens of the whole network encoded once, current traffic-light states), runs one cached policy
step for all agents in one batch, samples a token per agent and returns the next 0.5 s as 10 Hz states
(:class:`Plan`), placed at each agent's *actual* current pose (not the matched one) so that controlled
vehicles never jump. The simulator adapters (``sim/sumo_controller.py``, ``sim/highway_vehicle.py``) own
stepping; this module only decides.

Frames: internal (metres, x east, y north, yaw radians CCW from +x, box centres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from r1sim_sumo.rollout.samplers import Sampler, parse_sampler
from r1sim_sumo.scenario import N_HISTORY_10HZ, N_WINDOW_10HZ, AgentTracks, MapPolylines
from r1sim_sumo.tokens.batch import TokenizedScene, collate
from r1sim_sumo.tokens.map_tokens import tokenize_map
from r1sim_sumo.tokens.matching import match_agents, reconstruct_states

CURRENT_POSE = 2
STEPS_PER_TOKEN = 5
POLICY_DT_S = 0.5  # [s] one decision
SIM_DT_S = 0.1  # [s] one state of a plan


@dataclass
class Plan:
    """The next 0.5 s of ``A`` agents at 10 Hz, frame 0 = now (their actual current pose).

    xy_m ``[A, 6, 2]``, yaw_rad ``[A, 6]``, speed_mps ``[A, 5]`` (speed over each 0.1 s step), token ``[A]``,
    entropy ``[A]`` [nats] of the policy's distribution, ok ``[A]`` the plan is usable (finite, agent valid).
    """

    xy_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray
    token: np.ndarray
    entropy: np.ndarray
    ok: np.ndarray


class PolicyDriver:
    """Decides the next 0.5 s of agents with a trained policy.

    :param policy: a loaded policy (``r1sim_sumo.load_policy()``), with ``.model`` and ``.vocab``.
    :param road_map: the network's map (static polylines; per-lane traffic-light states are passed to ``plan``).
    :param sampler: a :class:`Sampler` or spec string (``topk:5``, ``entropy:16,80``, ``greedy``...).
    :param seed: seed of the sampler's random generator (episodes reproduce).
    :param map_radius_m: unused (kept for compatibility): the whole network is encoded once and every agent
        attends to its nearest map tokens within the model's own radius.
    """

    def __init__(self, policy, road_map: MapPolylines, sampler: Sampler | str = "topk:5", seed: int = 0,
                 map_radius_m: float = 60.0, device: str = "cpu"):
        self.model = policy.model.eval().to(device)
        self.vocab = policy.vocab
        self.sampler = parse_sampler(sampler) if isinstance(sampler, str) else sampler
        self.generator = torch.Generator().manual_seed(int(seed))
        self.map_radius_m = float(map_radius_m)
        self.device = device
        self.map_tokens = tokenize_map(road_map, n_pose=N_WINDOW_10HZ // STEPS_PER_TOKEN + 1)
        self._no_map = self.map_tokens.select(np.zeros(0, np.int64))
        self._map_ctx = self._encode_static_map()

    @torch.no_grad()
    def _encode_static_map(self):
        """Encode every map token of the network once: the map encoder does not see traffic-light states
        (they enter the agent layers), so per decision only ``MapContext.tl`` changes."""
        from r1sim_sumo.tokens.matching import TokenizedAgents

        empty = TokenizedAgents(
            token=np.full((0, 18), -1, np.int64), token_valid=np.zeros((0, 18), bool), pose_xy=np.zeros((0, 19, 2), np.float32),
            pose_yaw=np.zeros((0, 19), np.float32), pose_valid=np.zeros((0, 19), bool), agent_type=np.zeros(0, np.int64),
            length_m=np.zeros(0, np.float32), width_m=np.zeros(0, np.float32))
        batch = collate([TokenizedScene(empty, self.map_tokens, np.zeros(0, str), np.zeros(0, np.int64), "map")]).to(self.device)
        return self.model.encode_map(batch)

    def _map_context(self, tl_state: np.ndarray | None):
        """The cached map encoding with the current per-lane traffic-light states ``[L]``."""
        ctx = self._map_ctx
        if tl_state is None or not len(tl_state):
            return ctx
        tl = torch.as_tensor(np.asarray(tl_state, np.int64)[self.map_tokens.polyline], device=self.device)  # [M]
        tl = tl.clamp(0, self.model.config.num_tl_states - 1)
        return ctx._replace(tl=tl.view(1, -1, 1).expand_as(ctx.tl))

    @torch.no_grad()
    def plan(self, history: AgentTracks, tl_state: np.ndarray | None = None) -> Plan:
        """Next-0.5 s plan of every agent of ``history`` (``[A, <=11]`` states at 10 Hz, last = now).

        Agents not valid now get ``ok = False``; tl_state ``[L]`` int8 per map polyline (None = no signals).
        """
        A, T = history.num_agents, history.num_steps
        if T < 1:
            raise ValueError("PolicyDriver.plan: history needs at least the current state")
        win = AgentTracks.empty(A, N_WINDOW_10HZ)
        win.ids, win.agent_type, win.length_m, win.width_m = history.ids, history.agent_type, history.length_m, history.width_m
        n = min(T, N_HISTORY_10HZ)
        for f in (*AgentTracks.PER_STEP, "valid"):
            getattr(win, f)[:, N_HISTORY_10HZ - n:N_HISTORY_10HZ] = getattr(history, f)[:, T - n:]
        now_valid = win.valid[:, N_HISTORY_10HZ - 1].copy()
        agents = match_agents(win, self.vocab)
        scene = TokenizedScene(agents, self._no_map, np.asarray(history.ids).astype(str), np.arange(A), "online")
        batch = collate([scene]).to(self.device)
        # one teacher-forced pass over token steps 0..2 (history tokens 0, 1 and "now"): the same logits as
        # init_rollout + step (the cached path is tested equal to the uncached one) with a third of the ops
        short = batch._replace(agent_token=batch.agent_token[:, :, : CURRENT_POSE + 1],
                               agent_token_valid=batch.agent_token_valid[:, :, : CURRENT_POSE + 1])
        logits = self.model(short, map_ctx=self._map_context(tl_state), last_step_only=True)[:, :, -1]  # [1, A, V]
        out = self.sampler(logits.float(), self.generator)  # [1, A]
        token = out.token[0]
        # place the token at the actual current pose
        xy0 = torch.from_numpy(np.stack([history.x_m[:, -1], history.y_m[:, -1]], -1).astype(np.float32))
        yaw0 = torch.from_numpy(history.yaw_rad[:, -1].astype(np.float32))
        xy, yaw = reconstruct_states(xy0, yaw0, token[:, None], self.vocab, torch.from_numpy(np.asarray(history.agent_type, np.int64)))
        xy, yaw = xy.numpy(), yaw.numpy()  # [A, 6, 2], [A, 6]
        speed = np.linalg.norm(np.diff(xy, axis=1), axis=-1) / SIM_DT_S  # [A, 5]
        ok = now_valid & np.isfinite(xy).all((1, 2)) & np.isfinite(yaw).all(1)
        return Plan(xy, yaw, speed.astype(np.float32), token.numpy(), out.entropy[0].numpy(), ok)
