"""Realism meta metric (Waymo Open Sim Agents Challenge style) of simulated rollouts against the log.

For every feature (see :data:`FEATURES`, histogram ranges/bins and weights of the WOSAC 2024 config):

* time-series features: per evaluated agent, a histogram of the simulated values pooled over all rollouts
  and steps (invalid simulated entries left out), additive smoothing ``pseudocount`` (0.1) per bin, then
  normalised; the log-likelihood of each logged value under its agent's histogram, averaged over all valid
  (agent, step) pairs of the log; score = ``exp(mean log-likelihood)``.
* boolean features (collision, offroad, red-light violation): any() over the valid steps, then a Bernoulli
  estimate across rollouts (2-bin histogram with the same smoothing); score = ``exp(mean over agents of the
  log-probability of the logged outcome)``.
* buckets = weighted means over their features (kinematic: the 4 motion features; interactive: distance to
  nearest object, collision, TTC; map-based: distance to road edge, offroad, traffic-light violation);
  RMM = weighted mean over all features, weights normalised over the features that exist for the scenario
  (a feature without any valid logged value, or the traffic-light feature on maps without signals, is
  left out). Weight set ``"2024"`` (default) gives the traffic-light feature weight 0 (reported only);
  ``"2025"`` adds it at 0.05 and halves the road-edge distance weight.

Evaluated agents are those valid at the scenario's current step (as WOSAC's sim agents); all agents valid
at a step are obstacles for the interaction features.
"""

from __future__ import annotations

import math

import numpy as np

from r1sim_sumo.metrics.collisions import interaction_features
from r1sim_sumo.metrics.kinematics import kinematic_features
from r1sim_sumo.metrics.map_features import (
    DrivableArea,
    distance_to_road_edge,
    drivable_area,
    lane_assignment,
    offroad_flags,
    red_light_violations,
)
from r1sim_sumo.metrics.types import (
    FeatureSpec,
    HistogramSpec,
    MetricsInputError,
    RealismResult,
    SimTrajectories,
    TrajectoryFeatures,
)
from r1sim_sumo.scenario import Scenario

PSEUDOCOUNT = 0.1
NUM_HISTORY_PREFIX = 2  # logged states current_index-1, current_index start the finite differences

FEATURES: tuple[FeatureSpec, ...] = (
    FeatureSpec("linear_speed", "kinematic", "histogram", HistogramSpec(0.0, 25.0, 10), 0.05, 0.05),
    FeatureSpec("linear_acceleration", "kinematic", "histogram", HistogramSpec(-12.0, 12.0, 11), 0.05, 0.05),
    FeatureSpec("angular_speed", "kinematic", "histogram", HistogramSpec(-0.628, 0.628, 11), 0.05, 0.05),
    FeatureSpec("angular_acceleration", "kinematic", "histogram", HistogramSpec(-3.14, 3.14, 11), 0.05, 0.05),
    FeatureSpec("distance_to_nearest_object", "interactive", "histogram", HistogramSpec(-5.0, 40.0, 10), 0.10, 0.10),
    FeatureSpec("collision_indication", "interactive", "bernoulli", None, 0.25, 0.25),
    FeatureSpec("time_to_collision", "interactive", "histogram", HistogramSpec(0.0, 5.0, 10), 0.10, 0.10),
    FeatureSpec("distance_to_road_edge", "map_based", "histogram", HistogramSpec(-20.0, 40.0, 10), 0.10, 0.05),
    FeatureSpec("offroad_indication", "map_based", "bernoulli", None, 0.25, 0.25),
    FeatureSpec("traffic_light_violation", "map_based", "bernoulli", None, 0.0, 0.05),
)
BUCKETS = ("kinematic", "interactive", "map_based")

# feature name -> (values field, validity field) of TrajectoryFeatures
_FIELDS = {
    "linear_speed": ("linear_speed", "speed_valid"),
    "linear_acceleration": ("linear_acceleration", "acceleration_valid"),
    "angular_speed": ("angular_speed", "speed_valid"),
    "angular_acceleration": ("angular_acceleration", "acceleration_valid"),
    "distance_to_nearest_object": ("distance_to_nearest_object", "valid"),
    "collision_indication": ("collision", "valid"),
    "time_to_collision": ("time_to_collision", "valid"),
    "distance_to_road_edge": ("distance_to_road_edge", "valid"),
    "offroad_indication": ("offroad", "valid"),
    "traffic_light_violation": ("tl_violation", "valid"),
}


