"""Realism meta metric (Waymo Open Sim Agents Challenge) of simulated rollouts against the log.

The default :class:`RealismConfig` follows the official WOSAC code (``waymo-open-dataset`` 1.6.7,
``wdl_limited/sim_agents_metrics``: ``metrics.py``, ``metric_features.py``, ``estimators.py``, the 2024/2025
configs); ``scripts/wosac_golden.py`` checks it against that code (fixtures in ``tests/fixtures/wosac_golden/``).

For every feature (see :data:`FEATURES`, histogram ranges/bins and weights of the WOSAC 2024 config):

* time-series features: per evaluated agent, a histogram of the simulated values pooled over all rollouts and all
  simulated steps (``sim_histogram_mask="sim_valid"``: every step at which the agent exists in the rollout; WOSAC's
  rollouts always hold every sim agent, so it pools everything), additive smoothing ``histogram_pseudocount`` (0.1)
  per bin, then normalised; the log-likelihood of each logged value under its agent's histogram, averaged over the
  valid (agent, step) pairs of the *log* (the log side alone is masked); score = ``exp(mean log-likelihood)``.
  Kinematic values whose central difference is undefined (the last step, next to an invalid state) are ``nan`` and,
  as in WOSAC's histogram, fall in the last bin on the simulated side. On the log side WOSAC derives the speed /
  acceleration validity from the *future* validity alone (``kinematic_log_mask="future_only"``), so the first future
  step's logged speed and the first two logged accelerations are not scored, although the history makes them defined.
* boolean features (collision, offroad, red-light violation): any() over the steps at which the log is valid, then a
  Bernoulli estimate across rollouts (2-bin histogram with ``bernoulli_pseudocount`` = 0.001, the proto default the
  official configs leave in place); score = ``exp(mean over agents of the log-probability of the logged outcome)``.
* TTC and the traffic-light feature are scored on vehicles only (``vehicles_only_ttc_tl``), as WOSAC.
* buckets = weighted means over their features (kinematic: the 4 motion features; interactive: distance to
  nearest object, collision, TTC; map-based: distance to road edge, offroad, traffic-light violation);
  RMM = weighted mean over all features, weights normalised over the features that exist for the scenario
  (a feature without any valid logged value is left out; on maps without signals the traffic-light feature reads "no
  violation" on both sides, as WOSAC). Weight set ``"2024"`` (default) gives the traffic-light feature weight 0
  (reported only); ``"2025"`` adds it at 0.05 and halves the road-edge distance weight.

Agents. WOSAC simulates every object valid at the current step ("sim agents") and evaluates the ego plus the
``tracks_to_predict``; our SUMO/highway scenes have no ego and no curated track list, so every agent valid at the
current step is both simulated and evaluated (``r1sim export-wosac`` writes them all as ``tracks_to_predict``). The
interaction features (distance, collision, TTC) see only these sim agents as obstacles, on the log side too
(``obstacles="sim_agents"``): an agent that enters after the current step is never simulated, so the logged scene
does not hold it either.

Remaining known differences to the official code (measured by ``scripts/wosac_golden.py``, see
``tests/fixtures/wosac_golden/README.md``): the drivable area / road-edge distance is built from buffered lane
centres here and from road-edge polylines there (the exporter writes our drivable-area boundary as road edges); the
red-light rule is ours (lane change into a red via-lane, :mod:`.map_features`), not WOSAC's stop-line crossing; 2D
positions only (z = 0); WOSAC computes speeds next to invalid logged states from whatever coordinates the log stores
there, we leave them out (``nan``).

Older behaviour, kept as named options (:meth:`RealismConfig.legacy` gives all of them): log-side obstacles = every
agent valid at a step (``obstacles="all_valid"``), simulated samples masked by the log's validity
(``sim_histogram_mask="log_valid"``), Bernoulli smoothing 0.1, one-step backward differences
(``differences="backward"``), sharp boxes, wrapped TTC heading difference, TTC/traffic light on all agent types,
traffic-light feature dropped on maps without signals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from r1sim_sumo.metrics.collisions import BOX_SHAPES, TTC_HEADINGS, interaction_features
from r1sim_sumo.metrics.kinematics import DIFFERENCES, kinematic_features
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

PSEUDOCOUNT = 0.1  # histogram smoothing per bin (WOSAC configs)
BERNOULLI_PSEUDOCOUNT = 0.001  # Bernoulli smoothing (WOSAC proto default, left in place by the configs)
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

@dataclass(frozen=True)
class RealismConfig:
    """How the realism metric is computed; the defaults are the official WOSAC behaviour (module doc)."""

    obstacles: str = "sim_agents"
    """sim_agents (WOSAC: only agents valid at the current step are objects, log side too) or all_valid (every agent
    valid at a step, also those entering later)."""
    sim_histogram_mask: str = "sim_valid"
    """sim_valid (WOSAC: simulated histogram samples pooled over every simulated step) or log_valid (only the steps
    at which the log is valid)."""
    histogram_pseudocount: float = PSEUDOCOUNT
    """Additive smoothing per histogram bin (WOSAC 0.1)."""
    bernoulli_pseudocount: float = BERNOULLI_PSEUDOCOUNT
    """Additive smoothing of the Bernoulli estimate (WOSAC 0.001)."""
    differences: str = "central"
    """central (WOSAC: speed over 2 steps, acceleration over 4) or backward (one step)."""
    box_shape: str = "rounded"
    """rounded (WOSAC: corners rounded, factor 0.7) or sharp boxes for distance to nearest object and collisions."""
    ttc_heading: str = "unwrapped"
    """unwrapped (WOSAC: |yaw_j - yaw_i|) or wrapped heading difference in the TTC following test."""
    vehicles_only_ttc_tl: bool = True
    """Score TTC and the traffic-light feature on vehicles only (WOSAC)."""
    kinematic_log_mask: str = "future_only"
    """Which logged speeds/accelerations are scored: future_only (WOSAC: the central-difference validity is derived
    from the *future* validity alone, so the first future step has no logged speed and the first two no logged
    acceleration, like the last ones) or full (the validity of the differences over the logged history + future)."""
    tl_without_signals: str = "no_violation"
    """Maps without signal states: no_violation (WOSAC: the feature reads False on both sides) or drop (leave it
    out and renormalise the weights)."""

    def __post_init__(self) -> None:
        choices = {"obstacles": ("sim_agents", "all_valid"), "sim_histogram_mask": ("sim_valid", "log_valid"),
                   "differences": DIFFERENCES, "box_shape": BOX_SHAPES, "ttc_heading": TTC_HEADINGS,
                   "tl_without_signals": ("no_violation", "drop"), "kinematic_log_mask": ("future_only", "full")}
        for name, ok in choices.items():
            if getattr(self, name) not in ok:
                raise ValueError(f"RealismConfig.{name}: '{getattr(self, name)}' unknown; use one of {ok}")
        for name in ("histogram_pseudocount", "bernoulli_pseudocount"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RealismConfig.{name}: must be > 0, got {getattr(self, name)}")

    @classmethod
    def legacy(cls) -> RealismConfig:
        """The metric as computed before issue 16 (every figure reported before it used this)."""
        return cls(obstacles="all_valid", sim_histogram_mask="log_valid", bernoulli_pseudocount=0.1,
                   differences="backward", box_shape="sharp", ttc_heading="wrapped", vehicles_only_ttc_tl=False,
                   tl_without_signals="drop", kinematic_log_mask="full")


METRIC_VARIANTS = ("wosac", "legacy")


def metric_config(name: str) -> RealismConfig:
    """``wosac`` (the official computation, default) or ``legacy`` (before issue 16) as a :class:`RealismConfig`."""
    if name == "wosac":
        return RealismConfig()
    if name == "legacy":
        return RealismConfig.legacy()
    raise ValueError(f"metric '{name}' unknown; use one of {METRIC_VARIANTS}")


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


def bernoulli_log_likelihood(log_flags, sim_flags, pseudocount: float = BERNOULLI_PSEUDOCOUNT) -> np.ndarray:
    """``[A]`` log-probability of the logged boolean ``[A]`` under the rollouts' frequency ``[R, A]``."""
    sim = np.asarray(sim_flags, bool)
    p_true = (sim.sum(0) + pseudocount) / (sim.shape[0] + 2 * pseudocount)  # [A]
    return np.log(np.where(np.asarray(log_flags, bool), p_true, 1.0 - p_true))


