"""The glue around tyro: presets below the typed flags, a default instance (a resumed run's own
configuration) that only the typed flags change, and config.json round trips; plus the CLI
behaviour the recipes and docs rely on (spellings, booleans, nested sections, errors)."""
import json
import re
from dataclasses import dataclass, field
from typing import Literal, Optional

import pytest

from trakdis.utils.config import (
    apply_overrides,
    config_from_dict,
    config_to_dict,
    load_config,
    parse_config,
    save_config,
)


@dataclass
class Model:
    embed_dim: int = 64
    """width of the token embeddings"""
    num_layers: int = 2


@dataclass
class Base:
    resume: bool = False
    """continue a run"""


@dataclass
class Cfg(Base):
    task: Literal["ClothFold", "ClothFoldDiagonalPinned"] = "ClothFold"
    """which task"""
    lr: float = 1e-4
    """learning rate (100% of it)"""
    steps: int = 10
    batch: int = 8  # windows per update (an inline comment is help too)
    aug: bool = True
    """use image augmentation"""
    name: Optional[str] = None
    sizes: tuple[int, ...] = (32, 32)
    extra: str = ""
    model: Model = field(default_factory=Model)

    def __post_init__(self):
        if self.steps < 0:
            raise ValueError(f"--steps {self.steps}: must be >= 0")


PRESETS = {"paper": {"model": {"embed_dim": 256, "num_layers": 10}, "lr": 3e-4}, "fast": {"steps": 3}}


def error_text(capsys) -> str:
    """tyro's message without its box and line wrapping."""
    return " ".join(re.sub(r"[│╭╮╰╯─]", " ", capsys.readouterr().err).split())


def test_defaults_flags_and_spellings():
    assert parse_config(Cfg, []) == Cfg()
    cfg = parse_config(Cfg, ["--lr", "-3e-4", "--no-aug", "--model.embed-dim", "8", "--model.num_layers", "5",
                             "--sizes", "16", "8", "4", "--name", "x", "--extra=--flag 1"])
    assert cfg.lr == -3e-4 and cfg.aug is False and cfg.sizes == (16, 8, 4) and cfg.name == "x"
    assert (cfg.model.embed_dim, cfg.model.num_layers) == (8, 5)  # hyphen and underscore spellings
    assert cfg.extra == "--flag 1"  # a value that looks like options: --opt=VALUE
    assert parse_config(Cfg, ["--aug", "--name", "None", "--sizes"]) == Cfg(sizes=())


def test_preset_sits_between_defaults_and_typed_flags():
    cfg = parse_config(Cfg, ["--preset", "paper"], presets=PRESETS)
    assert (cfg.model.embed_dim, cfg.model.num_layers, cfg.lr, cfg.steps) == (256, 10, 3e-4, 10)
    cfg = parse_config(Cfg, ["--model.num-layers", "3", "--preset", "paper"], presets=PRESETS)
    assert (cfg.model.embed_dim, cfg.model.num_layers) == (256, 3)  # the flag wins wherever it is typed


def test_default_instance_changes_only_typed_flags():
    # how a resumed run works: its config.json is the default, and a preset is not applied again
    own = Cfg(lr=0.5, steps=7, aug=False, model=Model(embed_dim=12))
    cfg = parse_config(Cfg, ["--resume", "--preset", "paper", "--steps", "9"], presets=PRESETS, default=own)
    assert cfg == Cfg(resume=True, lr=0.5, steps=9, aug=False, model=Model(embed_dim=12))


def test_booleans_listed_once_in_help(capsys):
    with pytest.raises(SystemExit) as exc:
        parse_config(Cfg, ["--preset", "paper", "--help"], presets=PRESETS, description="Train a thing.")
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for needle in ("Train a thing.", "--preset {fast,paper}", "learning rate (100% of it)",
                   "use image augmentation", "width of the token embeddings", "--model.embed-dim", "continue a run",
                   "windows per update (an inline comment is help too)"):
        assert needle in text, needle
    assert text.count("--no-aug") == 1 and text.count("--aug,") == 1
    assert "(default: 256)" in text  # the help shows the preset's values


@pytest.mark.parametrize("argv,needles", [
    (["--steps", "ten"], ["--steps", "ten"]),
    (["--model.embed-dim", "x"], ["--model.embed-dim"]),
    (["--task", "Nope"], ["--task", "Nope"]),
    (["--unknown", "1"], ["--unknown"]),
    (["--steps", "-1"], ["--steps -1: must be >= 0"]),  # __post_init__'s ValueError
    (["--preset", "slow"], ["--preset", "slow"]),
])
def test_bad_values_exit_naming_the_option(capsys, argv, needles):
    with pytest.raises(SystemExit) as exc:
        parse_config(Cfg, argv, presets=PRESETS)
    assert exc.value.code == 2
    text = error_text(capsys)
    for needle in needles:
        assert needle in text, (needle, text)


def test_json_roundtrip(tmp_path):
    cfg = apply_overrides(Cfg(), {"model": {"embed_dim": 12}, "sizes": [1, 2]})
    assert cfg.sizes == (1, 2) and cfg.model == Model(embed_dim=12, num_layers=2)
    path = save_config(cfg, tmp_path / "config.json")
    data = json.loads(path.read_text())
    assert data["model"]["embed_dim"] == 12 and data["sizes"] == [1, 2]
    assert load_config(Cfg, path) == cfg
    assert config_from_dict(Cfg, config_to_dict(cfg)) == cfg
    assert config_from_dict(Cfg, {"steps": 3}) == Cfg(steps=3)  # missing keys keep their defaults


def test_json_errors_name_the_field(tmp_path):
    with pytest.raises(Exception, match="bogus"):
        apply_overrides(Cfg(), {"bogus": 1})
    with pytest.raises(Exception, match="nope"):
        config_from_dict(Cfg, {"model": {"nope": 1}})
    with pytest.raises(Exception, match="model.embed_dim"):
        config_from_dict(Cfg, {"model": {"embed_dim": "wide"}})
    (tmp_path / "config.json").write_text(json.dumps({"steps": "many"}))
    with pytest.raises(ValueError, match=r"config.json.*steps"):
        load_config(Cfg, tmp_path / "config.json")
    with pytest.raises(FileNotFoundError, match="missing.json"):
        load_config(Cfg, tmp_path / "missing.json")


@dataclass
class Renamed:
    estimate_noise: float = 0.0
    steps: int = 10
    SAVED_AS = {"state_noise": "estimate_noise"}  # not a field (no annotation): the earlier name of one


def test_a_renamed_field_loads_from_its_earlier_name(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"state_noise": 0.01, "steps": 3}))
    assert load_config(Renamed, tmp_path / "config.json") == Renamed(estimate_noise=0.01, steps=3)
    assert config_from_dict(Renamed, {"estimate_noise": 0.02}) == Renamed(estimate_noise=0.02)
    with pytest.raises(ValueError, match="state_noise.*estimate_noise"):
        config_from_dict(Renamed, {"state_noise": 0.01, "estimate_noise": 0.02})


@dataclass
class PassesFlags:
    stage_args: str = ""
    SAVED_FLAGS = {"stage_args": {"--old-flag": "--new-flag"}}


def test_renamed_flags_in_saved_stage_options_are_read_as_the_new_ones():
    loaded = config_from_dict(PassesFlags, {"stage_args": "--old-flag 1 --old-flag=2 --old-flagged 3 x--old-flag"})
    assert loaded.stage_args == "--new-flag 1 --new-flag=2 --old-flagged 3 x--old-flag"
    assert config_from_dict(PassesFlags, {}) == PassesFlags()
