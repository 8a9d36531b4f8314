"""scripts/eval_grpo_vs_pretrained.py: an earlier output's pretrained side is reused only for the same setting."""
from __future__ import annotations

import importlib.util
import json
from argparse import Namespace
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "eval_grpo_vs_pretrained.py"


def _script():
    spec = importlib.util.spec_from_file_location("eval_grpo_vs_pretrained", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _earlier(tmp_path, **over) -> Path:
    out = {"metric": "wosac", "pretrained": "runs/start/final", "grpo": "runs/a/final",
           "data": "data/generated/default/val", "seeds": [0, 1], "scenes": ["s1", "s2"],
           "results": {"pretrained (runs/start/final) / topk:5": {"realism/collision_rate": 0.02},
                       "runs/a/final / topk:5": {"realism/collision_rate": 0.01}}}
    out.update(over)
    path = tmp_path / "earlier.json"
    path.write_text(json.dumps(out))
    return path


def _args(path: Path, **over) -> Namespace:
    a = dict(reuse_pretrained=str(path), pretrained="runs/start/final", data="data/generated/default/val",
             seeds=[0, 1], metric="wosac")
    a.update(over)
    return Namespace(**a)


def test_the_pretrained_side_of_the_same_setting_is_reused(tmp_path):
    mod = _script()
    path = _earlier(tmp_path)
    got = mod.reused_pretrained(_args(path), "pretrained (runs/start/final)", ["s1", "s2"])
    assert got == {"pretrained (runs/start/final) / topk:5": {"realism/collision_rate": 0.02}}  # not the GRPO side


@pytest.mark.parametrize("field, change", [("data", {"data": "data/generated/default/test"}), ("seeds", {"seeds": [0, 2]}),
                                           ("pretrained", {"pretrained": "runs/other/final"})])
def test_another_setting_is_a_clear_error_naming_file_and_field(tmp_path, field, change):
    mod = _script()
    path = _earlier(tmp_path)
    with pytest.raises(SystemExit, match=f"{path}: field '{field}'"):
        mod.reused_pretrained(_args(path, **change), "pretrained (runs/start/final)", ["s1", "s2"])


def test_outputs_written_before_data_and_seeds_existed_count_as_the_test_split_and_seeds_0_to_4(tmp_path):
    mod = _script()
    path = _earlier(tmp_path)
    raw = json.loads(path.read_text())
    del raw["data"], raw["seeds"]
    path.write_text(json.dumps(raw))
    with pytest.raises(SystemExit, match="field 'seeds' is \\[0, 1, 2, 3, 4\\]"):
        mod.reused_pretrained(_args(path, data="data/generated/default/test"), "pretrained (runs/start/final)", ["s1", "s2"])
    with pytest.raises(SystemExit, match="field 'data' is 'data/generated/default/test'"):
        mod.reused_pretrained(_args(path), "pretrained (runs/start/final)", ["s1", "s2"])
    got = mod.reused_pretrained(_args(path, data="data/generated/default/test", seeds=[0, 1, 2, 3, 4]),
                                "pretrained (runs/start/final)", ["s1", "s2"])
    assert list(got) == ["pretrained (runs/start/final) / topk:5"]
