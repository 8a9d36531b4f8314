"""r1sim gymnasium envs: env checkers, rendering, learned-vehicle control, collisions, seeding, SB3 smoke.

An untrained nano policy (synthetic vocabulary) is installed with ``set_default_policy``: no checkpoint needed.
Its motion is random, so learned vehicles often leave the road; the coordinator must then hand them back
to IDM (default) or remove them, which is what the off-road test checks.
"""

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch

pytestmark = pytest.mark.highway

HIGHWAY_IDS = ["r1sim/highway-v0", "r1sim/merge-v0", "r1sim/roundabout-v0", "r1sim/intersection-v0"]
SMALL = {"r1sim/highway-v0": {"vehicles_count": 8},
         "r1sim/intersection-v0": {"initial_vehicle_count": 4, "spawn_probability": 0.3}}
SUMO_FAST = {"warmup_s": 2.0, "duration_s": 3.0}


@pytest.fixture(scope="module", autouse=True)
def policy():
    torch.set_num_threads(1)
    from r1sim_sumo.model.untrained import untrained_policy
    from r1sim_sumo.sim.highway_vehicle import set_default_policy

    set_default_policy(untrained_policy(), sampler="topk:5", seed=None)
    yield
    set_default_policy(None)


def _make(env_id, **kw):
    import r1sim_sumo.envs  # noqa: F401

    return gym.make(env_id, config={**SMALL.get(env_id, {}), **kw.pop("config", {})}, **kw)


def test_register_is_idempotent_and_lists_sumo_networks():
    from gymnasium.envs.registration import registry

    from r1sim_sumo.envs import register_envs, sumo_env_id
    from r1sim_sumo.resources import list_networks

    ids = register_envs()
    assert register_envs() == ids
    for env_id in HIGHWAY_IDS + [sumo_env_id(n) for n in list_networks()]:
        assert env_id in registry


