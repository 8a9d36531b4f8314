"""Data-parallel pretraining: batch sharding equals collating the slice, and 2 gloo processes (the torchrun code
path) follow the single-process loss curve for the same global batch."""

from __future__ import annotations

import csv

import pytest
import torch
from safetensors.torch import load_file
from test_evaluate import curved_scene

from r1sim_sumo.model.synthetic import synthetic_vocab
from r1sim_sumo.scenario import write_dataset
from r1sim_sumo.tokens.batch import collate, tokenize_scenario
from r1sim_sumo.tokens.motion_vocab import MotionVocab
from r1sim_sumo.train.ddp import (
    DistInfo,
    count_loss_tokens,
    global_token_mean,
    shard_batch,
    shard_rows,
)
from r1sim_sumo.train.ddp_launch import spawn_pretrain
from r1sim_sumo.train.pretrain import PretrainConfig, pretrain


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp")
    scs = [curved_scene(s, n_agents=2 + s % 4) for s in range(8)]  # different agent counts: padding differs by rank
    write_dataset(root / "train", scs, shard_size=4)
    torch.manual_seed(0)
    vocab = MotionVocab.from_traj({i: t.numpy() for i, t in enumerate(synthetic_vocab((64, 16, 16)))})
    vocab.save(root / "vocab.safetensors")
    return root, scs, vocab


def test_shard_rows_cover_the_batch_once():
    rows = [shard_rows(7, DistInfo(rank=r, world_size=3)) for r in range(3)]
    assert [list(r) for r in rows] == [[0, 1, 2], [3, 4], [5, 6]]
    with pytest.raises(ValueError, match="smaller than the number of processes"):
        shard_rows(1, DistInfo(rank=0, world_size=2))


def test_shard_equals_collating_the_slice_and_single_process_is_identity(data):
    _, scs, vocab = data
    scenes = [tokenize_scenario(sc, vocab) for sc in scs[:5]]
    full = collate(scenes)
    assert shard_batch(full, DistInfo()) is full
    for rank, (lo, hi) in enumerate([(0, 3), (3, 5)]):
        part, ref = shard_batch(full, DistInfo(rank=rank, world_size=2)), collate(scenes[lo:hi])
        # NaN (padding / unknown desired speeds) equals NaN here
        assert all(a.shape == b.shape and torch.equal(torch.isnan(a) if a.is_floating_point() else a,
                                                      torch.isnan(b) if b.is_floating_point() else b)
                   and (not a.is_floating_point() or torch.equal(a.nan_to_num(0.0), b.nan_to_num(0.0)))
                   for a, b in zip(part, ref, strict=True))
    loss, acc = torch.tensor(2.0, requires_grad=True), torch.tensor(0.5)
    bwd, logged, acc_out = global_token_mean(loss, acc, count_loss_tokens(full, 18), DistInfo())
    assert bwd is loss and float(logged) == 2.0 and acc_out is acc


def _cfg(root, out) -> PretrainConfig:
    return PretrainConfig(train_data=str(root / "train"), val_data=None, vocab=str(root / "vocab.safetensors"),
                          batch_size=4, max_steps=3, warmup_steps=1, lr=3e-3, ckpt_every=3, log_every=1,
                          out_dir=str(out), threads=1, history_drop_prob=0.5,
                          model_overrides={"agent_layers": 2, "map_layers": 1, "dropout": 0.0})


def _log(out) -> list[tuple[float, float]]:
    return [(float(r["loss"]), float(r["acc"])) for r in csv.DictReader(open(out / "log.csv"))]


def test_two_gloo_processes_match_one_process(data, tmp_path):
    root, _, _ = data
    pretrain(_cfg(root, tmp_path / "single"), progress=False)
    spawn_pretrain(_cfg(root, tmp_path / "ddp"), world_size=2)
    single, ddp = _log(tmp_path / "single"), _log(tmp_path / "ddp")
    assert len(single) == len(ddp) == 3
    assert single[0][0] > single[-1][0]  # it trains, so matching curves mean something
    for (l1, a1), (l2, a2) in zip(single, ddp, strict=True):
        assert l2 == pytest.approx(l1, rel=1e-4) and a2 == pytest.approx(a1, abs=1e-6)
    a = load_file(str(tmp_path / "single" / "final" / "model.safetensors"))
    b = load_file(str(tmp_path / "ddp" / "final" / "model.safetensors"))
    assert a.keys() == b.keys() and max(float((a[k] - b[k]).abs().max()) for k in a) < 1e-4
    assert not (tmp_path / "ddp" / "final" / "rank1").exists() and (tmp_path / "ddp" / "state").is_dir()
