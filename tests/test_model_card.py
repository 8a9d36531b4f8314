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
