from dataclasses import dataclass, field
from pathlib import Path

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


CONFIG_KINDS = {"dataset": "dataset", "grpo": "grpo", "sft": "grpo", "campaign": "pretrain", "pretrain": "pretrain",
                "model": "model"}


@pytest.mark.parametrize("path", sorted((Path(__file__).parent.parent / "configs").glob("*.yaml")),
                         ids=lambda p: p.name)
def test_every_bundled_config_loads_into_its_class(path):
    """Each YAML under configs/ is read by the class its commands load it with (an unknown or mistyped key is a
    ConfigError naming the file), so a config a README or docs command names cannot have rotted."""
    import yaml

    from r1sim_sumo.data.dataset import DatasetRecipe
    from r1sim_sumo.model.config import PolicyConfig
    from r1sim_sumo.train.grpo import GRPOConfig
    from r1sim_sumo.train.pretrain import PretrainConfig

    kind = CONFIG_KINDS.get(path.name.split("_")[0].removesuffix(".yaml"))
    assert kind is not None, f"{path.name}: no known kind; name it dataset_/grpo_/sft_/campaign_/pretrain_/model_*"
    if kind == "dataset":
        DatasetRecipe.from_yaml(path)
    elif kind == "model":
        PolicyConfig.from_dict(yaml.safe_load(path.read_text()))
    else:
        cfg = load_config(GRPOConfig if kind == "grpo" else PretrainConfig, path)
        assert cfg.out_dir