# ---------------------------------------------------------------------------- estimators


def _bin_index(values: np.ndarray, spec: HistogramSpec) -> np.ndarray:
    """Bin of each value, values clipped into ``[min_val, max_val]`` (NaN -> last bin, as WOSAC)."""
    v = np.nan_to_num(np.asarray(values, np.float64), nan=spec.max_val)
    v = np.clip(v, spec.min_val, spec.max_val)
    b = np.floor((v - spec.min_val) / (spec.max_val - spec.min_val) * spec.num_bins).astype(np.int64)
    return np.minimum(b, spec.num_bins - 1)


def histogram_log_likelihood(log_values, sim_values, sim_valid, spec: HistogramSpec,
                             pseudocount: float = PSEUDOCOUNT) -> np.ndarray:
    """``[A, T]`` log-likelihood of logged values under per-agent histograms of the simulated values.

    :param log_values: ``[A, T]`` logged feature values.
    :param sim_values: ``[R, A, T]`` simulated values; ``sim_valid`` ``[R, A, T]`` bool selects the samples.
    Each agent's histogram pools its rollouts and steps; every bin gets ``pseudocount`` before normalising.
    """
    sim_values = np.asarray(sim_values)
    R, A, T = sim_values.shape
    nb = spec.num_bins
    flat = (np.arange(A)[None, :, None] * nb + _bin_index(sim_values, spec))[np.asarray(sim_valid, bool)]
    counts = np.bincount(flat, minlength=A * nb).reshape(A, nb) + pseudocount  # [A, nb]
    prob = counts / counts.sum(1, keepdims=True)
    lb = _bin_index(log_values, spec)  # [A, T]
    return np.log(prob[np.arange(A)[:, None], lb])


def bernoulli_log_likelihood(log_flags, sim_flags, pseudocount: float = PSEUDOCOUNT) -> np.ndarray:
    """``[A]`` log-probability of the logged boolean ``[A]`` under the rollouts' frequency ``[R, A]``."""
    sim = np.asarray(sim_flags, bool)
    p_true = (sim.sum(0) + pseudocount) / (sim.shape[0] + 2 * pseudocount)  # [A]
    return np.log(np.where(np.asarray(log_flags, bool), p_true, 1.0 - p_true))


# ---------------------------------------------------------------------------- features


def compute_features(scenario: Scenario, x_m, y_m, yaw_rad, valid, area: DrivableArea | None = None,
                     offroad_tolerance_m: float = 0.0) -> TrajectoryFeatures:
    """Metric features of ``[R, A, T]`` future tracks of the scenario's agents (``R = 1`` for the log).

    Finite differences start from the logged states ``current_index - 1`` and ``current_index``.
    """
    a, ci, dt = scenario.agents, scenario.current_index, scenario.dt_s
    if ci < NUM_HISTORY_PREFIX - 1:
        raise MetricsInputError(f"scenario.current_index: need >= {NUM_HISTORY_PREFIX - 1} history step before it, got {ci}")
    x, y, yaw, v = (np.asarray(t) for t in (x_m, y_m, yaw_rad, valid))
    R, A, T = x.shape
    hs = slice(ci + 1 - NUM_HISTORY_PREFIX, ci + 1)
    hist = lambda f: np.broadcast_to(np.asarray(getattr(a, f))[None, :, hs], (R, A, NUM_HISTORY_PREFIX))  # noqa: E731
    cat = lambda h, f: np.concatenate([h, f], axis=-1)  # noqa: E731
    fx, fy, fyaw = cat(hist("x_m"), x), cat(hist("y_m"), y), cat(hist("yaw_rad"), yaw)
    fv = cat(hist("valid").astype(bool), v)  # [R, A, H+T]
    kin = kinematic_features(fx, fy, fyaw, fv, NUM_HISTORY_PREFIX, dt)
    inter = interaction_features(x, y, yaw, a.length_m, a.width_m, v, kin.linear_speed)
    area = drivable_area(scenario.map) if area is None else area
    edge = distance_to_road_edge(area, x, y, yaw, a.length_m, a.width_m, v)
    offroad = offroad_flags(edge, offroad_tolerance_m) & v
    tl = None
    m = scenario.map
    if m.tl_state.ndim == 2 and m.tl_state.shape[1] >= ci + 1 + T:
        p = NUM_HISTORY_PREFIX - 1  # keep only the current step as the "before" state
        lanes = lane_assignment(area, fx[..., p:], fy[..., p:], fyaw[..., p:], fv[..., p:])  # [R, A, T+1]
        tl = red_light_violations(lanes, fv[..., p:], m.tl_state[:, ci : ci + 1 + T])
    return TrajectoryFeatures(
        valid=v, linear_speed=kin.linear_speed, linear_acceleration=kin.linear_acceleration,
        angular_speed=kin.angular_speed, angular_acceleration=kin.angular_acceleration,
        speed_valid=kin.speed_valid & v, acceleration_valid=kin.acceleration_valid & v,
        distance_to_nearest_object=inter.distance_m, collision=inter.collision, time_to_collision=inter.ttc_s,
        distance_to_road_edge=edge, offroad=offroad, tl_violation=tl,
    )


