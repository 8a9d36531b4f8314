"""Widening a trained policy (r1sim_sumo.model.widen): the wider model predicts what the narrow one does, its new
units are not twins, and the command writes a loadable checkpoint."""

import pytest
import torch

from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.policy import TrafficPolicy
from r1sim_sumo.model.synthetic import synthetic_batch, synthetic_vocab
from r1sim_sumo.model.widen import widen_model


def _narrow(seed=0):
    torch.manual_seed(seed)
    cfg = PolicyConfig.preset("nano", agent_k=8, map_agent_k=8, map_k=8, dropout=0.0, agent_layers=2,
                              desired_speed_input=True, speed_trend_input=True)
    voc = synthetic_vocab(cfg.vocab_sizes)
    model = TrafficPolicy(cfg, voc).eval()
    with torch.no_grad():  # the added inputs start at zero output; give them weights so that they count
        for emb in (model.desired_speed_emb, model.speed_trend_emb):
            emb.lin2.weight.normal_(0, 0.1)
    return model, voc


@pytest.mark.parametrize("noise", [0.0, 0.05])
def test_the_wider_model_gives_the_narrow_models_logits(noise):
    narrow, voc = _narrow()
    wide = widen_model(narrow, voc, factor=2, noise=noise, seed=1)
    assert wide.config.hidden_dim == 2 * narrow.config.hidden_dim and wide.config.num_heads == 2 * narrow.config.num_heads
    assert sum(p.numel() for p in wide.parameters()) > 2.5 * sum(p.numel() for p in narrow.parameters())
    b = synthetic_batch(voc, num_scenes=2, num_agents=12, num_map_tokens=200, seed=3)
    with torch.no_grad():
        ref, got = narrow(b), wide(b)
    fin = torch.isfinite(ref)
    assert fin.sum() > 1000 and torch.equal(fin, torch.isfinite(got))
    assert (got[fin] - ref[fin]).abs().max() < 1e-3 * ref[fin].abs().max()


def test_the_split_weights_differ_between_the_copies_so_training_can_separate_them():
    narrow, voc = _narrow()
    twins = widen_model(narrow, voc, noise=0.0)
    split = widen_model(narrow, voc, noise=0.05)
    D = narrow.config.hidden_dim
    w0 = twins.head[1].weight  # [2D, 2D]: columns consume [x, x]
    assert torch.equal(w0[:, :D], w0[:, D:])
    w = split.head[1].weight
    assert not torch.allclose(w[:, :D], w[:, D:])
    assert torch.allclose(w[:, :D] + w[:, D:], 2 * w0[:, :D], atol=1e-6)  # the parts still sum to the narrow map


def test_widen_command_writes_a_checkpoint_that_loads(tmp_path, policy):
    from r1sim_sumo.model.checkpoint import load_checkpoint, save_checkpoint
    from r1sim_sumo.model.widen import main

    save_checkpoint(tmp_path / "narrow", policy.model, policy.vocab)
    out = tmp_path / "wide"
    assert main([str(tmp_path / "narrow"), str(out)]) == 0
    wide = load_checkpoint(out)
    assert wide.config.hidden_dim == 2 * policy.config.hidden_dim
    assert wide.info["training"]["widened_from"]["factor"] == 2
    with pytest.raises(SystemExit):
        main([str(tmp_path / "narrow"), str(out)])  # never overwrites
