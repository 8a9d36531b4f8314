"""Gymnasium env: an RL ego in a bundled SUMO network, background traffic driven by the learned policy.

``gym.make("r1sim/sumo-<network>-v0", config={...})`` (after ``import r1sim_sumo.envs``). SUMO runs
in-process through **libsumo, which holds ONE simulation per process**: create one SumoEgoEnv per process
(vectorise with ``SubprocVecEnv``/``AsyncVectorEnv``); a second env in the same process raises on ``reset``
until the first is closed.

Episode: ``reset(seed)`` starts SUMO on the network's ``.sumocfg`` (``--seed seed``, 0.1 s steps, collisions
reported but not acted on), runs ``warmup_s`` with the background attached to
:class:`~r1sim_sumo.sim.sumo_controller.SumoController` (the policy drives ``learned_fraction`` of the
vehicles, SUMO the rest), then inserts the ego (vType ``r1sim_ego``, 5 m x 2 m) on the route of a random
background vehicle. One env step = ``1 / policy_frequency`` s (default 0.5 s = 5 SUMO steps = one token).

Actions (``action_type``):

* ``"discrete"`` (highway-env's DiscreteMetaAction): 0 LANE_LEFT, 1 IDLE, 2 LANE_RIGHT, 3 FASTER, 4 SLOWER;
  target speed steps of ``speed_step_mps``, reached at <= ``max_accel_mps2``; lane changes by SUMO
  (``changeLane``); the ego's speed/lane-change safety checks are off (it can crash, as in highway-env).
* ``"continuous"``: ``[acceleration, steering]`` in [-1, 1] scaled to +-``max_accel_mps2`` [m/s^2] and
  +-pi/4 [rad]; a kinematic bicycle model (highway-env's) integrated at 10 Hz, placed with ``moveToXY``.

Observation (highway-env's Kinematics, ``[vehicles_observed, 5]`` float32 in [-1, 1]): rows = ego then the
nearest vehicles; features ``presence, x, y, vx, vy`` in the ego's frame (x ahead, y left) scaled by
``obs_range_m`` and 40 m/s; the ego row is ``(1, 0, 0, speed/40, 0)``; absent rows are zeros.

Reward (highway-env's highway reward): ``collision_reward * crashed + high_speed_reward * clip((v - v0) /
(v1 - v0), 0, 1) + right_lane_reward * (rightmost lane = 1 .. leftmost = 0)``, mapped linearly from
``[collision_reward, high_speed_reward + right_lane_reward]`` to [0, 1], times "on road";
``[v0, v1] = reward_speed_range`` (default ``[0.67, 1] x`` the network's speed limit). Terminated on a
crash (SAT overlap of the ego's box with any vehicle, or a SUMO collision of the ego); truncated after
``duration_s`` or when the ego reaches the end of its route.

Frames: internal (metres, x east, y north, yaw CCW from +x, box centres); SUMO through the adapters.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, fields

import gymnasium as gym
import numpy as np

from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.adapters.sumo_state import (
    KEEP_ROUTE_EXACT_XY,
    KEEP_ROUTE_SNAP,
    move_vehicle,
    read_vehicle_states,
    take_control,
)
from r1sim_sumo.geometry import boxes_overlap, wrap_angle
from r1sim_sumo.resources import network_files, network_path
from r1sim_sumo.sumo_launch import STEP_LENGTH_S as SUMO_DT_S  # [s]
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

EGO_ID = "ego"
EGO_TYPE = "r1sim_ego"
LEARNED_RGB, SUMO_RGB, EGO_RGB, CRASH_RGB = (0.63, 0.24, 0.78), (0.39, 0.78, 0.78), (0.31, 0.78, 0.31), (0.9, 0.2, 0.2)
_ACTIVE: list = []  # the SumoEgoEnv holding libsumo in this process


@dataclass
class SumoEgoConfig:
    """Options of :class:`SumoEgoEnv` (``gym.make(..., config={...})``; unknown keys are errors)."""

    checkpoint: str | None = None  # policy checkpoint; None = set_default_policy(...) or load_policy()
    sampler: str | None = None  # None = the default's ("topk:5")
    learned_fraction: float = 1.0  # share of background vehicles driven by the policy
    demand_scale: float = 1.0  # SUMO --scale: traffic density relative to the network's demand
    warmup_s: float = 20.0  # [s] background-only simulation before the ego enters
    duration_s: float = 40.0  # [s] episode length after the ego enters
    policy_frequency: int = 2  # [Hz] ego decisions per second (10 must be a multiple of it)
    action_type: str = "discrete"  # "discrete" | "continuous"
    vehicles_observed: int = 5  # rows of the observation (ego included)
    obs_range_m: float = 100.0  # [m] position scale and observation radius
    speed_step_mps: float = 5.0  # [m/s] FASTER / SLOWER
    max_accel_mps2: float = 5.0  # [m/s^2]
    collision_reward: float = -1.0
    high_speed_reward: float = 0.4
    right_lane_reward: float = 0.1
    reward_speed_range: tuple[float, float] | None = None  # [m/s]; None = (0.67, 1) x speed limit
    normalize_reward: bool = True

    @classmethod
    def from_dict(cls, d: dict | None) -> SumoEgoConfig:
        known = {f.name for f in fields(cls)}
        bad = sorted(set(d or {}) - known)
        if bad:
            raise ValueError(f"SumoEgoEnv config: unknown key(s) {bad}; valid keys are {sorted(known)}")
        cfg = cls(**(d or {}))
        if cfg.action_type not in ("discrete", "continuous"):
            raise ValueError(f"SumoEgoEnv config.action_type: got {cfg.action_type!r}, use 'discrete' or 'continuous'")
        if cfg.policy_frequency <= 0 or 10 % cfg.policy_frequency:
            raise ValueError(f"SumoEgoEnv config.policy_frequency: {cfg.policy_frequency} Hz must divide 10 Hz")
        return cfg


class SumoEgoEnv(gym.Env):
    """An RL ego among learned background traffic in bundled SUMO network ``network`` (see module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}
    ACTIONS = {0: "LANE_LEFT", 1: "IDLE", 2: "LANE_RIGHT", 3: "FASTER", 4: "SLOWER"}

    def __init__(self, network: str, config: dict | None = None, render_mode: str | None = None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"SumoEgoEnv: render_mode {render_mode!r} not supported; use 'rgb_array' or None")
        self.network = network
        self.cfg = SumoEgoConfig.from_dict(config)
        self.render_mode = render_mode
        self.files = network_files(network)
        meta = json.loads((network_path(network) / "network.json").read_text())
        self.speed_limit_mps = float(meta.get("speed_limit_mps", 30.0))
        self.reward_speed_range = self.cfg.reward_speed_range or (0.67 * self.speed_limit_mps, self.speed_limit_mps)
        self.metadata = {**self.metadata, "render_fps": self.cfg.policy_frequency}
        V = self.cfg.vehicles_observed
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (V, 5), np.float32)
        if self.cfg.action_type == "discrete":
            self.action_space = gym.spaces.Discrete(5)
        else:
            self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.conn = None
        self.controller = None
        self.crashed = False
        self._map_cache = None

    # ------------------------------------------------------------ lifecycle

    def _start_sumo(self, seed: int) -> None:
        import libsumo

        if _ACTIVE and _ACTIVE[0] is not self:
            raise RuntimeError("SumoEgoEnv: libsumo holds one simulation per process and another SumoEgoEnv is "
                               "open; close it first or run each env in its own process (SubprocVecEnv)")
        ensure_sumo_home()
        if self.conn is not None:  # the ego's last moveToXY (see settle_remote_control)
            settle_remote_control(libsumo)
            libsumo.close()
        libsumo.start(sumo_command(seed, sumocfg=self.files["sumocfg"], time_to_teleport_s=None,
                                   extra=("--scale", str(self.cfg.demand_scale))))
        self.conn = libsumo
        if not _ACTIVE:
            _ACTIVE.append(self)

    def close(self) -> None:
        if self.conn is not None:
            settle_remote_control(self.conn)  # the ego and the policy vehicles were moved with moveToXY
            self.conn.close()
            self.conn = None
        if _ACTIVE and _ACTIVE[0] is self:
            _ACTIVE.clear()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        from r1sim_sumo.sim.highway_vehicle import _DEFAULT, get_policy
        from r1sim_sumo.sim.sumo_controller import SumoController

        sumo_seed = int(self.np_random.integers(2**31 - 1))
        self._start_sumo(sumo_seed)
        c = self.conn
        frac = self.cfg.learned_fraction
        self.controller = SumoController(c, get_policy(self.cfg.checkpoint), net_file=str(self.files["net"]),
                                         control="all" if frac >= 1.0 else f"fraction={frac}",
                                         sampler=self.cfg.sampler or _DEFAULT.sampler, seed=sumo_seed,
                                         lane_changes="policy", merge_cooperation=False,
                                         speed_carry="off",
                                         junction_crossings="policy")  # as the ego-RL table was measured
        self.controller.selection = _ExcludeEgo(self.controller.selection)
        for _ in range(int(round(self.cfg.warmup_s / SUMO_DT_S))):
            self._sumo_step()
        self._insert_ego()
        self.crashed, self.time_s = False, 0.0
        self.target_speed_mps = float(c.vehicle.getSpeed(EGO_ID))
        self.ego_speed_mps = self.target_speed_mps  # continuous mode integrates its own speed
        obs = self._observe()
        return obs, self._info()

    def _sumo_step(self) -> None:
        self.conn.simulationStep()
        self.controller.step()

    def _insert_ego(self) -> None:
        c = self.conn
        others = [v for v in c.vehicle.getIDList() if v != EGO_ID]
        routes = [tuple(c.vehicle.getRoute(v)) for v in others] or [tuple(c.route.getEdges(r)) for r in c.route.getIDList()]
        if not routes:
            raise RuntimeError(f"SumoEgoEnv({self.network}): no route to put the ego on after warm-up; raise warmup_s")
        edges = routes[int(self.np_random.integers(len(routes)))]
        c.route.add("ego_route", list(edges))
        if EGO_TYPE not in c.vehicletype.getIDList():
            c.vehicletype.copy("DEFAULT_VEHTYPE", EGO_TYPE)
            c.vehicletype.setLength(EGO_TYPE, 5.0)
            c.vehicletype.setWidth(EGO_TYPE, 2.0)
            c.vehicletype.setMaxSpeed(EGO_TYPE, 40.0)
            c.vehicletype.setColor(EGO_TYPE, (80, 200, 80, 255))
        c.vehicle.add(EGO_ID, "ego_route", typeID=EGO_TYPE, departLane="best", departPos="free",
                      departSpeed="max")
        for _ in range(100):
            self._sumo_step()
            if EGO_ID in c.vehicle.getIDList():
                break
        else:
            raise RuntimeError(f"SumoEgoEnv({self.network}): the ego could not be inserted within 10 s")
        take_control(c, EGO_ID)

    # ------------------------------------------------------------ step

    def step(self, action):
        c = self.conn
        if c is None:
            raise RuntimeError("SumoEgoEnv.step called before reset")
        n_sub = 10 // self.cfg.policy_frequency
        ended = False
        if self.cfg.action_type == "discrete":
            self._discrete(int(action))
        for _ in range(n_sub):
            if self.cfg.action_type == "discrete":
                v = float(c.vehicle.getSpeed(EGO_ID))
                dv = float(np.clip(self.target_speed_mps - v, -self.cfg.max_accel_mps2 * SUMO_DT_S,
                                   self.cfg.max_accel_mps2 * SUMO_DT_S))
                c.vehicle.setSpeed(EGO_ID, max(v + dv, 0.0))
            else:
                self._continuous(np.asarray(action, np.float64))
            self._sumo_step()
            self.time_s += SUMO_DT_S
            if EGO_ID not in c.vehicle.getIDList():
                ended = True
                break
            if self._ego_collides():
                self.crashed = True
                break
        obs = self._observe() if not ended else np.zeros(self.observation_space.shape, np.float32)
        reward = self._reward(ended)
        terminated = self.crashed
        truncated = (not terminated) and (ended or self.time_s >= self.cfg.duration_s - 1e-9)
        return obs, reward, terminated, truncated, self._info()

    def _discrete(self, a: int) -> None:
        c = self.conn
        if a == 3:
            self.target_speed_mps = min(self.target_speed_mps + self.cfg.speed_step_mps, 40.0)
        elif a == 4:
            self.target_speed_mps = max(self.target_speed_mps - self.cfg.speed_step_mps, 0.0)
        elif a in (0, 2):
            lane = c.vehicle.getLaneIndex(EGO_ID)
            n = c.edge.getLaneNumber(c.vehicle.getRoadID(EGO_ID)) if lane >= 0 else 0
            target = lane + (1 if a == 0 else -1)  # SUMO lane 0 is the rightmost
            if 0 <= target < n:
                c.vehicle.changeLane(EGO_ID, target, 1.0)

    def _continuous(self, a: np.ndarray) -> None:
        """One 0.1 s step of highway-env's kinematic bicycle model, placed with moveToXY."""
        st = read_vehicle_states(self.conn, [EGO_ID])
        acc = float(np.clip(a[0], -1, 1)) * self.cfg.max_accel_mps2
        steer = float(np.clip(a[1], -1, 1)) * math.pi / 4
        beta = math.atan(0.5 * math.tan(steer))
        v, yaw = self.ego_speed_mps, float(st.yaw_rad[0])  # SUMO's speed of a moved vehicle is clipped
        x = float(st.x_m[0]) + v * math.cos(yaw + beta) * SUMO_DT_S
        y = float(st.y_m[0]) + v * math.sin(yaw + beta) * SUMO_DT_S
        yaw = float(wrap_angle(yaw + v * math.sin(beta) / (0.5 * st.length_m[0]) * SUMO_DT_S))
        v = self.ego_speed_mps = float(np.clip(v + acc * SUMO_DT_S, 0.0, 40.0))
        move_vehicle(self.conn, EGO_ID, x, y, yaw, float(st.length_m[0]), speed_mps=v,
                     keep_route=KEEP_ROUTE_SNAP | KEEP_ROUTE_EXACT_XY)

    def _ego_collides(self) -> bool:
        c = self.conn
        for col in c.simulation.getCollisions():
            if EGO_ID in (col.collider, col.victim):
                return True
        st = read_vehicle_states(c)
        e = int(np.flatnonzero(st.ids == EGO_ID)[0])
        o = np.flatnonzero(st.ids != EGO_ID)
        hit = boxes_overlap(st.x_m[e], st.y_m[e], st.yaw_rad[e], st.length_m[e], st.width_m[e],
                            st.x_m[o], st.y_m[o], st.yaw_rad[o], st.length_m[o], st.width_m[o])
        return bool(np.any(hit))

    # ------------------------------------------------------------ observation, reward

    def _observe(self) -> np.ndarray:
        st = read_vehicle_states(self.conn)
        V = self.cfg.vehicles_observed
        obs = np.zeros((V, 5), np.float32)
        e = int(np.flatnonzero(st.ids == EGO_ID)[0])
        yaw = st.yaw_rad[e]
        cs, sn = math.cos(yaw), math.sin(yaw)
        obs[0] = (1.0, 0.0, 0.0, st.speed_mps[e] / 40.0, 0.0)
        o = np.flatnonzero(st.ids != EGO_ID)
        dx, dy = st.x_m[o] - st.x_m[e], st.y_m[o] - st.y_m[e]
        d = np.hypot(dx, dy)
        near = o[np.argsort(d, kind="stable")][: V - 1]
        near = near[np.hypot(st.x_m[near] - st.x_m[e], st.y_m[near] - st.y_m[e]) <= self.cfg.obs_range_m]
        for k, j in enumerate(near, start=1):
            rx, ry = st.x_m[j] - st.x_m[e], st.y_m[j] - st.y_m[e]
            rvx, rvy = st.vx_mps[j] - st.vx_mps[e], st.vy_mps[j] - st.vy_mps[e]
            obs[k] = (1.0, (cs * rx + sn * ry) / self.cfg.obs_range_m, (-sn * rx + cs * ry) / self.cfg.obs_range_m,
                      (cs * rvx + sn * rvy) / 40.0, (-sn * rvx + cs * rvy) / 40.0)
        return np.clip(obs, -1.0, 1.0)

    def _reward(self, ended: bool) -> float:
        cfg, c = self.cfg, self.conn
        if ended:
            speed, right, on_road = self.target_speed_mps, 0.0, 1.0
        else:
            speed = float(c.vehicle.getSpeed(EGO_ID))
            if cfg.action_type == "continuous":
                speed = self.ego_speed_mps
            lane = c.vehicle.getLaneIndex(EGO_ID)
            on_road = 1.0 if lane >= 0 else 0.0
            n = c.edge.getLaneNumber(c.vehicle.getRoadID(EGO_ID)) if lane >= 0 else 1
            right = 1.0 - lane / (n - 1) if n > 1 and lane >= 0 else 1.0
        v0, v1 = self.reward_speed_range
        r = (cfg.collision_reward * float(self.crashed) + cfg.high_speed_reward * float(np.clip((speed - v0) / (v1 - v0), 0, 1))
             + cfg.right_lane_reward * right)
        if cfg.normalize_reward:
            lo, hi = cfg.collision_reward, cfg.high_speed_reward + cfg.right_lane_reward
            r = (r - lo) / (hi - lo)
        return float(r * on_road)

    def _info(self) -> dict:
        c = self.conn
        speed = float(c.vehicle.getSpeed(EGO_ID)) if EGO_ID in c.vehicle.getIDList() else 0.0
        if self.cfg.action_type == "continuous":
            speed = getattr(self, "ego_speed_mps", speed)
        return {"speed": speed, "crashed": self.crashed, "time_s": getattr(self, "time_s", 0.0),
                "controlled": len(self.controller.controlled_ids()) if self.controller else 0}

    # ------------------------------------------------------------ render

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        import matplotlib

        matplotlib.use("Agg")
        from matplotlib.figure import Figure
        from matplotlib.patches import Polygon

        from r1sim_sumo.geometry import box_corners

        if self._map_cache is None:
            self._map_cache = self.controller.map.polylines
        mp = self._map_cache
        st = read_vehicle_states(self.conn)
        fig = Figure(figsize=(6, 3), dpi=100)
        ax = fig.add_axes((0, 0, 1, 1))
        for i in range(mp.num_polylines):
            p = mp.polyline(i) if hasattr(mp, "polyline") else mp.points_m[mp.start[i]:mp.start[i + 1]]
            ax.plot(p[:, 0], p[:, 1], color="0.6" if mp.kind[i] == 0 else "0.2", lw=0.6)
        ctrl = set(self.controller.controlled_ids())
        corners = box_corners(st.x_m, st.y_m, st.yaw_rad, st.length_m, st.width_m)  # [N, 4, 2]
        for k, vid in enumerate(st.ids.tolist()):
            col = EGO_RGB if vid == EGO_ID else LEARNED_RGB if vid in ctrl else SUMO_RGB
            if vid == EGO_ID and self.crashed:
                col = CRASH_RGB
            ax.add_patch(Polygon(corners[k], closed=True, color=col))
        e = np.flatnonzero(st.ids == EGO_ID)
        cx, cy = (st.x_m[e[0]], st.y_m[e[0]]) if len(e) else (st.x_m.mean(), st.y_m.mean())
        ax.set_xlim(cx - 60, cx + 60)
        ax.set_ylim(cy - 30, cy + 30)
        ax.set_aspect("equal")
        ax.set_facecolor((0.92, 0.92, 0.92))
        ax.axis("off")
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        canvas = FigureCanvasAgg(fig)
        canvas.draw()
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()


class _ExcludeEgo:
    """SumoController selection that never hands the RL ego to the policy."""

    def __init__(self, inner):
        self.inner = inner
        self.kind = inner.kind

    def selects(self, veh_id: str, type_id: str) -> bool:
        return veh_id != EGO_ID and self.inner.selects(veh_id, type_id)
