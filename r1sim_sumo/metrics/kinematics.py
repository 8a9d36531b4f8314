"""Kinematic features by finite differences at 10 Hz: linear/angular speed and acceleration.

``differences="central"`` (default, as the official WOSAC code, ``trajectory_features.compute_kinematic_features``):
``speed[t] = |p[t+1] - p[t-1]| / (2 dt)``, ``accel[t] = (speed[t+1] - speed[t-1]) / (2 dt)``,
``angular_speed[t] = wrap(yaw[t+1] - yaw[t-1]) / (2 dt)`` (wrapped as WOSAC: ``wrap(2 d) / 2``), ``angular_accel[t]`` the
same central difference of the per-step heading change, over ``dt^2``. A speed spans 2 steps and is valid when states
``t-1`` and ``t+1`` are; an acceleration spans 4 steps and is valid when the speeds at ``t-1`` and ``t+1`` are (states
``t-2``, ``t``, ``t+2``). The last future step has no speed and the last two no acceleration (no state after the
horizon); there, and wherever the validity fails, values are ``nan`` (WOSAC pads with ``nan``; its histogram puts
``nan`` samples in the last bin, which :func:`r1sim_sumo.metrics.realism.histogram_log_likelihood` reproduces).

``differences="backward"`` (the earlier choice, kept as an option): ``speed[t] = |p[t] - p[t-1]| / dt``,
``accel[t] = (speed[t] - speed[t-1]) / dt``, same for the heading; causal, one step; invalid entries read 0.

The caller prepends the last two logged history states (scenario indices ``current_index - 1`` and ``current_index``),
which is all the first future step needs with either scheme.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from r1sim_sumo.geometry import wrap_angle

DIFFERENCES = ("central", "backward")


class Kinematics(NamedTuple):
    """All ``[..., T]`` over the future steps; ``speed_valid``/``acceleration_valid`` bool."""

    linear_speed: np.ndarray  # [m/s], >= 0
    linear_acceleration: np.ndarray  # [m/s^2], signed change of linear speed
    angular_speed: np.ndarray  # [rad/s], CCW positive
    angular_acceleration: np.ndarray  # [rad/s^2]
    speed_valid: np.ndarray
    acceleration_valid: np.ndarray


def _central(a: np.ndarray, pad) -> np.ndarray:
    """``(a[t+1] - a[t-1]) / 2`` along the last axis, padded with ``pad`` at both ends (same length)."""
    p = np.full((*a.shape[:-1], 1), pad, dtype=np.float64)
    return np.concatenate([p, (a[..., 2:] - a[..., :-2]) / 2.0, p], -1)


def _central_and(v: np.ndarray) -> np.ndarray:
    p = np.zeros((*v.shape[:-1], 1), bool)
    return np.concatenate([p, v[..., 2:] & v[..., :-2], p], -1)


def kinematic_features(x_m, y_m, yaw_rad, valid, num_prefix: int, dt_s: float, differences: str = "central") -> Kinematics:
    """Speeds and accelerations of ``[..., H + T]`` tracks whose first ``num_prefix = H`` steps are history.

    :param x_m, y_m, yaw_rad: ``[..., H + T]`` box centre [m] and heading [rad].
    :param valid: ``[..., H + T]`` bool.
    :param num_prefix: ``H >= 2`` history steps prepended (only used as the start of the differences).
    :param dt_s: step [s] (0.1 at 10 Hz).
    :param differences: ``central`` (WOSAC, default) or ``backward`` (module doc).
    :returns: :class:`Kinematics` with arrays ``[..., T]``.
    """
    if num_prefix < 2:
        raise ValueError(f"num_prefix: need >= 2 history steps for accelerations, got {num_prefix}")
    if differences not in DIFFERENCES:
        raise ValueError(f"differences '{differences}' unknown; use one of {DIFFERENCES}")
    x, y, yaw = (np.asarray(a, np.float64) for a in (x_m, y_m, yaw_rad))
    v = np.asarray(valid, bool)
    if differences == "central":
        speed = np.hypot(_central(x, np.nan), _central(y, np.nan)) / dt_s  # [..., H+T]
        accel = _central(speed, np.nan) / dt_s
        dh = wrap_angle(_central(yaw, np.nan) * 2.0) / 2.0  # per-step heading change [rad]
        d2h = wrap_angle(_central(dh, np.nan) * 2.0) / 2.0
        sv = _central_and(v)
        av = _central_and(sv)
        h = num_prefix
        nan = np.float64(np.nan)
        return Kinematics(
            linear_speed=np.where(sv, speed, nan)[..., h:],
            linear_acceleration=np.where(av, accel, nan)[..., h:],
            angular_speed=np.where(sv, dh / dt_s, nan)[..., h:],
            angular_acceleration=np.where(av, d2h / dt_s**2, nan)[..., h:],
            speed_valid=sv[..., h:],
            acceleration_valid=av[..., h:],
        )
    speed = np.hypot(np.diff(x, axis=-1), np.diff(y, axis=-1)) / dt_s  # [..., H+T-1]
    dyaw = wrap_angle(np.diff(yaw, axis=-1))  # [..., H+T-1] per-step heading change [rad]
    sv = v[..., 1:] & v[..., :-1]
    accel = np.diff(speed, axis=-1) / dt_s  # [..., H+T-2]
    dyaw2 = wrap_angle(np.diff(dyaw, axis=-1))
    av = sv[..., 1:] & sv[..., :-1]
    s = num_prefix - 1  # first future index in the speed arrays
    a = num_prefix - 2  # first future index in the acceleration arrays
    return Kinematics(
        linear_speed=np.where(sv, speed, 0.0)[..., s:],
        linear_acceleration=np.where(av, accel, 0.0)[..., a:],
        angular_speed=np.where(sv, dyaw / dt_s, 0.0)[..., s:],
        angular_acceleration=np.where(av, dyaw2 / dt_s**2, 0.0)[..., a:],
        speed_valid=sv[..., s:],
        acceleration_valid=av[..., a:],
    )
