"""Realism metrics (Waymo Open Sim Agents Challenge style) computed locally on our scenarios.

``compute_realism(scenario, SimTrajectories(...)) -> RealismResult`` and ``aggregate(results)``; the feature
code lives in :mod:`.kinematics`, :mod:`.collisions` (SAT collisions, box distance, TTC) and
:mod:`.map_features` (drivable area, road-edge distance, offroad, red-light violations).
"""

from r1sim_sumo.metrics.collisions import (
    collision_flags,
    distance_to_nearest_object,
    interaction_features,
    time_to_collision,
)
from r1sim_sumo.metrics.kinematics import kinematic_features
from r1sim_sumo.metrics.map_features import distance_to_road_edge, drivable_area, offroad_flags
from r1sim_sumo.metrics.realism import FEATURES, RealismConfig, aggregate, compute_features, compute_realism
from r1sim_sumo.metrics.types import MetricsInputError, RealismResult, SimTrajectories

__all__ = [
    "FEATURES", "MetricsInputError", "RealismConfig", "RealismResult", "SimTrajectories", "aggregate", "collision_flags",
    "compute_features", "compute_realism", "distance_to_nearest_object", "distance_to_road_edge",
    "drivable_area", "interaction_features", "kinematic_features", "offroad_flags", "time_to_collision",
]
