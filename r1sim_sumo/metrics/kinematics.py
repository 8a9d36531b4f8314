"""Kinematic features by finite differences at 10 Hz: linear/angular speed and acceleration.

Backward differences over ``[history..., future...]``: ``speed[t] = |p[t] - p[t-1]| / dt``,
``accel[t] = (speed[t] - speed[t-1]) / dt``, ``angular_speed[t] = wrap(yaw[t] - yaw[t-1]) / dt``,
``angular_accel[t] = wrap(dyaw[t] - dyaw[t-1]) / dt^2``. The caller prepends the last two logged history
states (scenario indices ``current_index - 1`` and ``current_index``), so every future step has a speed and
an acceleration when those states are valid. WOSAC uses central differences over the whole 9.1 s
instead; a backward difference is the same estimator shifted by half a step and is applied identically to
the log and to the rollouts, so the likelihoods compare like with like (and it stays causal).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from r1sim_sumo.geometry import wrap_angle


class Kinematics(NamedTuple):
    """All ``[..., T]`` over the future steps; ``speed_valid``/``acceleration_valid`` bool."""

    linear_speed: np.ndarray  # [m/s], >= 0
    linear_acceleration: np.ndarray  # [m/s^2], signed change of linear speed
    angular_speed: np.ndarray  # [rad/s], CCW positive
    angular_acceleration: np.ndarray  # [rad/s^2]
    speed_valid: np.ndarray
    acceleration_valid: np.ndarray


def kinematic_features(x_m, y_m, yaw_rad, valid, num_prefix: int, dt_s: float) -> Kinematics:
    """Speeds and accelerations of ``[..., H + T]`` tracks whose first ``num_prefix = H`` steps are history.

    :param x_m, y_m, yaw_rad: ``[..., H + T]`` box centre [m] and heading [rad].
    :param valid: ``[..., H + T]`` bool.
    :param num_prefix: ``H >= 2`` history steps prepended (only used as the start of the differences).
    :param dt_s: step [s] (0.1 at 10 Hz).
    :returns: :class:`Kinematics` with arrays ``[..., T]``.
    """
    if num_prefix < 2:
        raise ValueError(f"num_prefix: need >= 2 history steps for accelerations, got {num_prefix}")
    x, y, yaw = (np.asarray(a, np.float64) for a in (x_m, y_m, yaw_rad))
    v = np.asarray(valid, bool)
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
