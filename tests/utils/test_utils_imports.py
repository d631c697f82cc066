"""``trakdis.utils`` is generic: none of its modules imports anything from trakdis outside
``trakdis.utils`` (module level or inside a function); and no package imports a floor above its own."""
import ast
from pathlib import Path

import pytest

TRAKDIS = Path(__file__).resolve().parents[2] / "trakdis"

# floor of each part of trakdis: a part may import its own floor and the floors below it
FLOORS = {"utils": 0, "envs": 1, "modules": 2, "transforms": 2, "objectives": 3, "data": 3,
          "evaluation": 4, "policies": 4, "optim": 4, "training": 4, "method": 4}


def imported_modules(source: str, module: str) -> list[str]:
    """Absolute names of the modules that ``source`` (the module ``module``, e.g.
    ``"trakdis.utils.plot"``; a package's ``__init__`` is named by the package) imports anywhere."""
    names = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolved against the importing module's package
                base = module.split(".")[: len(module.split(".")) - node.level]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module
            names.append(name)
            names += [f"{name}.{alias.name}" for alias in node.names]  # `from trakdis import envs`
    return names


def _module_name(path: Path) -> str:
    parts = path.relative_to(TRAKDIS.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _relative_module(path: Path) -> str:
    """Like :func:`_module_name`, but a package's ``__init__`` resolves relative imports from the package."""
    name = _module_name(path)
    return name + ".__init__" if path.name == "__init__.py" else name


def foreign_imports(source: str, module: str) -> list[str]:
    """The imports of ``source`` that reach into trakdis outside ``trakdis.utils``."""
    return sorted({name for name in imported_modules(source, module)
                   if (name == "trakdis" or name.startswith("trakdis."))
                   and name != "trakdis.utils" and not name.startswith("trakdis.utils.")
                   and not name.startswith("trakdis.__")})


def test_utils_imports_nothing_from_trakdis_outside_utils():
    files = sorted((TRAKDIS / "utils").glob("*.py"))
    assert len(files) >= 8
    found = {f.name: foreign_imports(f.read_text(), _relative_module(f)) for f in files}
    assert {k: v for k, v in found.items() if v} == {}


def test_the_check_catches_an_import_from_the_domain():
    module = "trakdis.utils.example"
    assert foreign_imports("from .checkpoint import atomic_write_bytes\nimport torch\n", module) == []
    assert foreign_imports("def f():\n    from trakdis.envs import make_env\n", module) == ["trakdis.envs", "trakdis.envs.make_env"]
    assert foreign_imports("from ..data import DataConfig\n", module) == ["trakdis.data", "trakdis.data.DataConfig"]
    assert foreign_imports("from trakdis import policies\n", module) == ["trakdis", "trakdis.policies"]
    assert "trakdis.modules" in foreign_imports("import trakdis.modules\n", module)


def _part(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "trakdis" and parts[1] in FLOORS else None


@pytest.mark.parametrize("part", sorted(FLOORS))
def test_no_part_imports_a_floor_above_its_own(part):
    path = TRAKDIS / part
    files = sorted(path.glob("*.py")) if path.is_dir() else [path.with_suffix(".py")]
    upward = {}
    for f in files:
        for name in imported_modules(f.read_text(), _relative_module(f)):
            other = _part(name)
            if other is not None and FLOORS[other] > FLOORS[part]:
                upward.setdefault(f.name, set()).add(other)
    assert upward == {}
