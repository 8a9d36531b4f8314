"""``r1sim ablate`` at tiny scale: 2 scenes, 2 rollouts, 1 seed, 2 fine-tune iterations per model."""

from __future__ import annotations

import argparse
import json

import pytest

pytestmark = pytest.mark.sumo


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    from r1sim_sumo.data.sumo_reference import SumoGenConfig, generate_sumo_scenarios
    from r1sim_sumo.scenario import write_dataset

    root = tmp_path_factory.mktemp("ablate_data")
    cfg = SumoGenConfig(network="urban_intersection", seed=0, duration_s=12.0, warmup_s=40.0, stride_steps=25,
                        demand_scale=0.3)
    write_dataset(root, generate_sumo_scenarios(cfg))
    return root


def test_ablate_writes_tables_and_plots(policy, tiny_data, tmp_path):
    from r1sim_sumo.commands import ablate
    from r1sim_sumo.model.checkpoint import save_checkpoint
    from r1sim_sumo.scenario import ScenarioDataset

    assert len(ScenarioDataset(tiny_data)) >= 2
    il = save_checkpoint(tmp_path / "il", policy.model, policy.vocab)
    p = argparse.ArgumentParser()
    ablate.add_arguments(p)
    out = tmp_path / "ablate"
    args = p.parse_args([
        "--data", str(tiny_data), "--il", str(il), "--train-budget-iters", "2", "--train-data", str(tiny_data),
        "--train-set", "num_rollouts=2", "batch_scenes=1", "num_steps=2", "ppo_epochs=1", "num_minibatches=1",
        "freeze=head", "threads=1", "sampler=topk:8",
        "--rewards", "or", "spr", "--rollouts", "2", "--seeds", "0", "--max-scenarios", "2", "--threads", "1",
        "--easy-hard-quantile", "0.5", "--out", str(out),
    ])
    assert ablate.run(args) == 0
    md = (out / "ablation.md").read_text()
    for row in ("| topk:32 | IL |", "| entropy:16,80 | IL |", "| topk:32 | SFT |", "| topk:32 | GRPO-standard |",
                "| entropy:16,80 | GRPO-refined |", "| Sampling | topk:32 (IL) |", "| Optimization | SFT (entropy:16,80) |",
                "| OR |", "| SPR |"):
        assert row in md, row
    assert "| APR |" not in md  # not requested
    for png in ("training_curves.png", "entropy_before_after.png"):
        assert (out / png).stat().st_size > 5000
    res = json.loads((out / "ablation.json").read_text())
    assert set(res["models"]) == {"il", "sft", "grpo-std", "grpo", "reward-or"}
    assert "Runs with a log.csv: sft, grpo-std, grpo, reward-or." in md
    assert 0.0 <= res["summary"]["grpo|entropy:16,80"]["realism/rmm"] <= 1.0
    for k in ("sft", "grpo-std", "grpo", "reward-or"):
        assert (out / "train" / k / "log.csv").read_text().count("\n") == 3  # header + 2 iterations


def test_training_plot_skips_an_il_model_whose_folder_holds_a_pretraining_log(tmp_path):
    """The IL checkpoint's run folder may hold a pretraining log.csv (``step``, no ``iter``): the plot shows the
    fine-tunes and skips it instead of failing after every evaluation has run (session 26)."""
    from r1sim_sumo.commands import ablate

    il, ft = tmp_path / "pretrain", tmp_path / "grpo"
    (il / "final").mkdir(parents=True)
    (ft / "final").mkdir(parents=True)
    (il / "log.csv").write_text("step,loss\n1,2.0\n2,1.5\n")
    (ft / "log.csv").write_text("iter,reward,collision_rate,distance_m\n1,0.5,0.1,3.0\n2,0.6,0.08,2.8\n")
    plotted = ablate.plot_training({"il": str(il / "final"), "grpo": str(ft / "final")}, tmp_path / "curves.png")
    assert plotted == ["grpo"] and (tmp_path / "curves.png").stat().st_size > 0
