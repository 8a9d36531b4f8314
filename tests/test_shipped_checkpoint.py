"""The shipped default policy loads with no argument, is complete on its own, and drives a rollout."""

import json

import torch

import r1sim_sumo
from r1sim_sumo.model.synthetic import synthetic_batch
from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.samplers import parse_sampler


def test_default_checkpoint_loads_and_matches_its_card():
    pol = r1sim_sumo.load_policy()
    assert pol.path is not None and pol.path.name == "r1sim-nano"
    info = json.loads((pol.path / "checkpoint.json").read_text())
    assert pol.vocab.fingerprint() == info["vocab_fingerprint"]
    assert 0.7e6 <= pol.model.num_parameters() <= 1.5e6  # the "nano" size class
    card = (pol.path / "MODEL_CARD.md").read_text()
    assert "unigram" in card and "constant_velocity" in card
    assert (pol.path / "model.safetensors").stat().st_size < 20e6  # a few MB, fine for the wheel


def test_default_checkpoint_rolls_out():
    torch.set_num_threads(1)
    pol = r1sim_sumo.load_policy()
    tr = [torch.as_tensor(pol.vocab.traj[t]) for t in range(3)]
    batch = synthetic_batch(tr, num_scenes=1, num_agents=6, num_map_tokens=80, seed=0)
    r = rollout(pol.model, pol.vocab, batch, num_rollouts=2, sampler=parse_sampler("topk:5"), generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(r.xy_10hz).all() and r.token.shape == (2, 1, 6, 16)
