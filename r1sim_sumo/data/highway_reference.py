"""Reference scenarios recorded from highway-env's IDM/MOBIL traffic.

One episode = ``env.reset(seed=episode_seed)`` then ``round(episode_s / 0.1)`` steps of 0.1 s
(``simulation_frequency = policy_frequency = 10``: one ``env.step`` = one simulator step), recording every
vehicle at 10 Hz (step 0 = the state right after the reset). Overlapping windows of 91 states
(11 history + 80 future, current index 10) start every ``stride_steps`` steps and become
:class:`~r1sim_sumo.scenario.Scenario` objects holding the agents valid at the current index.

Choices, all deterministic for a seed:

* **The ego** (highway-env's controlled MDPVehicle) is replaced right after the reset by a copy of the
  background class (``config["other_vehicles_type"]``, IDMVehicle by default) built with
  ``create_from`` (same position, speed, route, target speed), so it drives with IDM/MOBIL like every other
  vehicle and is recorded as one of them. The env is stepped with ``action=None`` through
  ``env.unwrapped.step``, which never applies an ego action and ignores ``terminated``/``truncated``: an
  episode always runs to its end.
* **Crashes**: a vehicle whose ``crashed`` flag is set is recorded at that step and then removed from the
  road (highway-env would otherwise leave a wreck braking on the lane). A window is dropped when one of its
  agents (those valid at the current index) crashes inside it, so no scenario holds a crashed agent.
  (IDM/MOBIL crash often at intersection-v0's unsignalised junction, about every 5 s with default
  traffic; dropping every window that saw any crash anywhere would leave almost none.)
* **Speed**: the unused observation is switched off (``observation_type.observe`` returns None on the
  unwrapped env; highway-env would build a pandas frame every step).
* **Validity**: a vehicle is valid at a step when it is in ``road.vehicles`` and ``vehicle.on_road`` (its
  centre is on its current lane, with highway-env's 5 m margin past lane ends). Vehicles spawned or removed
  by the env (intersection-v0) and vehicles driving off a dead-end lane (merge-v0, the ego of
  intersection-v0 after its exit) thus appear and disappear through the valid mask.
* **Episode seeds**: episode ``k`` resets with ``SeedSequence([seed, k])``'s first 32-bit word, so any episode
  can be re-run alone; it is stored as ``episode_seed`` in the metadata.
* **Map**: read once per episode with :func:`read_highway_map`, cropped to the box around every recorded
  position plus ``MAP_MARGIN_M`` (highway-v0's lanes are 10 km long); all windows of an episode share it.
* intersection-v0 overwrites class attributes of the background vehicle class (``DISTANCE_WANTED``,
  ``COMFORT_ACC_MAX``, ``COMFORT_ACC_MIN``) on every reset; they are restored when generation ends so that a
  later run on another env in the same process is unaffected.
"""

from __future__ import annotations

import contextlib
import warnings

import numpy as np

from r1sim_sumo.adapters.highway_map import read_highway_map
from r1sim_sumo.adapters.highway_state import assign_vehicle_id, read_highway_vehicles
from r1sim_sumo.scenario import CURRENT_INDEX, DT_S, N_WINDOW_10HZ, AgentTracks, Scenario

GENERATOR_VERSION = "highway-reference/1"
SUPPORTED_ENVS = ("highway-v0", "merge-v0", "roundabout-v0", "intersection-v0")
SIM_FREQUENCY_HZ = 10  # one env.step = 1 / 10 s
MAP_MARGIN_M = 60.0  # map crop margin around all recorded positions [m]
MAP_STEP_M = 1.0  # lane sampling step [m]
# class attributes intersection-v0 overwrites on the background vehicle class at every reset
_MUTATED_CLASS_ATTRS = ("DISTANCE_WANTED", "COMFORT_ACC_MAX", "COMFORT_ACC_MIN")


def episode_seed(seed: int, episode: int) -> int:
    """Reset seed of episode ``episode`` of a run with ``seed`` (independent streams per episode)."""
    return int(np.random.SeedSequence([int(seed), int(episode)]).generate_state(1)[0])


