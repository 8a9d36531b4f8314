"""A randomly initialised policy on the synthetic motion vocabulary, for tests, smoke runs and timing.

Same compute per step as a trained policy of that size; its motion is random. Returned as a
:class:`~r1sim_sumo.model.checkpoint.Policy` like a loaded checkpoint, so every consumer takes either.
"""

from __future__ import annotations

import torch

from r1sim_sumo.model.checkpoint import Policy
from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.policy import TrafficPolicy
from r1sim_sumo.model.synthetic import synthetic_vocab
from r1sim_sumo.tokens.motion_vocab import MotionVocab

UNTRAINED_VOCAB_SIZES = (128, 32, 32)  # tokens per type (vehicle, cyclist, pedestrian)


def untrained_policy(seed: int = 0, preset: str = "nano", **overrides) -> Policy:
    """A ``preset`` policy (``overrides``: :class:`PolicyConfig` fields, e.g. ``desired_speed_input=True``) with
    random weights (``torch.manual_seed(seed)``, which also seeds torch's global generator) on the synthetic vocabulary of :data:`UNTRAINED_VOCAB_SIZES` (always drawn with seed 0, so only the
    weights depend on ``seed``); ``info = {"untrained": True, "preset": ..., "seed": ...}``, ``path = None``."""
    torch.manual_seed(seed)
    traj = synthetic_vocab(UNTRAINED_VOCAB_SIZES)
    vocab = MotionVocab.from_traj({i: t.numpy() for i, t in enumerate(traj)})
    cfg = PolicyConfig.preset(preset, **{**overrides, "vocab_sizes": vocab.sizes})
    model = TrafficPolicy(cfg, [torch.as_tensor(vocab.traj[i]) for i in range(len(traj))])
    return Policy(model=model.eval(), vocab=vocab, config=cfg, info={"untrained": True, "preset": preset, "seed": int(seed)})
