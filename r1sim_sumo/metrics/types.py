"""Typed inputs and outputs of the realism metrics (WOSAC-style, computed locally on our scenarios).

Frame: internal (metres, x east, y north, yaw radians CCW from +x, positions = box centres), 10 Hz.
Simulated rollouts cover the *future* steps of a scenario only: step ``t`` of a rollout is scenario step
``current_index + 1 + t`` (80 steps for standard 11 + 80 windows).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from r1sim_sumo.scenario import Scenario


class MetricsInputError(ValueError):
    """Simulated trajectories do not fit the scenario they are scored against (message names field + fix)."""


def _to_numpy(a, dtype) -> np.ndarray:
    if hasattr(a, "detach"):  # torch tensor
        a = a.detach().cpu().numpy()
    return np.asarray(a, dtype=dtype)


@dataclass(frozen=True)
class SimTrajectories:
    """``R`` simulated rollouts of the scenario's ``A`` agents (same agents, same order) over the future.

    :param x_m, y_m: ``[R, A, T]`` box centre [m], internal frame; ``T`` future steps at 10 Hz.
    :param yaw_rad: ``[R, A, T]`` heading [rad, CCW from east].
    :param valid: ``[R, A, T]`` or ``[A, T]`` bool, the agent exists in that rollout at that step;
        ``None`` = the scenario's logged future validity for every rollout.
    numpy arrays or torch tensors are accepted (converted to numpy by :meth:`checked`).
    """

    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    valid: np.ndarray | None = None

    @property
    def num_rollouts(self) -> int:
        return int(np.shape(self.x_m)[0])

    @property
    def num_steps(self) -> int:
        return int(np.shape(self.x_m)[2])

    @classmethod
    def log_replay(cls, scenario: Scenario, num_rollouts: int = 1, num_steps: int | None = None) -> SimTrajectories:
        """The scenario's logged future replicated ``num_rollouts`` times (the realism upper reference)."""
        ci = scenario.current_index
        T = scenario.num_steps - ci - 1 if num_steps is None else num_steps
        a = scenario.agents
        rep = lambda f: np.repeat(np.asarray(getattr(a, f))[None, :, ci + 1 : ci + 1 + T], num_rollouts, 0)  # noqa: E731
        return cls(x_m=rep("x_m"), y_m=rep("y_m"), yaw_rad=rep("yaw_rad"), valid=rep("valid"))

    def checked(self, scenario: Scenario) -> SimTrajectories:
        """Return a copy as float64/bool numpy with ``valid`` ``[R, A, T]``, after checking it fits ``scenario``.

        Raises :class:`MetricsInputError` naming the field and the expected shape.
        """
        x = _to_numpy(self.x_m, np.float64)
        y = _to_numpy(self.y_m, np.float64)
        yaw = _to_numpy(self.yaw_rad, np.float64)
        if x.ndim != 3:
            raise MetricsInputError(f"SimTrajectories.x_m: expected shape [R, A, T], got {x.shape}")
        R, A, T = x.shape
        for name, arr in (("y_m", y), ("yaw_rad", yaw)):
            if arr.shape != x.shape:
                raise MetricsInputError(f"SimTrajectories.{name}: expected shape {x.shape} like x_m, got {arr.shape}")
        if A != scenario.agents.num_agents:
            raise MetricsInputError(
                f"SimTrajectories.x_m: {A} agents but the scenario has {scenario.agents.num_agents}; pass every "
                "scenario agent in the scenario's order (invalid ones with valid=False)"
            )
        ci = scenario.current_index
        if ci + 1 + T > scenario.num_steps:
            raise MetricsInputError(
                f"SimTrajectories.x_m: {T} future steps but the scenario has only {scenario.num_steps - ci - 1} "
                f"after current_index {ci}; cut the rollouts to the scenario's future"
            )
        if self.valid is None:
            v = np.broadcast_to(np.asarray(scenario.agents.valid, bool)[:, ci + 1 : ci + 1 + T], (R, A, T)).copy()
        else:
            v = _to_numpy(self.valid, bool)
            if v.shape == (A, T):
                v = np.broadcast_to(v, (R, A, T)).copy()
            if v.shape != (R, A, T):
                raise MetricsInputError(f"SimTrajectories.valid: expected shape [R, A, T]={(R, A, T)} or [A, T], got {v.shape}")
        finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(yaw)
        if (v & ~finite).any():
            r, a, t = np.argwhere(v & ~finite)[0]
            raise MetricsInputError(f"SimTrajectories: non-finite x/y/yaw at a valid entry (rollout {r}, agent {a}, step {t})")
        return SimTrajectories(x_m=np.where(v, x, 0.0), y_m=np.where(v, y, 0.0), yaw_rad=np.where(v, yaw, 0.0), valid=v)