# ---------------------------------------------------------------------------- scores


def _feature_likelihood(spec: FeatureSpec, log_f: TrajectoryFeatures, sim_f: TrajectoryFeatures,
                        evaluated: np.ndarray, pseudocount: float) -> float:
    """Likelihood in [0, 1] of one feature, or ``nan`` when it does not exist for this scenario."""
    vf, mf = _FIELDS[spec.name]
    lv, sv = getattr(log_f, vf), getattr(sim_f, vf)
    if lv is None or sv is None:
        return math.nan
    log_valid = getattr(log_f, mf)[0] & evaluated[:, None]  # [A, T]
    sim_valid = getattr(sim_f, mf) & log_f.valid  # [R, A, T] (WOSAC masks sims by the log's validity)
    if spec.kind == "bernoulli":
        log_flag = (lv[0] & log_valid).any(-1)  # [A]
        sim_flag = (sv & sim_valid).any(-1)  # [R, A]
        ll = bernoulli_log_likelihood(log_flag[evaluated], sim_flag[:, evaluated], pseudocount)
        return float(np.exp(ll.mean())) if ll.size else math.nan
    if not log_valid.any():
        return math.nan
    ll = histogram_log_likelihood(lv[0], sv, sim_valid, spec.histogram, pseudocount)  # [A, T]
    return float(np.exp(ll[log_valid].mean()))


def _weighted(likelihoods: dict[str, float], specs, weights: str) -> float:
    num = den = 0.0
    for s in specs:
        w, lk = s.weight(weights), likelihoods.get(s.name, math.nan)
        if w > 0 and math.isfinite(lk):
            num, den = num + w * lk, den + w
    return num / den if den > 0 else math.nan