# ---------------------------------------------------------------------------- features


def compute_features(scenario: Scenario, x_m, y_m, yaw_rad, valid, area: DrivableArea | None = None,
                     offroad_tolerance_m: float = 0.0, config: RealismConfig | None = None) -> TrajectoryFeatures:
    """Metric features of ``[R, A, T]`` future tracks of the scenario's agents (``R = 1`` for the log).

    Finite differences start from the logged states ``current_index - 1`` and ``current_index``. With
    ``config.obstacles == "sim_agents"`` only agents valid at ``current_index`` take part in the interaction features
    (as obstacles and as subjects).
    """
    cfg = config or RealismConfig()
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
    kin = kinematic_features(fx, fy, fyaw, fv, NUM_HISTORY_PREFIX, dt, cfg.differences)
    iv = v
    if cfg.obstacles == "sim_agents":
        iv = v & np.asarray(a.valid, bool)[None, :, ci, None]
    ttc_speed = np.where(kin.speed_valid, kin.linear_speed, np.nan) if cfg.differences == "central" else kin.linear_speed
    inter = interaction_features(x, y, yaw, a.length_m, a.width_m, iv, ttc_speed, box_shape=cfg.box_shape,
                                 ttc_heading=cfg.ttc_heading)
    area = drivable_area(scenario.map) if area is None else area
    edge = distance_to_road_edge(area, x, y, yaw, a.length_m, a.width_m, v)
    offroad = offroad_flags(edge, offroad_tolerance_m) & v
    tl = None
    m = scenario.map
    if m.tl_state.ndim == 2 and m.tl_state.shape[1] >= ci + 1 + T:
        p = NUM_HISTORY_PREFIX - 1  # keep only the current step as the "before" state
        lanes = lane_assignment(area, fx[..., p:], fy[..., p:], fyaw[..., p:], fv[..., p:])  # [R, A, T+1]
        tl = red_light_violations(lanes, fv[..., p:], m.tl_state[:, ci : ci + 1 + T])
    elif cfg.tl_without_signals == "no_violation":
        tl = np.zeros(v.shape, bool)
    return TrajectoryFeatures(
        valid=v, linear_speed=kin.linear_speed, linear_acceleration=kin.linear_acceleration,
        angular_speed=kin.angular_speed, angular_acceleration=kin.angular_acceleration,
        speed_valid=kin.speed_valid & v, acceleration_valid=kin.acceleration_valid & v,
        distance_to_nearest_object=inter.distance_m, collision=inter.collision, time_to_collision=inter.ttc_s,
        distance_to_road_edge=edge, offroad=offroad, tl_violation=tl,
    )


