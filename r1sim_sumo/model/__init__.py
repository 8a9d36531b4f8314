"""Policy model: SMART-style next-token prediction over motion tokens with a KV-cached rollout step.

``TrafficPolicy(PolicyConfig.preset("nano"), token_traj)``; checkpoints via :func:`save_checkpoint` /
:func:`load_checkpoint` / :func:`load_policy`.
"""

from r1sim_sumo.model.checkpoint import (
    CheckpointError,
    Policy,
    bundled_checkpoints,
    load_checkpoint,
    load_policy,
    save_checkpoint,
)
from r1sim_sumo.model.config import PRESETS, PolicyConfig
from r1sim_sumo.model.policy import MapContext, RolloutCache, TrafficPolicy

__all__ = [
    "PolicyConfig", "PRESETS", "TrafficPolicy", "MapContext", "RolloutCache",
    "Policy", "CheckpointError", "save_checkpoint", "load_checkpoint", "load_policy", "bundled_checkpoints",
]
