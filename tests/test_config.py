from dataclasses import dataclass, field

import pytest

from r1sim_sumo.config import ConfigError, from_dict, load_config


@dataclass
class Inner:
    hidden_dim: int = 64


@dataclass
class Outer:
    lr: float = 1e-3
    steps: int = 10
    name: str | None = None
    layers: list[int] = field(default_factory=lambda: [1, 2])
    model: Inner = field(default_factory=Inner)
    flag: bool = False


def test_defaults_file_and_overrides(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("lr: 0.01\nmodel:\n  hidden_dim: 128\n")
    cfg = load_config(Outer, p, overrides=["steps=5", "model.hidden_dim=32", "flag=true"])
    assert cfg.lr == 0.01 and cfg.steps == 5 and cfg.model.hidden_dim == 32 and cfg.flag is True


def test_unknown_key_names_file_and_key(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("lr: 0.01\nlearning_rate: 3\n")
    with pytest.raises(ConfigError, match=r"bad.yaml.*learning_rate"):
        load_config(Outer, p)


def test_nested_unknown_key():
    with pytest.raises(ConfigError, match="hidden"):
        from_dict(Outer, {"model": {"hidden": 3}}, "x.yaml")


@pytest.mark.parametrize("data,field_name", [({"steps": "ten"}, "steps"), ({"lr": "fast"}, "lr"), ({"layers": 3}, "layers"), ({"flag": "maybe"}, "flag")])
def test_wrong_types(data, field_name):
    with pytest.raises(ConfigError, match=field_name):
        from_dict(Outer, data, "x.yaml")


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(Outer, tmp_path / "nope.yaml")
    p = tmp_path / "m.yaml"
    p.write_text("lr: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(Outer, p)
    p.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(Outer, p)