# ---------------------------------------------------------------------------- scores


_VEHICLE_ONLY = ("time_to_collision", "traffic_light_violation")
_SPEEDS = ("linear_speed", "angular_speed")
_ACCELERATIONS = ("linear_acceleration", "angular_acceleration")


def _central_and(v: np.ndarray) -> np.ndarray:
    """``v[t-1] & v[t+1]`` along the last axis, False at both ends (WOSAC ``central_logical_and``)."""
    out = np.zeros_like(v, dtype=bool)
    out[..., 1:-1] = v[..., 2:] & v[..., :-2]
    return out


def _feature_likelihood(spec: FeatureSpec, log_f: TrajectoryFeatures, sim_f: TrajectoryFeatures,
                        evaluated: np.ndarray, is_vehicle: np.ndarray, cfg: RealismConfig) -> float:
    """Likelihood in [0, 1] of one feature, or ``nan`` when it does not exist for this scenario."""
    vf, mf = _FIELDS[spec.name]
    lv, sv = getattr(log_f, vf), getattr(sim_f, vf)
    if lv is None or sv is None:
        return math.nan
    scored = evaluated & is_vehicle if (cfg.vehicles_only_ttc_tl and spec.name in _VEHICLE_ONLY) else evaluated  # [A]
    log_valid = getattr(log_f, mf)[0] & scored[:, None]  # [A, T]
    if cfg.kinematic_log_mask == "future_only" and spec.name in _SPEEDS + _ACCELERATIONS:
        kv = _central_and(log_f.valid[0])  # WOSAC: compute_kinematic_validity(future validity)
        if spec.name in _ACCELERATIONS:
            kv = _central_and(kv)
        log_valid = kv & scored[:, None]
    if spec.kind == "bernoulli":
        # any() over the steps at which the log is valid, on both sides (WOSAC); agents outside ``scored`` read False
        mask = log_f.valid[0] & scored[:, None]  # [A, T]
        log_flag = (lv[0] & mask).any(-1)  # [A]
        sim_flag = (sv & sim_f.valid & mask).any(-1)  # [R, A]
        ll = bernoulli_log_likelihood(log_flag[evaluated], sim_flag[:, evaluated], cfg.bernoulli_pseudocount)
        return float(np.exp(ll.mean())) if ll.size else math.nan
    if not log_valid.any():
        return math.nan
    if cfg.sim_histogram_mask == "sim_valid":
        sim_valid = sim_f.valid  # [R, A, T] every simulated step (undefined kinematics are nan: last bin)
    else:
        sim_valid = getattr(sim_f, mf) & log_f.valid  # legacy: masked by the log's validity
    ll = histogram_log_likelihood(lv[0], sv, sim_valid, spec.histogram, cfg.histogram_pseudocount)  # [A, T]
    return float(np.exp(ll[log_valid].mean()))


