"""Ending lanes as a map token kind (issue 19, session 41): which lanes end beside one that goes on, their tokens'
kind, models of two kinds reading them as lane centres, a third kind added to a trained model without changing its
logits, and version-1 compact datasets read with the kinds a rebuild would write."""

import json
import shutil

import numpy as np
import pytest
import torch

from r1sim_sumo.model.config import PolicyConfig
from r1sim_sumo.model.packed import loss_mask
from r1sim_sumo.model.policy import TrafficPolicy
from r1sim_sumo.model.synthetic import synthetic_batch, synthetic_vocab
from r1sim_sumo.scenario import MapPolylines
from r1sim_sumo.tokens.map_tokens import ENDING_LANE, tokenize_map


def _seg(x0, x1, y):
    return np.stack([np.linspace(x0, x1, 5), np.full(5, y)], 1)


def _merge_map():
    """``acc_0`` (y = 0, x 0..200 m) ends beside ``acc_1`` (y = 3.5 m), which goes on to ``main_0``; ``exit_0`` ends
    with no sibling (a network exit); ``acc#left`` is a road edge."""
    return MapPolylines.from_lists([_seg(0, 200, 0.0), _seg(0, 200, 3.5), _seg(200, 400, 3.5), _seg(-100, 0, -30.0),
                                    _seg(0, 200, 5.3)], [0, 0, 0, 0, 1],
                                   ["acc_0", "acc_1", "main_0", "exit_0", "acc#left"], [30.0] * 4 + [0.0],
                                   [3.5] * 4 + [0.0], successors=[(1, 2)])


def test_ending_lanes_are_lanes_that_end_beside_one_that_goes_on():
    m = _merge_map()
    assert m.ending_lanes() == [0]
    assert m.select([0, 1, 3, 4]).ending_lanes() == []  # cut without the connectivity: nothing marked
    hw = MapPolylines.from_lists([_seg(0, 100, 0.0), _seg(0, 100, 4.0), _seg(100, 200, 4.0)], [0, 0, 0],
                                 ["b->c#0", "b->c#1", "c->d#0"], [30.0] * 3, [4.0] * 3, successors=[(1, 2)])
    assert hw.ending_lanes() == [0]  # highway-env ids: the edge is what comes before '#'


@pytest.mark.sumo
def test_the_bundled_merges_ending_lanes():
    from r1sim_sumo.adapters.sumo_map import read_sumo_map
    from r1sim_sumo.resources import networks_dir

    got = {}
    for net in ("motorway_merge", "lane_drop", "roundabout"):
        m = read_sumo_map(next((networks_dir() / net).glob("*.net.xml")))
        m = getattr(m, "polylines", m)
        got[net] = [str(m.lane_id[j]) for j in m.ending_lanes()]
    assert got == {"motorway_merge": ["merge_0"], "lane_drop": ["pre_drop_0"], "roundabout": []}


def test_the_tokens_of_an_ending_lane_are_kind_2_and_the_others_keep_their_polylines_kind():
    m = _merge_map()
    t = tokenize_map(m)
    assert (t.kind[t.polyline == 0] == ENDING_LANE).all() and (t.polyline == 0).sum() == 40  # 200 m in 5 m tokens
    assert (t.kind[t.polyline != 0] == np.asarray(m.kind, np.int64)[t.polyline[t.polyline != 0]]).all()


def _model(num_map_kinds, seed=0):
    torch.manual_seed(seed)
    cfg = PolicyConfig.preset("nano", agent_k=8, map_agent_k=8, map_k=8, dropout=0.0, agent_layers=2,
                              num_map_kinds=num_map_kinds)
    voc = synthetic_vocab(cfg.vocab_sizes)
    return TrafficPolicy(cfg, voc).eval(), voc


