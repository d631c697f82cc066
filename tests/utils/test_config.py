import dataclasses
import json
from dataclasses import dataclass, field
from typing import Literal, Optional

import pytest

from trakdis.utils.config import (
    apply_overrides,
    build_parser,
    config_from_dict,
    config_to_dict,
    field_docs,
    load_config,
    parse_config,
    save_config,
)


@dataclass
class Model:
    embed_dim: int = 64
    """width of the token embeddings"""
    num_layers: int = 2
    dropout: float = field(default=0.1, metadata={"help": "dropout probability"})


@dataclass
class Cfg:
    task: Literal["ClothFold", "ClothFoldDiagonalPinned"] = "ClothFold"
    """which task"""
    lr: float = 1e-4
    """learning rate (100% of it)"""
    steps: int = 10
    aug: bool = True
    """use image augmentation"""
    name: Optional[str] = None
    sizes: tuple[int, ...] = (32, 32)
    model: Model = field(default_factory=Model)


PRESETS = {"paper": {"model": {"embed_dim": 256, "num_layers": 10}, "lr": 1e-4}, "fast": {"steps": 3}}


def test_defaults_and_overrides():
    cfg, explicit = parse_config(Cfg, [])
    assert cfg == Cfg() and explicit == {}
    cfg, explicit = parse_config(
        Cfg,
        ["--lr", "3e-4", "--no-aug", "--model.embed-dim", "8", "--sizes", "16", "8", "4", "--name", "x"],
    )
    assert cfg.lr == 3e-4 and cfg.aug is False and cfg.model.embed_dim == 8
    assert cfg.sizes == (16, 8, 4) and cfg.name == "x"
    assert cfg.model.num_layers == 2  # untouched nested default
    assert explicit == {"lr": 3e-4, "aug": False, "model.embed_dim": 8, "sizes": [16, 8, 4], "name": "x"}


def test_underscore_spelling_and_none():
    cfg, _ = parse_config(Cfg, ["--model.num_layers", "5", "--name", "none"])
    assert cfg.model.num_layers == 5 and cfg.name is None


def test_preset_below_explicit_flags():
    cfg, _ = parse_config(Cfg, ["--preset", "paper"], presets=PRESETS)
    assert cfg.model.embed_dim == 256 and cfg.model.num_layers == 10
    cfg, _ = parse_config(Cfg, ["--preset", "paper", "--model.num-layers", "3"], presets=PRESETS)
    assert cfg.model.embed_dim == 256 and cfg.model.num_layers == 3


def test_bad_values_exit_with_message(capsys):
    with pytest.raises(SystemExit):
        parse_config(Cfg, ["--steps", "ten"])
    assert "--steps" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_config(Cfg, ["--task", "Nope"])
    with pytest.raises(SystemExit):
        parse_config(Cfg, ["--unknown", "1"])


def test_help_has_docs():
    text = build_parser(Cfg, presets=PRESETS).format_help()
    for needle in ("learning rate (100% of it)", "use image augmentation", "--no-aug",
                   "width of the token embeddings", "dropout probability", "--model.embed-dim", "--preset"):
        assert needle in text, needle
    assert field_docs(Model)["embed_dim"] == "width of the token embeddings"


def test_roundtrip_json(tmp_path):
    cfg = apply_overrides(Cfg(), {"model.embed_dim": 12, "sizes": [1, 2]})
    assert cfg.sizes == (1, 2)
    path = save_config(cfg, tmp_path / "config.json")
    data = json.loads(path.read_text())
    assert data["model"]["embed_dim"] == 12 and data["sizes"] == [1, 2]
    assert load_config(Cfg, path) == cfg
    assert config_from_dict(Cfg, config_to_dict(cfg)) == cfg


def test_errors_name_the_field(tmp_path):
    with pytest.raises(KeyError, match="bogus"):
        apply_overrides(Cfg(), {"bogus": 1})
    with pytest.raises(KeyError, match="model"):
        config_from_dict(Cfg, {"model": {"nope": 1}})
    with pytest.raises(ValueError, match="steps"):
        config_from_dict(Cfg, {"steps": "many"})
    with pytest.raises(FileNotFoundError, match="missing.json"):
        load_config(Cfg, tmp_path / "missing.json")
    assert dataclasses.is_dataclass(Cfg())