def _weighted(likelihoods: dict[str, float], specs, weights: str) -> float:
    num = den = 0.0
    for s in specs:
        w, lk = s.weight(weights), likelihoods.get(s.name, math.nan)
        if w > 0 and math.isfinite(lk):
            num, den = num + w * lk, den + w
    return num / den if den > 0 else math.nan


def compute_realism(scenario: Scenario, sim: SimTrajectories, *, weights: str = "2024",
                    offroad_tolerance_m: float = 0.0, config: RealismConfig | None = None) -> RealismResult:
    """Realism of ``sim`` (``R`` rollouts of the scenario's future) against the scenario's logged future.

    :param weights: ``"2024"`` (default) or ``"2025"`` meta-metric weights (module doc).
    :param offroad_tolerance_m: [m] a corner must be this far outside the drivable area to be offroad.
    :param config: :class:`RealismConfig` (default: the official WOSAC computation; ``RealismConfig.legacy()`` the
        pre-issue-16 one).
    """
    cfg = config or RealismConfig()
    FEATURES[0].weight(weights)  # validates the name early
    s = sim.checked(scenario)
    R, A, T = s.x_m.shape
    ci = scenario.current_index
    evaluated = np.asarray(scenario.agents.valid, bool)[:, ci]  # [A]
    if not evaluated.any():
        raise MetricsInputError("scenario.agents.valid: no agent is valid at current_index; nothing to evaluate")
    area = drivable_area(scenario.map)
    log = SimTrajectories.log_replay(scenario, 1, T).checked(scenario)
    log_f = compute_features(scenario, log.x_m, log.y_m, log.yaw_rad, log.valid, area, offroad_tolerance_m, cfg)
    sim_f = compute_features(scenario, s.x_m, s.y_m, s.yaw_rad, s.valid, area, offroad_tolerance_m, cfg)
    is_vehicle = np.asarray(scenario.agents.agent_type) == 0  # [A]

    likelihoods = {f.name: _feature_likelihood(f, log_f, sim_f, evaluated, is_vehicle, cfg) for f in FEATURES}
    likelihoods = {k: v for k, v in likelihoods.items() if math.isfinite(v)}
    buckets = {b: _weighted(likelihoods, [f for f in FEATURES if f.bucket == b], weights) for b in BUCKETS}
    rmm = _weighted(likelihoods, FEATURES, weights)

    sv = s.valid  # [R, A, T]
    rate = lambda flags: float((flags & sv).any(-1)[:, evaluated].mean())  # noqa: E731
    tl = scenario.map.tl_state
    has_signals = tl.ndim == 2 and tl.shape[1] >= ci + 1 + T
    tl_rate = rate(sim_f.tl_violation) if has_signals else math.nan

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