@pytest.mark.parametrize("env_id", HIGHWAY_IDS)
def test_env_checkers_and_render(env_id):
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    env = _make(env_id, render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gym_check(env.unwrapped, skip_render_check=True)
        sb3_check(env.unwrapped, warn=False)
    env.reset(seed=1)
    env.step(env.action_space.sample())
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.std() > 5  # not blank
    # learned vehicles are drawn purple
    from highway_env.vehicle.graphics import VehicleGraphics

    from r1sim_sumo.sim.highway_vehicle import LEARNED_COLOR, LearnedVehicle

    learned = [v for v in env.unwrapped.road.vehicles if isinstance(v, LearnedVehicle) and v.learned and not v.crashed]
    assert all(VehicleGraphics.get_color(v) == LEARNED_COLOR for v in learned)
    env.close()


def test_learned_vehicles_stay_on_road_or_are_handed_to_idm():
    from r1sim_sumo.sim.highway_vehicle import LearnedVehicle, coordinator_of

    env = _make("r1sim/highway-v0", config={"vehicles_count": 15, "duration": 100})
    env.reset(seed=3)
    coord = coordinator_of(env.unwrapped.road)
    for _ in range(30):
        env.unwrapped.vehicle.crashed = False
        env.step(1)
        for v in env.unwrapped.road.vehicles:
            if isinstance(v, LearnedVehicle) and v.policy_controlled:
                s, lat = v.lane.local_coordinates(v.position)
                assert v.lane.on_lane(v.position, s, lat, margin=coord.config.offroad_margin_m)
    assert coord.stats.plan_calls >= 1
    handed = [v for v in env.unwrapped.road.vehicles if isinstance(v, LearnedVehicle) and not v.learned]
    assert len(handed) == coord.stats.handed_to_idm  # off-road ones became IDM vehicles
    env.close()

    env = _make("r1sim/highway-v0", config={"vehicles_count": 15, "duration": 100, "offroad": "remove"})
    env.reset(seed=3)
    n0 = len(env.unwrapped.road.vehicles)
    for _ in range(20):
        env.unwrapped.vehicle.crashed = False
        env.step(1)
    coord = coordinator_of(env.unwrapped.road)
    assert len(env.unwrapped.road.vehicles) == n0 - coord.stats.removed
    env.close()


def test_spawned_vehicles_get_controlled():
    from r1sim_sumo.sim.highway_vehicle import LearnedVehicle

    env = _make("r1sim/intersection-v0", config={"spawn_probability": 1.0, "duration": 30})
    env.reset(seed=0)
    initial = {id(v) for v in env.unwrapped.road.vehicles}
    spawned_planned = 0
    for _ in range(12):
        _, _, term, trunc, _ = env.step(1)
        for v in env.unwrapped.road.vehicles:
            if id(v) not in initial and isinstance(v, LearnedVehicle) and v.plan is not None:
                spawned_planned += 1
        if term or trunc:
            break
    assert spawned_planned > 0
    env.close()


def test_collision_with_learned_vehicle_ends_the_episode():
    from r1sim_sumo.sim.highway_vehicle import LearnedVehicle

    env = _make("r1sim/highway-v0")
    env.reset(seed=0)
    ego = env.unwrapped.vehicle
    blocker = LearnedVehicle(env.unwrapped.road, ego.position + np.array([4.0, 0.0]), ego.heading, 0.0)
    env.unwrapped.road.vehicles.append(blocker)
    _, _, terminated, _, info = env.step(1)
    assert terminated and info["crashed"] and blocker.crashed
    env.close()


def test_seeding_reproduces_episodes():
    def rollout(seed):
        env = _make("r1sim/highway-v0")
        obs = [env.reset(seed=seed)[0]]
        for a in [1, 3, 0, 1, 4, 2]:
            o, _, term, trunc, _ = env.step(a)
            obs.append(o)
            if term or trunc:
                break
        env.close()
        return np.stack(obs)

    a, b, c = rollout(7), rollout(7), rollout(8)
    np.testing.assert_array_equal(a, b)
    assert a.shape != c.shape or not np.array_equal(a, c)


@pytest.mark.sumo
@pytest.mark.parametrize("network", ["lane_drop", pytest.param("all", marks=pytest.mark.slow)])
def test_sumo_envs_check_and_render(network):
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    from r1sim_sumo.envs import sumo_env_id
    from r1sim_sumo.resources import list_networks

    for net in list_networks() if network == "all" else [network]:
        env = _make(sumo_env_id(net), config=SUMO_FAST, render_mode="rgb_array")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gym_check(env.unwrapped, skip_render_check=True)
            sb3_check(env.unwrapped, warn=False)
        o1, _ = env.reset(seed=5)
        o2, _ = env.reset(seed=5)
        np.testing.assert_array_equal(o1, o2)
        # the background traffic's junction handling as the ego-RL table was measured (not the drop-in's later default)
        assert env.unwrapped.controller.junction_crossings == "policy"
        frame = env.render()
        assert frame.shape[2] == 3 and frame.std() > 5
        env.close()


@pytest.mark.sumo
def test_sumo_continuous_ego_moves():
    from r1sim_sumo.envs import sumo_env_id

    env = _make(sumo_env_id("lane_drop"), config={**SUMO_FAST, "action_type": "continuous"})
    env.reset(seed=0)
    speeds = [env.step(np.array([1.0, 0.0], np.float32))[4]["speed"] for _ in range(4)]
    assert speeds[-1] > speeds[0]  # full throttle accelerates
    env.close()


@pytest.mark.sumo
def test_sb3_ppo_trains_on_highway_and_sumo():
    from stable_baselines3 import PPO

    from r1sim_sumo.envs import sumo_env_id

    for env_id, cfg in [("r1sim/highway-v0", {}), (sumo_env_id("lane_drop"), SUMO_FAST)]:
        env = _make(env_id, config=cfg)
        model = PPO("MlpPolicy", env, n_steps=64, batch_size=32, n_epochs=1, seed=0, device="cpu", verbose=0)
        model.learn(total_timesteps=128)
        assert model.num_timesteps >= 128
        env.close()


class _FastStraightDriver:
    """Stand-in for the policy: every vehicle drives straight on at >= 35 m/s (ignores what is ahead)."""

    def plan(self, history, tl_state=None):
        from r1sim_sumo.sim.policy_driver import Plan

        x0, y0, yaw = history.x_m[:, -1], history.y_m[:, -1], history.yaw_rad[:, -1]
        v = np.maximum(history.speed_mps[:, -1], 35.0)
        t = np.arange(6) * 0.1
        xy = np.stack([x0[:, None] + v[:, None] * t * np.cos(yaw)[:, None], y0[:, None] + v[:, None] * t * np.sin(yaw)[:, None]], -1)
        n = len(x0)
        return Plan(xy, np.repeat(yaw[:, None], 6, 1), np.repeat(v[:, None], 5, 1).astype(np.float32),
                    np.zeros(n, np.int64), np.zeros(n, np.float32), history.valid[:, -1].copy())


@pytest.mark.parametrize("safety", ["krauss", "none"])
def test_safety_filter_keeps_learned_vehicles_off_the_ego(safety):
    from r1sim_sumo.sim.highway_vehicle import LearnedVehicle, coordinator_of

    env = _make("r1sim/highway-v0", config={"vehicles_count": 0, "safety": safety, "duration": 20})
    env.reset(seed=0)
    ego = env.unwrapped.vehicle
    chaser = LearnedVehicle(env.unwrapped.road, ego.position - np.array([30.0, 0.0]), ego.heading, 35.0)
    env.unwrapped.road.vehicles.append(chaser)
    coordinator_of(env.unwrapped.road)._driver = _FastStraightDriver()
    crashed = False
    for _ in range(10):  # 10 s: without the filter the chaser closes the 30 m gap in about 3 s
        _, _, terminated, _, info = env.step(1)  # IDLE
        crashed |= bool(info["crashed"])
        if terminated:
            break
    slowdowns = coordinator_of(env.unwrapped.road).stats.safety_slowdowns
    env.close()
    if safety == "krauss":
        assert not crashed and slowdowns > 0 and chaser.position[0] < ego.position[0]
    else:
        assert crashed and slowdowns == 0


def test_highway_vehicles_pass_their_target_speed_as_desired_speed():
    """The policy's desired-speed input gets each highway-env vehicle's target_speed (IDM / learned vehicles)."""
    from r1sim_sumo.sim.highway_vehicle import coordinator_of

    env = _make("r1sim/highway-v0", config={"vehicles_count": 8, "duration": 100})
    env.reset(seed=1)
    env.step(1)
    coord = coordinator_of(env.unwrapped.road)
    vehicles = list(env.unwrapped.road.vehicles)
    tr = coord._tracks(vehicles)  # noqa: SLF001
    want = np.array([v.target_speed for v in vehicles], np.float32)
    np.testing.assert_allclose(tr.desired_speed_mps, want)
    assert np.isfinite(want).all() and want.min() > 10.0
    env.close()


@pytest.mark.parametrize("env_id", HIGHWAY_IDS + ["r1sim/racetrack-v0"])
def test_env_config_reaches_the_learned_traffic(env_id):
    """Every highway-env env hands its config to the road's coordinator, whichever method builds its road
    (highway-v0: _create_road; merge, roundabout, intersection, racetrack: _make_road): with learned_fraction 0 no
    vehicle is planned by the policy (merge / roundabout / intersection / racetrack ignored it before session 57)."""
    from r1sim_sumo.sim.highway_vehicle import COORDINATOR_ATTR

    env = _make(env_id, config={"learned_fraction": 0.0, "safety": "none", "offroad": "remove", "sampler": "greedy",
                                "speed_carry": "gains"})
    env.reset(seed=0)
    for _ in range(3):
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            break
    coord = getattr(env.unwrapped.road, COORDINATOR_ATTR)
    cfg = coord.config
    assert (cfg.learned_fraction, cfg.safety, cfg.offroad, cfg.sampler) == (0.0, "none", "remove", "greedy")
    assert cfg.speed_carry == "gains" and coord.driver.speed_carry == "gains"
    assert coord.safety is None and coord.stats.plan_calls == 0
    env.close()

