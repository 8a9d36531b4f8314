"""Regenerating a model card keeps what a person wrote into the previous one."""

import json

import pytest

from r1sim_sumo.train.model_card import kept_from_previous_card


def test_regenerated_card_keeps_notes_and_training_machine(tmp_path):
    (tmp_path / "model_card.json").write_text(json.dumps({
        "notes": ["Trained for 2,500 steps."], "machine": "AMD EPYC, 2 threads shared", "closed_loop": {"overall": {}}}))
    kept = kept_from_previous_card(tmp_path)
    assert kept == {"notes": ["Trained for 2,500 steps."], "machine": "AMD EPYC, 2 threads shared"}
    assert kept_from_previous_card(tmp_path / "missing") == {}


def test_a_broken_previous_card_is_refused_with_its_path(tmp_path):
    (tmp_path / "model_card.json").write_text("{not json")
    with pytest.raises(ValueError, match="model_card.json"):
        kept_from_previous_card(tmp_path)


def _versus_file(tmp_path, results):
    p = tmp_path / "eval_grpo.json"
    p.write_text(json.dumps({"metric": "wosac", "pretrained": "r1sim-nano", "grpo": "runs/x/final",
                             "scenes": ["a", "b"], "results": results}))
    return p


def _metrics(rmm, coll, off):
    return {"realism/rmm": rmm, "realism/rmm/std": 0.002, "realism/collision_rate": coll,
            "realism/collision_rate/std": 0.003, "realism/offroad_rate": off, "realism/offroad_rate/std": 0.001}


def test_fine_tune_card_shows_its_start_and_the_collision_change_per_sampler(tmp_path):
    from r1sim_sumo.train.model_card import load_versus, versus_section

    p = _versus_file(tmp_path, {
        "pretrained (r1sim-nano) / entropy:16,80": _metrics(0.78, 0.15, 0.18),
        "runs/x/final / entropy:16,80": _metrics(0.81, 0.075, 0.16),
        "pretrained (r1sim-nano) / topk:5": _metrics(0.83, 0.04, 0.14),
        "runs/x/final / topk:5": _metrics(0.83, 0.05, 0.14)})
    text = "\n".join(versus_section([load_versus(p)]))
    rows = [ln for ln in text.splitlines() if ln.startswith("| ") and "model" not in ln]
    assert len(rows) == 4
    assert rows[0].startswith("| entropy:16,80 | pretrained (r1sim-nano) |") and rows[0].endswith("| start |")
    assert rows[1].endswith("| -50% |") and "0.0750 ± 0.0030" in rows[1]
    assert rows[3].endswith("| +25% |")
    assert "2 held-out SUMO test scenes" in text


def test_a_versus_file_without_results_is_refused_before_any_rollout(tmp_path):
    from r1sim_sumo.train.model_card import load_versus

    with pytest.raises(ValueError, match="eval_grpo.json.*results"):
        load_versus(_versus_file(tmp_path, {}))
    bad = _versus_file(tmp_path, {"model / topk:5": {"realism/rmm": 0.8}})
    with pytest.raises(ValueError, match="realism/collision_rate"):
        load_versus(bad)
    with pytest.raises(ValueError, match="cannot read"):
        load_versus(tmp_path / "missing.json")


def test_card_names_the_preset_of_a_fine_tune_from_its_model_config():
    from r1sim_sumo.train.model_card import _preset_name

    nano = {"hidden_dim": 64, "num_heads": 4, "map_layers": 2, "agent_layers": 4, "dropout": 0.1}
    assert _preset_name({"config": {"model": "tiny"}}, {"model_config": nano}) == "tiny"  # pretraining names it
    assert _preset_name({"config": {"lr": 3e-5}}, {"model_config": nano}) == "nano"  # a fine-tune does not
    assert _preset_name({}, {"model_config": {**nano, "hidden_dim": 96}}) == "custom"
