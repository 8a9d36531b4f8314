"""Shipping a checkpoint as a bundled policy: weights unchanged, lineage recorded, broken input refused."""

import json

import pytest
import yaml

from r1sim_sumo.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from r1sim_sumo.model.untrained import untrained_policy
from r1sim_sumo.train.ship import lineage, ship


@pytest.fixture()
def chain(tmp_path):
    """bundled/base (shipped) -> runs/pre/ckpt-000010 (pretrain) -> runs/ft/ckpt-000005 (GRPO fine-tune)."""
    pol = untrained_policy(seed=1)
    bundled = tmp_path / "bundled"
    save_checkpoint(bundled / "base", pol.model, pol.vocab, {"train": {"steps": 7, "segments": [{"steps": "0-7", "what": "first"}]}})
    pre = tmp_path / "runs" / "pre"
    save_checkpoint(pre / "ckpt-000010", pol.model, pol.vocab,
                    {"train": {"steps": 10, "cpu_hours": 0.25, "init_checkpoint": "base", "config": {"lr": 1e-3}}})
    (pre / "config.yaml").write_text(yaml.safe_dump({"init_checkpoint": "base", "lr": 1e-3}))
    (pre / "log.csv").write_text("step,loss\n10,2.0\n")
    ft = tmp_path / "runs" / "ft"
    save_checkpoint(ft / "ckpt-000005", pol.model, pol.vocab, {"finetune": {"iters": 5, "method": "grpo"}})
    (ft / "config.yaml").write_text(yaml.safe_dump({"init_checkpoint": str(pre / "ckpt-000010"), "method": "grpo"}))
    (ft / "log.csv").write_text("iter,reward\n5,0.7\n")
    return bundled, pre / "ckpt-000010", ft / "ckpt-000005"


def test_lineage_walks_back_to_the_shipped_policy(chain):
    bundled, pre, ft = chain
    got = lineage(ft, bundled)
    assert [e["kind"] for e in got] == ["shipped", "pretrain", "finetune"]
    assert got[0]["segments"] == [{"steps": "0-7", "what": "first"}]
    assert got[1]["steps"] == 10 and got[1]["cpu_hours"] == 0.25 and got[1]["run_config"]["lr"] == 1e-3
    assert got[2]["method"] == "grpo" and got[2]["iters"] == 5 and got[2]["init_checkpoint"] == str(pre)


def test_ship_copies_weights_and_records_lineage(chain):
    bundled, pre, ft = chain
    (bundled / "r1sim-grpo").mkdir()
    (bundled / "r1sim-grpo" / "MODEL_CARD.md").write_text("old card of other weights")
    dest = ship(ft, "r1sim-grpo", bundled)
    src_meta = json.loads((ft / "checkpoint.json").read_text())
    meta = json.loads((dest / "checkpoint.json").read_text())
    assert meta["weights"] == src_meta["weights"]  # same file, same SHA-256
    assert load_checkpoint(dest).config == load_checkpoint(ft).config
    info = meta["training"]["finetune"]
    assert info["shipped_from"] == str(ft) and [e["kind"] for e in info["lineage"]] == ["shipped", "pretrain", "finetune"]
    assert info["cpu_hours_recorded_total"] == 0.25
    assert not (dest / "MODEL_CARD.md").exists()  # the stale card is gone; the card command regenerates it
    assert (dest / "train_log.csv").read_text().startswith("iter,reward")
    assert yaml.safe_load((dest / "finetune_config.yaml").read_text())["method"] == "grpo"


def test_ship_refuses_a_broken_checkpoint_and_leaves_the_bundled_one(chain):
    bundled, pre, ft = chain
    good = ship(pre, "r1sim-nano", bundled)
    before = (good / "model.safetensors").read_bytes()
    w = ft / "model.safetensors"
    w.write_bytes(w.read_bytes()[:-10])
    with pytest.raises(CheckpointError, match="truncated"):
        ship(ft, "r1sim-nano", bundled)
    assert (good / "model.safetensors").read_bytes() == before
    assert load_checkpoint(good) is not None


def test_shipping_again_over_a_shipped_policy_keeps_its_lineage(chain, tmp_path):
    """A run continued from a policy that ship() wrote inherits that policy's whole recorded lineage."""
    bundled, pre, ft = chain
    first = ship(pre, "r1sim-nano", bundled)  # lineage: shipped base -> pre
    pol = untrained_policy(seed=2)
    nxt = tmp_path / "runs" / "next"
    save_checkpoint(nxt / "ckpt-000004", pol.model, pol.vocab,
                    {"train": {"steps": 4, "cpu_hours": 0.5, "init_checkpoint": "r1sim-nano", "config": {}}})
    (nxt / "config.yaml").write_text(yaml.safe_dump({"init_checkpoint": "r1sim-nano"}))
    got = lineage(nxt / "ckpt-000004", bundled)
    assert got[0]["kind"] == "shipped" and got[0]["checkpoint"] == "r1sim-nano"
    inherited = json.loads((first / "checkpoint.json").read_text())["training"]["train"]["lineage"]
    assert got[0]["segments"] == inherited and [e["kind"] for e in inherited] == ["shipped", "pretrain"]


def test_recorded_cpu_hours_count_the_runs_of_the_inherited_lineage(chain, tmp_path):
    from r1sim_sumo.train.ship import flat_runs

    bundled, pre, ft = chain
    ship(pre, "r1sim-nano", bundled)  # 0.25 CPU h
    pol = untrained_policy(seed=2)
    nxt = tmp_path / "runs" / "next"
    save_checkpoint(nxt / "ckpt-000004", pol.model, pol.vocab,
                    {"train": {"steps": 4, "cpu_hours": 0.5, "init_checkpoint": "r1sim-nano", "config": {}}})
    (nxt / "config.yaml").write_text(yaml.safe_dump({"init_checkpoint": "r1sim-nano"}))
    dest = ship(nxt / "ckpt-000004", "r1sim-nano", bundled)
    info = json.loads((dest / "checkpoint.json").read_text())["training"]["train"]
    assert [e["checkpoint"] for e in flat_runs(info["lineage"])] == [str(pre), str(nxt / "ckpt-000004")]
    assert info["cpu_hours_recorded_total"] == 0.75
