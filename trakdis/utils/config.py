"""Recipe configuration: a dataclass is the command line (tyro) and ``config.json`` (dacite).

tyro turns a (nested) dataclass into options: ``--field VALUE``, ``--section.field VALUE`` for
a nested dataclass, ``--flag`` / ``--no-flag`` for booleans, several values for tuples, ``None``
for optional fields, the choices of a ``Literal``, and help text from the attribute docstring
written below each field or from a comment on the field's own line (``steps: int = 10  # number
of updates``). A bad value exits with a message naming the option, as does a ``ValueError``
raised by the dataclass's ``__post_init__``.

What is left here is the glue tyro does not have:

* :func:`parse_config`: ``--preset NAME`` (tyro's presets are positional subcommands) and a
  ``default`` instance that the typed flags override (how a resumed run keeps its own
  ``config.json`` and changes only what the user typed);
* :func:`config_to_dict` / :func:`config_from_dict` / :func:`save_config` / :func:`load_config`:
  ``config.json`` and back, with dacite checking the types (JSON lists become tuples).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence, TypeVar

import dacite
import tyro

from .checkpoint import atomic_write_bytes
from .limits import read_json

__all__ = ["parse_config", "apply_overrides", "config_to_dict", "config_from_dict", "save_config", "load_config"]

T = TypeVar("T")


def parse_config(
    cls: type[T],
    argv: Sequence[str] | None = None,
    *,
    presets: Mapping[str, Mapping[str, Any]] | None = None,
    description: str | None = None,
    default: T | None = None,
) -> T:
    """Parse ``argv`` (default: ``sys.argv[1:]``) into an instance of dataclass ``cls``.

    Precedence, lowest first: the dataclass defaults, ``--preset NAME`` (a nested dict of
    ``presets``), the typed flags. A given ``default`` (a resumed run's saved configuration,
    which already holds the preset it was started with) replaces the first two, and a
    ``--preset`` is then ignored.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if presets:
        # tyro's presets are positional subcommands; `--preset NAME` is read first and becomes the
        # default instance that tyro's flags override, so a preset sits below the typed flags.
        pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
        pre.add_argument("--preset", choices=sorted(presets))
        known, argv = pre.parse_known_args(argv)
        if default is None and known.preset is not None:
            default = apply_overrides(cls(), presets[known.preset])
        description = (f"{description or ''}\n\n--preset {{{','.join(sorted(presets))}}}: named overrides of the "
                       "defaults, below the typed flags (--preset NAME --help shows its values)").strip()
    return tyro.cli(cls, args=argv, default=default, description=description)


def apply_overrides(cfg: T, overrides: Mapping[str, Any]) -> T:
    """A copy of dataclass ``cfg`` with a nested dict of ``overrides`` (a preset) merged in."""

    def merge(base: dict[str, Any], new: Mapping[str, Any]) -> dict[str, Any]:
        return {**base, **{k: merge(base[k], v) if isinstance(v, Mapping) and isinstance(base.get(k), dict) else v
                           for k, v in new.items()}}

    return config_from_dict(type(cfg), merge(config_to_dict(cfg), overrides))


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-ready dict of a (nested) dataclass; tuples become lists."""
    if not dataclasses.is_dataclass(cfg):
        raise TypeError(f"{cfg!r} is not a dataclass instance")
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=str))


def config_from_dict(cls: type[T], data: Mapping[str, Any]) -> T:
    """Rebuild dataclass ``cls`` from :func:`config_to_dict` output (missing keys keep their
    defaults, or take ``cls.SAVED_WITHOUT``'s value: what a configuration saved before the field
    existed ran with, where today's default differs); a key named in ``cls.SAVED_AS`` (``{old field
    name: new field name}``, a field renamed since) is read as the new field; in a string field named in
    ``cls.SAVED_FLAGS`` (``{field: {old flag: new flag}}``: options passed on to another recipe, whose
    flag was renamed since) each old flag is read as the new one; ``cls.upgrade_saved(data)``, where ``cls``
    has it, rewrites what a field's meaning change needs; an unknown key or a value of the wrong type raises
    an error naming the field."""
    data = dict(data)
    if hasattr(cls, "upgrade_saved"):
        data = dict(cls.upgrade_saved(data))
    for old, new in getattr(cls, "SAVED_AS", {}).items():
        if old in data:
            if new in data:
                raise ValueError(f"config of {cls.__name__}: both {old!r} and its new name {new!r}")
            data[new] = data.pop(old)
    for key, flags in getattr(cls, "SAVED_FLAGS", {}).items():
        if isinstance(data.get(key), str):
            for old, new in flags.items():
                data[key] = re.sub(rf"(?<!\S){re.escape(old)}(?=[\s=]|$)", new, data[key])
    data = {**getattr(cls, "SAVED_WITHOUT", {}), **data}
    return dacite.from_dict(cls, data, config=dacite.Config(cast=[tuple], strict=True))


def save_config(cfg: Any, path: str | Path) -> Path:
    """Write the resolved configuration as indented JSON (atomically)."""
    path = Path(path)
    atomic_write_bytes(path, (json.dumps(config_to_dict(cfg), indent=2) + "\n").encode())
    return path


def load_config(cls: type[T], path: str | Path) -> T:
    """Read a configuration written by :func:`save_config`."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"config file {path} does not exist")
    data = read_json(path, error=ValueError, what="config file")  # a regular file of bounded size
    try:
        return config_from_dict(cls, data)
    except dacite.DaciteError as err:
        raise ValueError(f"config file {path}: {err}") from err