class HistogramSpec(NamedTuple):
    """Histogram estimator: ``num_bins`` equal bins on ``[min_val, max_val]`` (values are clipped into it)."""

    min_val: float
    max_val: float
    num_bins: int


@dataclass(frozen=True)
class FeatureSpec:
    """One realism feature: its bucket, estimator and meta-metric weights (WOSAC 2024 / 2025 configs).

    :param kind: ``"histogram"`` (per-step values) or ``"bernoulli"`` (boolean, any() over time).
    """

    name: str
    bucket: str
    kind: str
    histogram: HistogramSpec | None
    weight_2024: float
    weight_2025: float

    def weight(self, weights: str) -> float:
        if weights == "2024":
            return self.weight_2024
        if weights == "2025":
            return self.weight_2025
        raise ValueError(f"weights: unknown weight set '{weights}'; use '2024' or '2025'")


class TrajectoryFeatures(NamedTuple):
    """Per-step metric features of ``R`` rollouts (``R = 1`` for the logged reference), all ``[R, A, T]``.

    Units: speeds [m/s], accelerations [m/s^2], angular speed [rad/s], angular acceleration [rad/s^2],
    distances [m] (signed: negative = overlapping / inside the drivable area), TTC [s].
    ``tl_violation`` is ``None`` when the scenario's map has no traffic-light states.
    """

    valid: np.ndarray
    linear_speed: np.ndarray
    linear_acceleration: np.ndarray
    angular_speed: np.ndarray
    angular_acceleration: np.ndarray
    speed_valid: np.ndarray
    acceleration_valid: np.ndarray
    distance_to_nearest_object: np.ndarray
    collision: np.ndarray
    time_to_collision: np.ndarray
    distance_to_road_edge: np.ndarray
    offroad: np.ndarray
    tl_violation: np.ndarray | None


@dataclass
class RealismResult:
    """Realism of one scenario's rollouts.

    :param likelihoods: feature name -> likelihood score in [0, 1] (exp of mean log-likelihood).
    :param buckets: ``kinematic`` / ``interactive`` / ``map_based`` -> weighted mean of its features.
    :param rmm: realism meta metric (weights normalised over the features present).
    :param collision_rate, offroad_rate, tl_violation_rate: fraction of (rollout, evaluated agent) pairs
        with any collision / offroad / red-light violation in simulation (``nan`` when not applicable).
    :param ade: mean displacement to the log [m], averaged over agents, steps and rollouts;
        ``min_ade``: the best rollout's mean displacement [m] (WOSAC: min over rollouts of the mean over agents).
    :param diversity: mean pairwise distance [m] between rollouts' final positions, averaged over agents.
    :param extra: further figures; :func:`compute_realism` adds ``collision_rate_log_window`` and
        ``offroad_rate_log_window``: the rates counted only over steps at which the logged agent exists (on a
        finite map an agent whose log ends where it leaves the network keeps driving in simulation, off the map).
    """

    likelihoods: dict[str, float]
    buckets: dict[str, float]
    rmm: float
    collision_rate: float
    offroad_rate: float
    tl_violation_rate: float
    ade: float
    min_ade: float
    diversity: float
    num_rollouts: int
    num_evaluated_agents: int
    weights: str = "2024"
    extra: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, float]:
        """Flat ``{name: value}`` with grouped names (``realism/...``, ``likelihood/...``, ``bucket/...``)."""
        out = {"realism/rmm": float(self.rmm)}
        out.update({f"bucket/{k}": float(v) for k, v in self.buckets.items()})
        out.update({f"likelihood/{k}": float(v) for k, v in self.likelihoods.items()})
        for k in ("collision_rate", "offroad_rate", "tl_violation_rate", "ade", "min_ade", "diversity"):
            out[f"realism/{k}"] = float(getattr(self, k))
        out["realism/num_rollouts"] = float(self.num_rollouts)
        out["realism/num_evaluated_agents"] = float(self.num_evaluated_agents)
        out.update({f"realism/{k}": float(v) for k, v in self.extra.items()})
        return out

    def is_finite(self) -> bool:
        vals = [v for k, v in self.to_dict().items() if not k.endswith("tl_violation_rate")]
        return all(math.isfinite(v) for v in vals)