def _env_config(default_config: dict, env_name: str, episode_s: float, vehicles_count: int | None) -> dict:
    cfg = {
        "simulation_frequency": SIM_FREQUENCY_HZ,
        "policy_frequency": SIM_FREQUENCY_HZ,
        "duration": float(episode_s),
        "offroad_terminal": False,
        # the observation is not used: keep it as cheap as highway-env allows
        "observation": {
            "type": "Kinematics",
            "vehicles_count": 1,
            "features": ["presence"],
            "normalize": False,
        },
    }
    if vehicles_count is not None:
        if "vehicles_count" in default_config:
            cfg["vehicles_count"] = int(vehicles_count)
        elif "initial_vehicle_count" in default_config:
            cfg["initial_vehicle_count"] = int(vehicles_count)
        else:
            warnings.warn(
                f"generate_highway_scenarios: {env_name} has no vehicle-count setting (its traffic layout is "
                f"fixed by highway-env); vehicles_count={vehicles_count} is ignored",
                stacklevel=3,
            )
    return cfg


@contextlib.contextmanager
def _restore_class_attrs(cls, names):
    saved = {n: cls.__dict__[n] for n in names if n in cls.__dict__}
    try:
        yield
    finally:
        for n in names:
            if n in saved:
                setattr(cls, n, saved[n])
            elif n in cls.__dict__:
                delattr(cls, n)


def _make_ego_background(env) -> None:
    """Replace every controlled vehicle by a background-class (IDM/MOBIL) copy at the same state."""
    from highway_env.utils import class_from_path

    cls = class_from_path(env.config["other_vehicles_type"])
    road = env.road
    for k, ego in enumerate(list(env.controlled_vehicles)):
        new = cls.create_from(ego)
        assign_vehicle_id(road, new, assign_vehicle_id(road, ego))
        if ego in road.vehicles:
            road.vehicles[road.vehicles.index(ego)] = new
        env.controlled_vehicles[k] = new


def _no_observation():
    return None


def _record_episode(env, n_steps: int, pbar=None) -> tuple[AgentTracks, np.ndarray]:
    """Step ``env`` (unwrapped, already reset) ``n_steps`` times.

    :return: tracks ``[A, n_steps + 1]`` and crash flags ``[A, n_steps + 1]`` (True at the step a vehicle
        is recorded crashed; it is removed from the road right after).
    """
    T = n_steps + 1
    rows: dict[str, int] = {}
    static: list[tuple[float, float]] = []  # (length, width) per agent row
    per_step: list[tuple[np.ndarray, object]] = []  # (rows of the vehicles, their states) per step
    for t in range(T):
        if t > 0:
            env.step(None)
            if pbar is not None:
                pbar.update(1)
        st = read_highway_vehicles(env.road)
        for vid, length, width in zip(st.ids.tolist(), st.length_m, st.width_m, strict=True):
            if vid not in rows:
                rows[vid] = len(rows)
                static.append((float(length), float(width)))
        per_step.append((np.array([rows[v] for v in st.ids.tolist()], np.int64), st))
        if st.crashed.any():
            env.road.vehicles = [v for v in env.road.vehicles if not v.crashed]
    tracks = AgentTracks.empty(len(rows), T)
    tracks.ids = np.array(list(rows), dtype=str) if rows else np.zeros(0, "<U1")
    tracks.length_m = np.array([s[0] for s in static], np.float32).reshape(-1)
    tracks.width_m = np.array([s[1] for s in static], np.float32).reshape(-1)
    crashed = np.zeros((len(rows), T), bool)  # [A, T]
    for t, (r, st) in enumerate(per_step):
        ok = st.on_road  # [N] vehicles off their lane (past a dead end) are not recorded
        r = r[ok]
        for f in AgentTracks.PER_STEP:
            getattr(tracks, f)[r, t] = getattr(st, f)[ok]
        tracks.valid[r, t] = True
        crashed[r, t] = st.crashed[ok]
    return tracks, crashed


def _windows(
    tracks: AgentTracks, crashed: np.ndarray, stride_steps: int, episode_map, metadata: dict
) -> tuple[list[Scenario], int]:
    """Cut 91-step windows every ``stride_steps``, keeping the agents valid at the current index.

    Windows with no current agent, or in which a kept agent crashes (``crashed`` ``[A, T]``), are dropped.
    :return: scenarios and the number of windows dropped for a crash.
    """
    out: list[Scenario] = []
    dropped_crash = 0
    T = tracks.num_steps
    for start in range(0, T - N_WINDOW_10HZ + 1, stride_steps):
        stop = start + N_WINDOW_10HZ
        w = tracks.slice_steps(start, stop)
        keep = w.valid[:, CURRENT_INDEX]  # [A] only agents present "now"
        if not keep.any():
            continue
        if crashed[keep, start:stop].any():
            dropped_crash += 1
            continue
        sc = Scenario(
            agents=w.select(keep).astype_canonical(),
            map=episode_map,
            metadata={**metadata, "start_step": int(start), "start_time_s": round(start * DT_S, 3)},
        )
        out.append(
            sc.validate(
                source=f"highway-env {metadata['network']} episode {metadata['episode']} step {start}"
            )
        )
    return out, dropped_crash


