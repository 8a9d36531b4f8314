"""Gymnasium environments for ego RL against learned traffic; registered on ``import r1sim_sumo.envs``.

==========================  ===============================================  ================================
id                          base                                             background
==========================  ===============================================  ================================
``r1sim/highway-v0``        highway-env ``HighwayEnv`` (highway-v0)          :class:`LearnedVehicle`
``r1sim/merge-v0``          highway-env ``MergeEnv`` (merge-v0)              :class:`LearnedVehicle`
``r1sim/roundabout-v0``     highway-env ``RoundaboutEnv`` (roundabout-v0)    :class:`LearnedVehicle`
``r1sim/intersection-v0``   highway-env ``IntersectionEnv`` (intersection-v0) :class:`LearnedVehicle`
``r1sim/racetrack-v0``      highway-env ``RacetrackEnv`` (racetrack-v0)      :class:`LearnedVehicle`
``r1sim/sumo-<net>-v0``     :class:`r1sim_sumo.sim.sumo_ego_env.SumoEgoEnv`  the policy, in SUMO (libsumo)
==========================  ===============================================  ================================

The highway-env ones keep highway-env's observation, action and reward configs; only these keys change or
are added (``gym.make(id, config={...})``)::

    other_vehicles_type   "r1sim_sumo.sim.highway_vehicle.LearnedVehicle"
    simulation_frequency  10   # [Hz] 10 Hz states
    policy_frequency      2    # [Hz] one ego action per 0.5 s motion token
    checkpoint            None # policy checkpoint (name or path); None = set_default_policy(...) or load_policy()
    sampler               None # sampler spec ("topk:5", "entropy:16,80", "greedy"); None = the default's
    policy_seed           None # sampler seed; None = from the env seed (reset(seed=...) reproduces episodes)
    learned_fraction      1.0  # share of background vehicles driven by the policy (the rest IDM/MOBIL)
    offroad               "idm" # learned vehicles leaving the road: "idm" (hand back to IDM) or "remove"

``vehicles_count`` / ``vehicles_density`` are highway-env's own. The baseline "IDM traffic" is highway-env's
env with the same frequencies (or ``learned_fraction=0``).

``r1sim/sumo-<net>-v0`` exist for every bundled network (:func:`r1sim_sumo.resources.list_networks`); see
:mod:`r1sim_sumo.sim.sumo_ego_env` (libsumo: ONE SUMO env per process).

Gymnasium 1.x has no plugin entry point for environments (``gymnasium.envs`` entry points were dropped),
so registration happens on import of this module, or with ``gym.make("r1sim_sumo.envs:r1sim/highway-v0")``.
"""

from __future__ import annotations

from highway_env.envs.highway_env import HighwayEnv
from highway_env.envs.intersection_env import IntersectionEnv
from highway_env.envs.merge_env import MergeEnv
from highway_env.envs.racetrack_env import RacetrackEnv
from highway_env.envs.roundabout_env import RoundaboutEnv
from highway_env.vehicle.behavior import IDMVehicle

from r1sim_sumo.sim.highway_vehicle import LearnedTrafficConfig, LearnedTrafficCoordinator, LearnedVehicle

LEARNED_VEHICLE_PATH = "r1sim_sumo.sim.highway_vehicle.LearnedVehicle"
NAMESPACE = "r1sim"

LEARNED_TRAFFIC_DEFAULTS = {
    "other_vehicles_type": LEARNED_VEHICLE_PATH,
    "simulation_frequency": 10,  # [Hz]
    "policy_frequency": 2,  # [Hz]
    "checkpoint": None,
    "sampler": None,
    "policy_seed": None,
    "learned_fraction": 1.0,
    "offroad": "idm",
    "safety": "krauss",  # learned vehicles never faster than a safe following speed; "none" = raw policy
    "speed_carry": "off",  # "gains": keep the speed-ups a token's end pose gives back (the SUMO drop-in's default)
}


