"""Tiny end-to-end pretraining on generated highway-env data: the loss falls, and resume is exact."""

import pytest
import torch
from safetensors.torch import load_file

from r1sim_sumo.scenario import write_dataset
from r1sim_sumo.train.pretrain import EpochBatches, PretrainConfig, lr_at, pretrain

pytestmark = pytest.mark.highway


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from r1sim_sumo.data.highway_reference import generate_highway_scenarios
    from r1sim_sumo.tokens.motion_vocab import VocabBuildConfig
    from r1sim_sumo.tokens.vocab_build import build_vocab_from_dataset

    root = tmp_path_factory.mktemp("pt")
    scs = generate_highway_scenarios("merge-v0", seed=0, n_episodes=1, episode_s=16.0, stride_steps=10, progress=False)
    assert len(scs) >= 6
    write_dataset(root / "train", scs[:-2], shard_size=4)
    write_dataset(root / "val", scs[-2:], shard_size=4)
    vocab, _ = build_vocab_from_dataset(scs, VocabBuildConfig(size=(64, 16, 16), heldout_fraction=0.0, min_real_segments=10, n_synthetic=500))
    vocab.save(root / "vocab.safetensors")
    return root


def _cfg(root, out, steps):
    return PretrainConfig(train_data=str(root / "train"), val_data=str(root / "val"), vocab=str(root / "vocab.safetensors"),
                          batch_size=2, max_steps=steps, warmup_steps=1, lr=3e-3, eval_every=100, ckpt_every=3,
                          log_every=1, out_dir=str(out), threads=1, model_overrides={"agent_layers": 2, "map_layers": 1})


def _losses(out):
    import csv

    return [float(r["loss"]) for r in csv.DictReader(open(out / "log.csv"))]


def test_loss_falls_and_checkpoint_loads(data, tmp_path):
    import r1sim_sumo

    final = pretrain(_cfg(data, tmp_path / "run", 12), progress=False)
    losses = _losses(tmp_path / "run")
    assert len(losses) == 12
    assert sum(losses[-3:]) / 3 < sum(losses[:3]) / 3 - 0.1
    pol = r1sim_sumo.load_policy(final)
    assert pol.vocab.sizes == (64, 16, 16)


def test_resume_after_interruption_is_exact(data, tmp_path):
    pretrain(_cfg(data, tmp_path / "full", 6), progress=False)
    # "killed" after step 4: the last periodic checkpoint is step 3, so step 4 is recomputed on resume
    assert pretrain(_cfg(data, tmp_path / "cut", 6), progress=False, stop_at_step=4) is None
    with pytest.raises(FileExistsError):
        pretrain(_cfg(data, tmp_path / "cut", 6), progress=False)  # refuses to overwrite without --resume
    pretrain(_cfg(data, tmp_path / "cut", 6), resume=True, progress=False)
    a = load_file(str(tmp_path / "full" / "final" / "model.safetensors"))
    b = load_file(str(tmp_path / "cut" / "final" / "model.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert _losses(tmp_path / "full") == _losses(tmp_path / "cut")  # no lost or repeated steps in the log


def test_schedule_and_batches():
    cfg = PretrainConfig(lr=1.0, warmup_steps=10, max_steps=110, min_lr_ratio=0.1)
    assert lr_at(0, cfg) == pytest.approx(0.1) and lr_at(9, cfg) == pytest.approx(1.0)
    assert lr_at(110, cfg) == pytest.approx(0.1) and lr_at(60, cfg) == pytest.approx(0.55)
    eb = EpochBatches(10, 3, seed=0)
    first_epoch = sum((eb(s) for s in range(3)), [])
    assert len(set(first_epoch)) == 9 and eb(0) == EpochBatches(10, 3, seed=0)(0) and eb(3) != eb(0)


def test_noised_matching_trains_resumes_exactly_and_is_validated(data, tmp_path):
    from dataclasses import replace

    from r1sim_sumo.config import ConfigError

    noisy = lambda out, steps: replace(_cfg(data, out, steps), token_noise_top_k=3)  # noqa: E731
    pretrain(noisy(tmp_path / "full", 6), progress=False)
    assert pretrain(noisy(tmp_path / "cut", 6), progress=False, stop_at_step=4) is None
    pretrain(noisy(tmp_path / "cut", 6), resume=True, progress=False)
    pretrain(_cfg(data, tmp_path / "exact", 6), progress=False)
    a, b, c = (load_file(str(tmp_path / r / "final" / "model.safetensors")) for r in ("full", "cut", "exact"))
    assert all(torch.equal(a[k], b[k]) for k in a)  # the noise depends on (seed, step, scene) only
    assert any(not torch.equal(a[k], c[k]) for k in a)  # and it changes the training targets
    with pytest.raises(ConfigError, match="token_noise_top_k"):
        PretrainConfig(token_noise_top_k=0)
    # noise that keeps the speed: another draw than the free noise, and a bad tolerance is named
    pretrain(replace(noisy(tmp_path / "kept", 6), token_noise_speed_tol_mps=0.0), progress=False)
    d = load_file(str(tmp_path / "kept" / "final" / "model.safetensors"))
    assert any(not torch.equal(a[k], d[k]) for k in a)
    with pytest.raises(ConfigError, match="token_noise_speed_tol_mps"):
        PretrainConfig(token_noise_speed_tol_mps=-0.1)
    with pytest.raises(ConfigError, match="token_noise_speed_tol_mps"):
        PretrainConfig(token_noise_speed_tol_mps=[0.3])
    PretrainConfig(token_noise_speed_tol_mps=[0.3, 0.0])  # slower-only: a valid band
    for key in ("eval_every", "log_every", "ckpt_every"):  # once crashed mid-run with a ZeroDivisionError
        with pytest.raises(ConfigError, match=f"'{key}'.*max_steps"):
            PretrainConfig(**{key: 0})


def test_checkpoint_from_state_exports_the_states_weights(data, tmp_path):
    """scripts/checkpoint_from_state.py: a run stopped between kept checkpoints exports its last state as a loadable
    checkpoint, equal to the checkpoint kept at that step."""
    import importlib.util
    from dataclasses import replace
    from pathlib import Path

    import r1sim_sumo

    out = tmp_path / "cut"
    cfg = replace(_cfg(data, out, 6), keep_every=3)
    assert pretrain(cfg, progress=False, stop_at_step=5) is None  # state at step 3, ckpt-000003 kept
    spec = importlib.util.spec_from_file_location("cfs", Path(__file__).parents[1] / "scripts" / "checkpoint_from_state.py")
    cfs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cfs)
    assert cfs.main([str(out), "--like", str(out / "ckpt-000003"), "--out", str(out / "exported")]) == 0
    kept = r1sim_sumo.load_policy(out / "ckpt-000003")
    exported = r1sim_sumo.load_policy(out / "exported")
    a, b = kept.model.state_dict(), exported.model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert exported.info["training"]["train"]["steps"] == 3
    with pytest.raises(SystemExit, match="exists"):  # nothing is overwritten
        cfs.main([str(out), "--like", str(out / "ckpt-000003"), "--out", str(out / "exported")])