def _batch_with_ending_lanes(voc):
    b = synthetic_batch(voc, num_scenes=2, num_agents=12, num_map_tokens=200, seed=3)
    g = torch.Generator().manual_seed(3)
    b = b._replace(map_pos=b.map_pos + torch.rand(b.map_pos.shape, generator=g) * 0.01)
    ending = (b.map_kind == 0) & (torch.rand(b.map_kind.shape, generator=g) < 0.3)
    assert ending.sum() > 20
    return b._replace(map_kind=torch.where(ending, torch.full_like(b.map_kind, ENDING_LANE), b.map_kind)), ending


def test_a_two_kind_model_reads_an_ending_lane_as_a_lane_centre():
    model, voc = _model(2)
    b, ending = _batch_with_ending_lanes(voc)
    as_lane = b._replace(map_kind=torch.where(ending, torch.zeros_like(b.map_kind), b.map_kind))
    with torch.no_grad():
        mask = loss_mask(b)
        assert torch.equal(model(b), model(as_lane))  # padded forward
        assert torch.equal(model(b, out_mask=mask), model(as_lane, out_mask=mask))  # packed forward


def test_a_third_map_kind_starts_from_the_trained_models_logits_and_then_tells_ending_lanes_apart():
    from types import SimpleNamespace

    from r1sim_sumo.train.pretrain import load_init_weights

    old, voc = _model(2, seed=0)
    new, _ = _model(3, seed=1)
    load_init_weights(new, SimpleNamespace(model=old, config=old.config), "old")
    assert torch.equal(new.map_kind.weight[2], old.map_kind.weight[0])
    b, _ = _batch_with_ending_lanes(voc)
    with torch.no_grad():
        mask = loss_mask(b)
        assert torch.equal(new(b, out_mask=mask), old(b, out_mask=mask))
        new.map_kind.weight[2] += 0.5  # what training can now learn: the ending lane's own embedding
        assert not torch.allclose(new(b, out_mask=mask), old(b, out_mask=mask))
    wrong, _ = _model(3, seed=1)
    with pytest.raises(ValueError, match="init_checkpoint"):  # fewer kinds than the start is still refused
        load_init_weights(old, SimpleNamespace(model=wrong, config=wrong.config), "wrong")


@pytest.fixture(scope="module")
def merge_tokens(tmp_path_factory):
    """A compact dataset of highway-env merge scenes whose merging lane ``b->c#2`` ends (its fallback successor taken
    out of the maps), built by this version (format 2)."""
    from r1sim_sumo.data.highway_reference import generate_highway_scenarios
    from r1sim_sumo.scenario import write_dataset
    from r1sim_sumo.tokens.compact import build_compact
    from r1sim_sumo.tokens.motion_vocab import VocabBuildConfig
    from r1sim_sumo.tokens.vocab_build import build_vocab_from_dataset

    root = tmp_path_factory.mktemp("ending")
    scs = generate_highway_scenarios("merge-v0", seed=0, n_episodes=1, episode_s=12.0, stride_steps=10, progress=False)
    for sc in scs:
        ids = np.asarray(sc.map.lane_id)
        keep = ids[sc.map.successors[:, 0]] != "b->c#2"
        sc.map.successors = sc.map.successors[keep]
        assert [str(ids[j]) for j in sc.map.ending_lanes()] == ["b->c#2"]
    write_dataset(root / "train", scs, shard_size=4)
    vocab, _ = build_vocab_from_dataset(scs, VocabBuildConfig(size=(64, 16, 16), heldout_fraction=0.0,
                                                              min_real_segments=10, n_synthetic=500))
    build_compact(root, vocab, root / "tokens", splits=("train",), workers=1, progress=False)
    return root / "tokens"