class LearnedTrafficMixin:
    """Adds learned background traffic to a highway-env env (put it first in the bases)."""

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(LEARNED_TRAFFIC_DEFAULTS)
        return config

    def _traffic_config(self) -> LearnedTrafficConfig:
        c = self.config
        return LearnedTrafficConfig(checkpoint=c["checkpoint"], sampler=c["sampler"], seed=c["policy_seed"],
                                    learned_fraction=float(c["learned_fraction"]), offroad=c["offroad"],
                                    safety=c.get("safety", "krauss"), speed_carry=c.get("speed_carry", "off"))

    def _create_road(self) -> None:  # highway-v0 builds its road here
        super()._create_road()
        LearnedTrafficCoordinator.for_road(self.road, self._traffic_config())

    def _make_road(self) -> None:
        """merge / roundabout / intersection / racetrack build their road here. Without this override (before session
        57) their coordinator was created on the first learned vehicle's step with the default options: the env's
        ``learned_fraction``, ``checkpoint``, ``sampler``, ``policy_seed``, ``offroad`` and ``safety`` were ignored."""
        super()._make_road()
        LearnedTrafficCoordinator.for_road(self.road, self._traffic_config())

    def _reset(self) -> None:
        super()._reset()
        if self.config["other_vehicles_type"] != LEARNED_VEHICLE_PATH:
            return
        # envs that build IDMVehicle directly (racetrack) get learned vehicles in their place
        for i, v in enumerate(self.road.vehicles):
            if type(v) is IDMVehicle and v not in self.controlled_vehicles:
                nv = LearnedVehicle.create_from(v)
                nv.target_speed, nv.route = v.target_speed, v.route
                self.road.vehicles[i] = nv


class LearnedHighwayEnv(LearnedTrafficMixin, HighwayEnv):
    """highway-v0 with learned background traffic."""


class LearnedMergeEnv(LearnedTrafficMixin, MergeEnv):
    """merge-v0 with learned background traffic."""


class LearnedRoundaboutEnv(LearnedTrafficMixin, RoundaboutEnv):
    """roundabout-v0 with learned background traffic."""


class LearnedIntersectionEnv(LearnedTrafficMixin, IntersectionEnv):
    """intersection-v0 with learned background traffic (vehicles spawned mid-episode are learned too)."""


class LearnedRacetrackEnv(LearnedTrafficMixin, RacetrackEnv):
    """racetrack-v0 with learned background traffic."""


HIGHWAY_ENVS = {
    f"{NAMESPACE}/highway-v0": "r1sim_sumo.envs:LearnedHighwayEnv",
    f"{NAMESPACE}/merge-v0": "r1sim_sumo.envs:LearnedMergeEnv",
    f"{NAMESPACE}/roundabout-v0": "r1sim_sumo.envs:LearnedRoundaboutEnv",
    f"{NAMESPACE}/intersection-v0": "r1sim_sumo.envs:LearnedIntersectionEnv",
    f"{NAMESPACE}/racetrack-v0": "r1sim_sumo.envs:LearnedRacetrackEnv",
}


def sumo_env_id(network: str) -> str:
    """Gymnasium id of the SUMO ego env on bundled network ``network``."""
    return f"{NAMESPACE}/sumo-{network}-v0"


def register_envs() -> list[str]:
    """Register every r1sim env with gymnasium (idempotent); returns the ids."""
    from gymnasium.envs.registration import register, registry

    from r1sim_sumo.resources import list_networks

    ids = []
    for env_id, entry in HIGHWAY_ENVS.items():
        if env_id not in registry:
            register(id=env_id, entry_point=entry)
        ids.append(env_id)
    for net in list_networks():
        env_id = sumo_env_id(net)
        if env_id not in registry:
            register(id=env_id, entry_point="r1sim_sumo.sim.sumo_ego_env:SumoEgoEnv", kwargs={"network": net},
                     max_episode_steps=None)
        ids.append(env_id)
    return ids


ENV_IDS = register_envs()
