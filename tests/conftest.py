"""Shared fixtures: a small untrained nano policy on a synthetic vocabulary (tests need no checkpoint)."""

import pytest
import torch

from r1sim_sumo.model.untrained import untrained_policy


@pytest.fixture(scope="module")
def policy():
    torch.set_num_threads(1)
    return untrained_policy(seed=0)
