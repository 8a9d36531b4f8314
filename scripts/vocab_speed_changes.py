"""How a policy's vehicle tokens change speed *within* their 0.5 s: per band of mean speed, how many tokens accelerate
or brake by more than a threshold between their first and last 0.1 s interval.

    python scripts/vocab_speed_changes.py [--checkpoint CKPT] [--threshold 0.5] [--band 4]

A token is 6 poses 0.1 s apart in its start frame (``MotionVocab.traj``); its interval speeds are the distances between
consecutive poses / 0.1 s [m/s], its mean speed their mean, its in-token acceleration (last - first interval speed) /
0.4 s [m/s^2]. A band with few accelerating tokens speeds a vehicle up only from one token to the next (a faster
constant-speed token each 0.5 s), never inside one. Session 50: the nano's vocabulary has 14 of 295 vehicle tokens
with +0.5 m/s^2 or more at 18-22 m/s mean speed, against 129 of 501 at 10-14 m/s.
"""

from __future__ import annotations

import argparse

import numpy as np

from r1sim_sumo.scenario import DT_S  # [s] 0.1


def speed_change_table(traj: np.ndarray, threshold: float, band: float, top: float = 34.0) -> list[tuple]:
    """Rows ``(lo, hi, tokens, straight, accelerating, braking)`` over mean-speed bands [m/s] of ``traj`` [V, 6, 3];
    ``straight``: final heading within 0.05 rad of the start."""
    step = np.hypot(np.diff(traj[..., 0], axis=1), np.diff(traj[..., 1], axis=1)) / DT_S  # [V, 5] m/s
    v_mean = step.mean(axis=1)
    accel = (step[:, -1] - step[:, 0]) / (DT_S * (step.shape[1] - 1))  # [V] m/s^2
    straight = np.abs(traj[:, -1, 2]) < 0.05
    rows = []
    for lo in np.arange(10.0, top, band):
        m = (v_mean >= lo) & (v_mean < lo + band)
        rows.append((lo, lo + band, int(m.sum()), int((m & straight).sum()), int((m & (accel > threshold)).sum()),
                     int((m & (accel < -threshold)).sum())))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default=None, help="policy whose vocabulary is read (default: the shipped r1sim-nano)")
    ap.add_argument("--threshold", type=float, default=0.5, help="[m/s^2] in-token acceleration that counts")
    ap.add_argument("--band", type=float, default=4.0, help="[m/s] width of a mean-speed band")
    a = ap.parse_args(argv)

    from r1sim_sumo.model.checkpoint import load_policy

    vocab = load_policy(a.checkpoint).vocab if a.checkpoint else load_policy().vocab
    print(f"{a.checkpoint or 'r1sim-nano'}: vehicle tokens by mean speed, in-token acceleration beyond +-{a.threshold:g} m/s^2")
    print("  mean speed [m/s]   tokens   straight   accelerating   braking")
    for lo, hi, n, s, up, down in speed_change_table(vocab.traj[0], a.threshold, a.band):
        print(f"  {lo:5.0f}-{hi:<5.0f}        {n:6d}   {s:8d}   {up:12d}   {down:7d}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
