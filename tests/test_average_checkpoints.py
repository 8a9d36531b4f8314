"""Iterate averaging of checkpoints (r1sim_sumo.train.average_checkpoints)."""

import json

import pytest
import torch

from r1sim_sumo.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from r1sim_sumo.model.untrained import untrained_policy
from r1sim_sumo.train.average_checkpoints import average_checkpoints, main


def _save(tmp_path, name, seed, **overrides):
    p = untrained_policy(seed, **overrides)
    return save_checkpoint(tmp_path / name, p.model, p.vocab, extra={"finetune": {"iters": seed}}), p


def test_the_average_is_the_mean_of_every_weight_and_records_its_inputs(tmp_path):
    (a, pa), (b, pb), (c, pc) = (_save(tmp_path, f"it{s}", s) for s in (1, 2, 3))
    out = average_checkpoints([a, b, c], tmp_path / "avg")
    avg = load_checkpoint(out)  # an ordinary checkpoint: hash and vocabulary checked on load
    sa, sb, sc = (p.model.state_dict() for p in (pa, pb, pc))
    for k, v in avg.model.state_dict().items():
        if v.is_floating_point():
            torch.testing.assert_close(v, (sa[k].double() + sb[k].double() + sc[k].double()).div(3).float())
    meta = json.loads((out / "checkpoint.json").read_text())
    assert [i["path"] for i in meta["training"]["average_of"]] == [str(a), str(b), str(c)]
    assert meta["training"]["average_of"][1]["weights_sha256"] == json.loads((b / "checkpoint.json").read_text())["weights"]["sha256"]
    assert meta["training"]["finetune"] == {"iters": 1}  # the first input's training info is kept
    # the mean differs from every input (the seeds give different weights)
    key = next(k for k, v in sa.items() if v.is_floating_point() and v.numel() > 10)
    assert all(not torch.equal(avg.model.state_dict()[key], s[key]) for s in (sa, sb, sc))


def test_checkpoints_of_another_model_or_too_few_inputs_are_refused(tmp_path, capsys):
    a, _ = _save(tmp_path, "a", 1)
    b, _ = _save(tmp_path, "b", 2, desired_speed_input=True)
    with pytest.raises(CheckpointError, match="model_config differs"):
        average_checkpoints([a, b], tmp_path / "avg")
    with pytest.raises(ValueError, match="at least two"):
        average_checkpoints([a], tmp_path / "avg")
    with pytest.raises(ValueError, match="one of the inputs"):
        average_checkpoints([a, b], a)
    assert main([str(tmp_path / "avg"), str(a), str(b)]) == 2
    assert "model_config differs" in capsys.readouterr().err
    assert not (tmp_path / "avg").exists()  # nothing written on a refusal
