"""scripts/vocab_speed_changes.py: tokens are counted as accelerating only when their speed changes inside the 0.5 s."""

from __future__ import annotations

import numpy as np


def _token(v0_mps: float, accel_mps2: float) -> np.ndarray:
    t = np.arange(6) * 0.1
    x = v0_mps * t + 0.5 * accel_mps2 * t**2
    return np.stack([x, np.zeros(6), np.zeros(6)], axis=-1)


def test_constant_speed_tokens_do_not_count_and_an_accelerating_one_does(repo_script):
    mod = repo_script("scripts/vocab_speed_changes.py")
    traj = np.stack([_token(20.0, 0.0), _token(20.5, 0.0), _token(19.5, 2.0), _token(21.0, -3.0), _token(12.0, 1.0)])
    rows = {lo: (n, s, up, down) for lo, _hi, n, s, up, down in mod.speed_change_table(traj, 0.5, 4.0)}
    assert rows[18.0] == (4, 4, 1, 1)  # four tokens at 18-22 m/s mean, all straight, one speeding up, one braking
    assert rows[10.0] == (1, 1, 1, 0)
    assert rows[22.0] == (0, 0, 0, 0)
