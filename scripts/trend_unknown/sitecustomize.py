"""Diagnostic (session 34): the drop-in with the policy's speed-trend input hidden at every decision.

Put this folder on ``PYTHONPATH`` and set ``R1SIM_TREND_OFF=1``: every Python process (the drop-in runs of
``examples/full_horizon_runs.py`` are subprocesses) then passes each decision's token-before-last as "none", so the
model's speed-trend input reads as unknown (as for an agent's first token) while its history tokens are unchanged.
Question it answers: is the give-back after a speeding-up past (``scripts/probe_token_distribution.py
--history-accel=2``) carried by the trend input? Not an option of the package (it did not change arrivals):

    R1SIM_TREND_OFF=1 PYTHONPATH=scripts/trend_unknown python examples/full_horizon_runs.py --out runs/trendoff_s0 \\
        --modes native commands --reuse native --scenarios sumo-game-ramp roundabout sumo-game-grid6 motorway_merge
    R1SIM_TREND_OFF=1 PYTHONPATH=scripts/trend_unknown python scripts/diag_free_road_states.py --scenario sumo-game-ramp
"""

import os

if os.environ.get("R1SIM_TREND_OFF") == "1":
    # isort: off
    import r1sim_sumo  # noqa: F401  first, as everywhere: it sets the OpenMP wait policy before torch loads
    import torch
    # isort: on

    from r1sim_sumo.model.policy import TrafficPolicy

    _step = TrafficPolicy.step

    def _step_trend_unknown(self, cache, step_k, prev_token, pose_xy, pose_yaw, valid, before_token=None):
        if before_token is not None:  # an online decision over remembered features: the trend's second token
            before_token = torch.full_like(before_token, -1)
        return _step(self, cache, step_k, prev_token, pose_xy, pose_yaw, valid, before_token=before_token)

    TrafficPolicy.step = _step_trend_unknown