@pytest.mark.highway
def test_a_version_1_compact_folder_is_read_with_the_kinds_a_rebuild_writes(merge_tokens, tmp_path):
    from r1sim_sumo.tokens.compact import MANIFEST, CompactFormatError, CompactTokenDataset, _write_xz

    built = CompactTokenDataset(merge_tokens, "train")
    assert (built.a["map_kind"] == ENDING_LANE).sum() > 10
    old = tmp_path / "v1"  # what session 38-40 builds wrote: no kind 2, format_version 1
    shutil.copytree(merge_tokens, old)
    arrays = dict(built.a)
    arrays["map_kind"] = np.where(arrays["map_kind"] == ENDING_LANE, 0, arrays["map_kind"]).astype(np.int8)
    man = json.loads((old / MANIFEST).read_text())
    man["format_version"] = 1
    man["splits"]["train"]["arrays"] = _write_xz(old / "train.xz", arrays, 1)
    (old / MANIFEST).write_text(json.dumps(man))
    read = CompactTokenDataset(old, "train")
    assert np.array_equal(read.a["map_kind"], built.a["map_kind"])
    for i in range(len(read)):
        assert np.array_equal(read[i].map.kind, built[i].map.kind)
    (old / "train.polylines.npz").unlink()
    with pytest.raises(CompactFormatError, match="train.polylines.npz.*format_version 1.*r1sim tokens build"):
        CompactTokenDataset(old, "train")


def test_val_tokens_without_a_val_split_is_refused_with_the_fix(tmp_path):
    from r1sim_sumo.train.pretrain import PretrainConfig, training_datasets

    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "manifest.json").write_text(json.dumps({"format_version": 2, "splits": {"train": {}}}))
    cfg = PretrainConfig(tokens=str(tmp_path / "t"), val_tokens=str(tmp_path / "t"))
    with pytest.raises(ValueError, match="val_tokens.*has no val split.*--splits val"):
        training_datasets(cfg, tmp_path)


@pytest.mark.highway
def test_ending_lane_lr_mult_trains_the_ending_lanes_row_fast_and_freezes_the_others(merge_tokens, tmp_path):
    from safetensors.torch import load_file

    from r1sim_sumo.config import ConfigError
    from r1sim_sumo.train.pretrain import PretrainConfig, pretrain

    kw = dict(tokens=str(merge_tokens), batch_size=2, warmup_steps=1, lr=1e-4, eval_every=100, ckpt_every=100,
              log_every=1, threads=1, model_overrides={"agent_layers": 2, "map_layers": 1, "dropout": 0.0, "num_map_kinds": 3})
    pretrain(PretrainConfig(out_dir=str(tmp_path / "start"), max_steps=2, **kw), progress=False)
    start = str(tmp_path / "start" / "final")
    for mult in (1.0, 30.0):
        pretrain(PretrainConfig(out_dir=str(tmp_path / f"m{mult:g}"), max_steps=4, init_checkpoint=start,
                                ending_lane_lr_mult=mult, **kw), progress=False)
    key = "model.map_kind.weight"
    w0, w1, w30 = (load_file(str(p / "model.safetensors"))[key] for p in
                   (tmp_path / "start" / "final", tmp_path / "m1" / "final", tmp_path / "m30" / "final"))
    assert torch.equal(w30[:ENDING_LANE], w0[:ENDING_LANE])  # the lane centre's and road edge's rows: frozen
    assert not torch.equal(w1[:ENDING_LANE], w0[:ENDING_LANE])  # (trained without the option)
    assert (w30[ENDING_LANE] - w0[ENDING_LANE]).norm() > 10 * (w1[ENDING_LANE] - w0[ENDING_LANE]).norm()
    with pytest.raises(ConfigError, match="ending_lane_lr_mult.*num_map_kinds: 3"):
        pretrain(PretrainConfig(out_dir=str(tmp_path / "two"), max_steps=1, ending_lane_lr_mult=30.0,
                                **{**kw, "model_overrides": {"agent_layers": 2, "map_layers": 1}}), progress=False)
    with pytest.raises(ConfigError, match="ending_lane_lr_mult"):
        PretrainConfig(ending_lane_lr_mult=0.0)