def generate_highway_scenarios(
    env_name: str,
    seed: int,
    n_episodes: int = 1,
    episode_s: float = 40.0,
    stride_steps: int = 20,
    vehicles_count: int | None = None,
    progress: bool = True,
) -> list[Scenario]:
    """Record IDM/MOBIL traffic on a highway-env env and slice it into 91-step scenarios.

    :param env_name: one of ``SUPPORTED_ENVS`` (highway-v0, merge-v0, roundabout-v0, intersection-v0).
    :param seed: run seed; episode ``k`` resets with :func:`episode_seed` ``(seed, k)``.
    :param n_episodes: number of episodes (>= 1).
    :param episode_s: simulated time per episode [s], at least 9.0 (one 91-state window).
    :param stride_steps: steps (0.1 s each) between consecutive window starts, >= 1.
    :param vehicles_count: background vehicles (highway-v0 ``vehicles_count``, intersection-v0
        ``initial_vehicle_count``); ``None`` keeps the env's default; ignored with a warning elsewhere.
    :param progress: show a tqdm bar over simulated steps.
    :return: validated scenarios with metadata ``source, network, seed, generator_version, episode,
        episode_seed, start_step, start_time_s``.
    """
    if env_name not in SUPPORTED_ENVS:
        raise ValueError(
            f"generate_highway_scenarios: env_name '{env_name}' unsupported; choose one of {SUPPORTED_ENVS}"
        )
    n_steps = int(round(float(episode_s) / DT_S))
    if n_steps + 1 < N_WINDOW_10HZ:
        raise ValueError(
            f"generate_highway_scenarios: episode_s={episode_s} s is shorter than one window "
            f"({(N_WINDOW_10HZ - 1) * DT_S:.1f} s = {N_WINDOW_10HZ} states); raise episode_s"
        )
    if n_episodes < 1 or stride_steps < 1:
        raise ValueError(
            f"generate_highway_scenarios: n_episodes ({n_episodes}) and stride_steps ({stride_steps}) must be >= 1"
        )

    import gymnasium
    import highway_env  # noqa: F401  (registers the envs)
    from highway_env.utils import class_from_path

    env = gymnasium.make(env_name)
    u = env.unwrapped
    u.configure(_env_config(u.default_config(), env_name, episode_s, vehicles_count))
    background_cls = class_from_path(u.config["other_vehicles_type"])
    pbar = None
    if progress:
        from tqdm import tqdm

        pbar = tqdm(total=n_episodes * n_steps, desc=f"{env_name} seed {seed}", unit="step")
    scenarios: list[Scenario] = []
    try:
        with _restore_class_attrs(background_cls, _MUTATED_CLASS_ATTRS):
            for ep in range(n_episodes):
                es = episode_seed(seed, ep)
                u.reset(seed=es)
                _make_ego_background(u)
                # the observation is never used; highway-env builds a pandas frame for it every step (~12 %)
                u.observation_type.observe = _no_observation
                tracks, crashed = _record_episode(u, n_steps, pbar)
                if tracks.num_agents == 0 or not tracks.valid.any():
                    continue
                xy = np.stack([tracks.x_m[tracks.valid], tracks.y_m[tracks.valid]], axis=1)  # [V, 2]
                lo, hi = xy.min(axis=0) - MAP_MARGIN_M, xy.max(axis=0) + MAP_MARGIN_M
                hmap = read_highway_map(u.road.network, MAP_STEP_M, bounds_m=(lo[0], lo[1], hi[0], hi[1]))
                meta = {
                    "source": "highway-env",
                    "network": env_name,
                    "seed": int(seed),
                    "generator_version": GENERATOR_VERSION,
                    "episode": ep,
                    "episode_seed": es,
                }
                windows, _ = _windows(tracks, crashed, stride_steps, hmap.polylines, meta)
                scenarios.extend(windows)
    finally:
        if pbar is not None:
            pbar.close()
        env.close()
    return scenarios
