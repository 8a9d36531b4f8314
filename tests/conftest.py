"""Shared fixtures: a small untrained nano policy on a synthetic vocabulary (tests need no checkpoint), and a loader
for the repository's scripts and examples (files, not package modules)."""

import importlib.util
from pathlib import Path

import pytest
import torch

from r1sim_sumo.model.untrained import untrained_policy


@pytest.fixture(scope="module")
def policy():
    torch.set_num_threads(1)
    return untrained_policy(seed=0)


@pytest.fixture(scope="session")
def repo_script():
    """``repo_script("scripts/x.py")``: that file of the repository loaded as a fresh module."""

    def load(relpath: str):
        path = Path(__file__).resolve().parents[1] / relpath
        spec = importlib.util.spec_from_file_location(path.stem, path)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod

    return load
