"""Dataset recipe: seed-disjoint splits, held-out network, build, YAML overrides, CLI guards."""

from __future__ import annotations

import json

import pytest

from r1sim_sumo import cli
from r1sim_sumo.commands.generate import parse_seeds
from r1sim_sumo.config import ConfigError
from r1sim_sumo.data.dataset import (
    DatasetRecipe,
    GenerationError,
    HighwayGenJob,
    build_dataset,
    run_generation_jobs,
)
from r1sim_sumo.resources import configs_dir
from r1sim_sumo.scenario import ScenarioDataset

TINY = DatasetRecipe(networks=("motorway_merge", "lane_drop"), heldout_networks=("lane_drop",), train_seeds=2,
                     val_seeds=1, test_seeds=1, duration_s=11.1, warmup_s=5.0, highway_envs=())


def _seeds_and_nets(recipe: DatasetRecipe):
    jobs = recipe.jobs()
    sumo = {s: {(j.network, j.seed) for j in js if hasattr(j, "network")} for s, js in jobs.items()}
    hw = {s: {(j.env_name, j.seed) for j in js if hasattr(j, "env_name")} for s, js in jobs.items()}
    return sumo, hw


def test_recipe_splits_hold_out_seeds_and_network():
    sumo, hw = _seeds_and_nets(TINY.__class__(**{**TINY.to_dict(), "highway_envs": ("merge-v0",)}))
    seeds = {s: {seed for _, seed in v} for s, v in sumo.items()}
    assert seeds["train"] == {0, 1} and not seeds["train"] & seeds["val"] and not seeds["train"] & seeds["test"]
    assert not seeds["val"] & seeds["test"]
    nets = {s: {n for n, _ in v} for s, v in sumo.items()}
    assert nets == {"train": {"motorway_merge"}, "val": {"motorway_merge"}, "test": {"motorway_merge", "lane_drop"}}
    hw_seeds = {s: {seed for _, seed in v} for s, v in hw.items()}
    assert all(hw_seeds[a].isdisjoint(hw_seeds[b]) for a in hw_seeds for b in hw_seeds if a != b)


def test_default_recipe_gives_20k_training_windows_and_matches_yaml():
    r = DatasetRecipe()
    assert "roundabout" in r.heldout_networks
    assert r.expected_sumo_windows("train") >= 20_000
    assert "roundabout" not in r.split_networks("train") + r.split_networks("val")
    assert DatasetRecipe.from_yaml(configs_dir() / "dataset.yaml") == r


def test_yaml_overrides_and_unknown_key(tmp_path):
    p = tmp_path / "d.yaml"
    p.write_text("train_seeds: 3\nhighway_envs: [merge-v0]\n")
    r = DatasetRecipe.from_yaml(p, base=DatasetRecipe.small())
    assert r.train_seeds == 3 and r.highway_envs == ("merge-v0",) and r.duration_s == DatasetRecipe.small().duration_s
    p.write_text("train_seed: 3\n")
    with pytest.raises(ConfigError, match="train_seed"):
        DatasetRecipe.from_yaml(p)


@pytest.mark.sumo
def test_build_dataset_splits_by_seed_and_network(tmp_path):
    out = build_dataset(tmp_path / "ds", TINY, workers=2, progress=False)
    info = json.loads((out / "splits.json").read_text())
    assert info["heldout_networks"] == ["lane_drop"]
    sp = info["splits"]
    assert sp["train"]["sumo"] == {"networks": ["motorway_merge"], "seeds": [0, 1]}
    assert sp["test"]["sumo"]["networks"] == ["lane_drop", "motorway_merge"]
    seen = {}
    for split in ("train", "val", "test"):
        ds = ScenarioDataset(out / split)
        assert len(ds) == sp[split]["num_scenarios"] > 0
        seen[split] = {(s.metadata["network"], s.metadata["seed"]) for s in ds}
    assert all(n != "lane_drop" for n, _ in seen["train"] | seen["val"])
    assert any(n == "lane_drop" for n, _ in seen["test"])
    seeds = {k: {s for _, s in v} for k, v in seen.items()}
    assert seeds["train"].isdisjoint(seeds["val"] | seeds["test"]) and seeds["val"].isdisjoint(seeds["test"])
    assert not (out / ".staging").exists()


@pytest.mark.highway
def test_highway_job_through_the_pool(tmp_path):
    out = run_generation_jobs([HighwayGenJob("merge-v0", seed=0, episode_s=9.1)], tmp_path / "hw", workers=1,
                              progress=False)
    ds = ScenarioDataset(out)
    assert len(ds) == 1 and ds[0].metadata["source"] == "highway-env" and ds[0].num_steps == 91


def test_cli_refuses_existing_folder_and_bad_seeds(tmp_path, capsys):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    assert cli.main(["dataset", "build", "--out", str(tmp_path / "x"), "--size", "small"]) == 1
    assert "refusing to overwrite" in capsys.readouterr().err
    assert cli.main(["generate", "sumo", "--networks", "motorway_merge", "--out", str(tmp_path / "x")]) == 1
    assert (tmp_path / "x" / "keep.txt").read_text() == "mine"
    assert parse_seeds("0-3") == [0, 1, 2, 3] and parse_seeds("5,1-2") == [1, 2, 5]
    with pytest.raises(Exception, match="seeds"):
        parse_seeds("3-1")
    with pytest.raises(GenerationError, match="no generation jobs"):
        run_generation_jobs([], tmp_path / "empty", progress=False)