def compute_realism(scenario: Scenario, sim: SimTrajectories, *, weights: str = "2024",
                    offroad_tolerance_m: float = 0.0, pseudocount: float = PSEUDOCOUNT) -> RealismResult:
    """Realism of ``sim`` (``R`` rollouts of the scenario's future) against the scenario's logged future.

    :param weights: ``"2024"`` (default) or ``"2025"`` meta-metric weights (module doc).
    :param offroad_tolerance_m: [m] a corner must be this far outside the drivable area to be offroad.
    :param pseudocount: additive smoothing per histogram bin.
    """
    FEATURES[0].weight(weights)  # validates the name early
    s = sim.checked(scenario)
    R, A, T = s.x_m.shape
    ci = scenario.current_index
    evaluated = np.asarray(scenario.agents.valid, bool)[:, ci]  # [A]
    if not evaluated.any():
        raise MetricsInputError("scenario.agents.valid: no agent is valid at current_index; nothing to evaluate")
    area = drivable_area(scenario.map)
    log = SimTrajectories.log_replay(scenario, 1, T).checked(scenario)
    log_f = compute_features(scenario, log.x_m, log.y_m, log.yaw_rad, log.valid, area, offroad_tolerance_m)
    sim_f = compute_features(scenario, s.x_m, s.y_m, s.yaw_rad, s.valid, area, offroad_tolerance_m)

    likelihoods = {f.name: _feature_likelihood(f, log_f, sim_f, evaluated, pseudocount) for f in FEATURES}
    likelihoods = {k: v for k, v in likelihoods.items() if math.isfinite(v)}
    buckets = {b: _weighted(likelihoods, [f for f in FEATURES if f.bucket == b], weights) for b in BUCKETS}
    rmm = _weighted(likelihoods, FEATURES, weights)

    sv = s.valid  # [R, A, T]
    rate = lambda flags: float((flags & sv).any(-1)[:, evaluated].mean())  # noqa: E731
    tl_rate = rate(sim_f.tl_violation) if sim_f.tl_violation is not None else math.nan

    both = sv & log.valid & evaluated[None, :, None]  # [R, A, T]
    disp = np.hypot(s.x_m - log.x_m, s.y_m - log.y_m)
    n = both.sum((1, 2))
    ade_r = np.where(n > 0, (disp * both).sum((1, 2)) / np.maximum(n, 1), np.nan)  # [R]
    ade = float(np.nanmean(ade_r)) if np.isfinite(ade_r).any() else math.nan
    min_ade = float(np.nanmin(ade_r)) if np.isfinite(ade_r).any() else math.nan
    # the same rates over only the steps at which the logged agent still exists (as WOSAC masks the likelihoods):
    # an agent that left a finite network in the log but drives on in simulation is not offroad "on the road"
    in_log = sv & log.valid
    rate_log = lambda flags: float((flags & in_log).any(-1)[:, evaluated].mean())  # noqa: E731
    return RealismResult(
        likelihoods=likelihoods, buckets=buckets, rmm=rmm,
        collision_rate=rate(sim_f.collision), offroad_rate=rate(sim_f.offroad), tl_violation_rate=tl_rate,
        ade=ade, min_ade=min_ade, diversity=final_position_diversity(s, evaluated),
        num_rollouts=R, num_evaluated_agents=int(evaluated.sum()), weights=weights,
        extra={"collision_rate_log_window": rate_log(sim_f.collision), "offroad_rate_log_window": rate_log(sim_f.offroad)},
    )


def final_position_diversity(sim: SimTrajectories, evaluated: np.ndarray | None = None) -> float:
    """Mean pairwise distance [m] between rollouts' final positions (last step), averaged over agents.

    Pairs where either rollout has the agent invalid at the last step are left out; 0 with one rollout.
    """
    p = np.stack([np.asarray(sim.x_m)[..., -1], np.asarray(sim.y_m)[..., -1]], -1)  # [R, A, 2]
    v = np.asarray(sim.valid, bool)[..., -1] if sim.valid is not None else np.ones(p.shape[:2], bool)
    if evaluated is not None:
        p, v = p[:, evaluated], v[:, evaluated]
    R = p.shape[0]
    if R < 2:
        return 0.0
    d = np.linalg.norm(p[:, None] - p[None, :], axis=-1)  # [R, R, A]
    pair = v[:, None] & v[None, :] & ~np.eye(R, dtype=bool)[..., None]
    cnt = pair.sum((0, 1))  # [A]
    per_agent = (d * pair).sum((0, 1)) / np.maximum(cnt, 1)
    return float(per_agent[cnt > 0].mean()) if (cnt > 0).any() else 0.0


def aggregate(results: list[RealismResult]) -> dict[str, float]:
    """Means over scenarios of every entry of :meth:`RealismResult.to_dict` (NaN entries skipped)."""
    if not results:
        raise ValueError("aggregate: empty list of RealismResult")
    keys = list(dict.fromkeys(k for r in results for k in r.to_dict()))
    rows = [r.to_dict() for r in results]
    out = {}
    for k in keys:
        vals = np.array([row.get(k, math.nan) for row in rows], np.float64)
        out[k] = float(np.nanmean(vals)) if np.isfinite(vals).any() else math.nan
    out["realism/num_scenarios"] = float(len(results))
    return out
