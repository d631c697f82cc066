"""Typed recipe configuration: dataclasses <-> command line <-> ``config.json``.

Every field of a (possibly nested) dataclass becomes a command-line option:

* ``--field VALUE`` for top-level fields, ``--section.field VALUE`` for fields of a nested
  dataclass (a field whose type is itself a dataclass);
* booleans become ``--flag`` / ``--no-flag``;
* ``tuple[int, ...]`` / ``list[float]`` take several values (``--sizes 64 64``);
* ``Optional[T]`` accepts ``none`` to reset to ``None``; ``Literal[...]`` restricts the choices;
* help text comes from ``field(metadata={"help": ...})`` or, when absent, from the attribute
  docstring written right below the field (``x: int = 3`` followed by ``\"\"\"doc\"\"\"``).

Presets (``--preset NAME``) are named dicts of overrides applied on top of the defaults and
below the explicit command-line values. The resolved configuration is a plain dataclass that
:func:`config_to_dict` / :func:`config_from_dict` turn into JSON and back.

argparse's own ``default`` values are suppressed so that the parser reports only what the user
typed; this is what lets presets and resumed ``config.json`` files sit between the dataclass
defaults and the explicit flags.
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import json
import sys
import textwrap
import types
import typing
from pathlib import Path
from typing import Any, Mapping, Sequence

__all__ = [
    "parse_config",
    "build_parser",
    "apply_overrides",
    "config_to_dict",
    "config_from_dict",
    "save_config",
    "load_config",
    "field_docs",
]

_NONE_STRINGS = ("none", "null")


# --------------------------------------------------------------------------- field docs
def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings of a dataclass: ``{field: doc}`` (inherited ones included)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            source = textwrap.dedent(inspect.getsource(klass))
            tree = ast.parse(source)
        except (OSError, TypeError, SyntaxError):  # classes built at run time have no source
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, nxt in zip(body, body[1:]):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)
            ):
                docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


# --------------------------------------------------------------------------- type handling
def _resolved_hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception as err:  # pragma: no cover - a broken annotation is a programming error
        raise TypeError(f"cannot resolve the type annotations of {cls.__name__}: {err}") from err


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0], True
        raise TypeError(f"unsupported union type {tp!r} (only Optional[T] is supported)")
    return tp, False


def _scalar_parser(tp: Any, optional: bool, name: str):
    def convert(text: str):
        if optional and text.lower() in _NONE_STRINGS:
            return None
        if tp is bool:
            low = text.lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise argparse.ArgumentTypeError(f"--{name}: expected a boolean, got {text!r}")
        try:
            return tp(text)
        except ValueError as err:
            raise argparse.ArgumentTypeError(
                f"--{name}: expected {getattr(tp, '__name__', tp)}, got {text!r}"
            ) from err

    convert.__name__ = getattr(tp, "__name__", "value")
    return convert


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Turn a JSON/preset value into the field's type (tuples from lists, floats from ints)."""
    base, optional = _unwrap_optional(tp)
    if value is None:
        if optional:
            return None
        raise ValueError(f"{where}: None given for a non-optional field of type {tp!r}")
    if dataclasses.is_dataclass(base):
        if isinstance(value, base):
            return value
        if not isinstance(value, Mapping):
            raise ValueError(f"{where}: expected a mapping for section {base.__name__}, got {value!r}")
        return config_from_dict(base, value, where=where)
    origin = typing.get_origin(base)
    if origin in (tuple, list):
        args = [a for a in typing.get_args(base) if a is not Ellipsis] or [Any]
        items = [_coerce(v, args[0] if len(args) == 1 else args[i], f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else list(items)
    if origin is typing.Literal:
        if value not in typing.get_args(base):
            raise ValueError(f"{where}: {value!r} is not one of {typing.get_args(base)}")
        return value
    if base is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if base in (int, str, bool) and not isinstance(value, base):
        raise ValueError(f"{where}: expected {base.__name__}, got {value!r}")
    return value


# --------------------------------------------------------------------------- parser
def _add_fields(parser: argparse.ArgumentParser, cls: type, prefix: str = "", group=None) -> None:
    hints = _resolved_hints(cls)
    docs = field_docs(cls)
    target = group if group is not None else parser
    for f in dataclasses.fields(cls):
        if not f.init or f.metadata.get("cli", True) is False:
            continue
        tp = hints[f.name]
        base, optional = _unwrap_optional(tp)
        name = prefix + f.name
        if dataclasses.is_dataclass(base):
            section_help = f.metadata.get("help") or docs.get(f.name) or (base.__doc__ or "").strip().split("\n")[0]
            sub = parser.add_argument_group(f"{name} options", section_help)
            _add_fields(parser, base, prefix=name + ".", group=sub)
            continue
        default = _field_default(f)
        help_text = f.metadata.get("help") or docs.get(f.name) or ""
        help_text = f"{help_text} (default: {default!r})".strip().replace("%", "%%")
        flag = "--" + name.replace("_", "-")
        options = [flag] if flag == "--" + name else [flag, "--" + name]
        kwargs: dict[str, Any] = dict(dest=name, help=help_text, default=argparse.SUPPRESS)
        origin = typing.get_origin(base)
        if base is bool and not optional:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif origin in (tuple, list):
            args = [a for a in typing.get_args(base) if a is not Ellipsis] or [str]
            kwargs["nargs"] = "*" if origin is list or Ellipsis in typing.get_args(base) else len(args)
            kwargs["type"] = _scalar_parser(args[0], False, name)
            kwargs["metavar"] = getattr(args[0], "__name__", "V").upper()
        elif origin is typing.Literal:
            choices = list(typing.get_args(base))
            kwargs["type"] = _scalar_parser(type(choices[0]), optional, name)
            kwargs["choices"] = choices + ([None] if optional else [])
            kwargs["metavar"] = "{" + ",".join(map(str, choices)) + "}"
        else:
            kwargs["type"] = _scalar_parser(base, optional, name)
            kwargs["metavar"] = getattr(base, "__name__", "V").upper()
        target.add_argument(*options, **kwargs)


def _field_default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        value = f.default_factory()  # type: ignore[misc]
        return config_to_dict(value) if dataclasses.is_dataclass(value) else value
    return None


def build_parser(
    cls: type,
    *,
    presets: Mapping[str, Mapping[str, Any]] | None = None,
    description: str | None = None,
    prog: str | None = None,
) -> argparse.ArgumentParser:
    """An ``argparse`` parser with one option per (nested) field of dataclass ``cls``."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    parser = argparse.ArgumentParser(
        prog=prog,
        description=description or (cls.__doc__ or "").strip() or None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        allow_abbrev=False,
    )
    if presets:
        parser.add_argument(
            "--preset",
            choices=sorted(presets),
            default=None,
            help="named set of overrides applied before the explicit flags: "
            + "; ".join(f"{k}: {', '.join(f'{kk}={vv!r}' for kk, vv in _flatten(v).items())}" for k, v in presets.items()).replace("%", "%%"),
        )
    _add_fields(parser, cls)
    return parser


# --------------------------------------------------------------------------- overrides
def _flatten(overrides: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in overrides.items():
        if isinstance(value, Mapping):
            flat.update(_flatten(value, prefix + key + "."))
        else:
            flat[prefix + key] = value
    return flat


def apply_overrides(cfg: Any, overrides: Mapping[str, Any]) -> Any:
    """A copy of ``cfg`` with ``{"a.b": v}`` or nested ``{"a": {"b": v}}`` overrides applied."""
    flat = _flatten(overrides)
    nested: dict[str, dict[str, Any]] = {}
    direct: dict[str, Any] = {}
    names = {f.name: f for f in dataclasses.fields(cfg)}
    hints = _resolved_hints(type(cfg))
    for key, value in flat.items():
        head, _, rest = key.partition(".")
        if head not in names:
            raise KeyError(
                f"unknown config field {key!r} for {type(cfg).__name__}; known: {sorted(names)}"
            )
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[head] = _coerce(value, hints[head], key)
    for head, sub in nested.items():
        current = getattr(cfg, head)
        if not dataclasses.is_dataclass(current):
            raise KeyError(f"config field {head!r} is not a section; cannot set {head}.{next(iter(sub))}")
        direct[head] = apply_overrides(current, sub)
    return dataclasses.replace(cfg, **direct)


def parse_config(
    cls: type,
    argv: Sequence[str] | None = None,
    *,
    presets: Mapping[str, Mapping[str, Any]] | None = None,
    description: str | None = None,
    base: Any = None,
) -> tuple[Any, dict[str, Any]]:
    """Parse ``argv`` into an instance of dataclass ``cls``.

    Order of precedence (lowest first): dataclass defaults (or ``base``), ``--preset``, explicit
    flags. Returns ``(config, explicit)`` where ``explicit`` maps the dotted names of the fields
    the user set on the command line to their values (used to re-apply them over a resumed
    ``config.json``).
    """
    parser = build_parser(cls, presets=presets, description=description)
    ns = vars(parser.parse_args(sys.argv[1:] if argv is None else list(argv)))
    preset = ns.pop("preset", None)
    cfg = base if base is not None else cls()
    if preset is not None:
        cfg = apply_overrides(cfg, presets[preset])
    explicit = dict(ns)
    cfg = apply_overrides(cfg, explicit)
    return cfg, explicit


# --------------------------------------------------------------------------- (de)serialisation
def config_to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-ready dict of a (nested) dataclass; tuples become lists."""
    if not dataclasses.is_dataclass(cfg):
        raise TypeError(f"{cfg!r} is not a dataclass instance")
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=str))


def config_from_dict(cls: type, data: Mapping[str, Any], *, strict: bool = True, where: str = "") -> Any:
    """Rebuild dataclass ``cls`` from :func:`config_to_dict` output (missing keys keep defaults)."""
    hints = _resolved_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = set(data) - names
    if unknown and strict:
        raise KeyError(f"{where or cls.__name__}: unknown config keys {sorted(unknown)}")
    kwargs = {
        k: _coerce(v, hints[k], f"{where + '.' if where else ''}{k}") for k, v in data.items() if k in names
    }
    return cls(**kwargs)


def save_config(cfg: Any, path: str | Path) -> Path:
    """Write the resolved configuration as indented JSON (atomically)."""
    from .checkpoint import atomic_write_bytes

    path = Path(path)
    atomic_write_bytes(path, (json.dumps(config_to_dict(cfg), indent=2, sort_keys=False) + "\n").encode())
    return path


def load_config(cls: type, path: str | Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file {path} does not exist")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"config file {path} is not valid JSON: {err}") from err
    return config_from_dict(cls, data)
