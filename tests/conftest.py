"""Shared fixtures: a small untrained nano policy on a synthetic vocabulary (tests need no checkpoint)."""

from types import SimpleNamespace

import pytest
import torch


@pytest.fixture(scope="module")
def policy():
    from r1sim_sumo.model.config import PolicyConfig
    from r1sim_sumo.model.policy import TrafficPolicy
    from r1sim_sumo.model.synthetic import synthetic_vocab
    from r1sim_sumo.tokens.motion_vocab import MotionVocab

    torch.set_num_threads(1)
    torch.manual_seed(0)
    tr = synthetic_vocab((128, 32, 32))
    vocab = MotionVocab.from_traj({i: t.numpy() for i, t in enumerate(tr)})
    model = TrafficPolicy(PolicyConfig.preset("nano", vocab_sizes=vocab.sizes), [torch.as_tensor(vocab.traj[i]) for i in range(3)])
    return SimpleNamespace(model=model.eval(), vocab=vocab)
