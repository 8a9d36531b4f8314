"""scripts/compare_cards.py: issue 19's three card targets are read from model_card.json, per network for offroad."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


def _card(folder: Path, collision: float, offroad: dict[str, float], rmm: float, rollouts: int = 8) -> Path:
    folder.mkdir(parents=True)

    def real(c, o, r):
        return {"realism/collision_rate": c, "realism/offroad_rate_log_window": o, "realism/rmm": r}

    card = {"token_metrics": {"policy": {"nll": 0.95}},
            "closed_loop": {"rollouts": rollouts,
                            "overall": {"policy": real(collision, sum(offroad.values()) / len(offroad), rmm),
                                        "constant_velocity": real(0.25, 0.16, 0.50),
                                        "log_replay": real(0.0, 0.0, 0.90)},
                            "per_network": {n: {"policy": real(collision, o, rmm)}
                                            for n, o in offroad.items()}}}
    (folder / "model_card.json").write_text(json.dumps(card))
    return folder


def test_targets_hold_only_when_every_network_is_under_the_offroad_bound(tmp_path, capsys, repo_script):
    mod = repo_script("scripts/compare_cards.py")
    good = _card(tmp_path / "good", 0.029, {"lane_drop": 0.049, "roundabout": 0.040}, 0.83)
    one_net = _card(tmp_path / "one_net", 0.029, {"lane_drop": 0.051, "roundabout": 0.010}, 0.83)
    weak = _card(tmp_path / "weak", 0.031, {"lane_drop": 0.01, "roundabout": 0.01}, 0.77)
    r = mod.card_row(good)
    assert r["targets"] == {"collision": True, "offroad": True, "rmm": True}
    assert r["gap"] == pytest.approx(0.825)
    assert mod.card_row(one_net)["targets"]["offroad"] is False  # the mean is 0.03, one network is above 0.05
    assert mod.card_row(weak)["targets"] == {"collision": False, "offroad": True, "rmm": False}  # gap 0.675
    assert mod.main([str(good), str(one_net), str(weak)]) == 0
    out = capsys.readouterr().out
    assert "| good | 8 | 0.950 | 0.0290 |" in out and "3/3 |" in out
    assert "2/3 (missed: offroad)" in out and "1/3 (missed: collision, rmm)" in out


def test_a_folder_without_a_card_names_the_command_that_writes_one(tmp_path, repo_script):
    mod = repo_script("scripts/compare_cards.py")
    with pytest.raises(FileNotFoundError, match="model_card"):
        mod.card_row(tmp_path)
