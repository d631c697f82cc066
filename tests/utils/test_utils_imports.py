"""The layering of trakdis: ``trakdis.utils`` is generic (none of its modules imports anything from
trakdis outside ``trakdis.utils``, module level or inside a function); no part imports a floor above its
own; and no module imports itself through others (anywhere in a module: a function-local import hides
a cycle from Python, not from this check)."""
import ast
from pathlib import Path
from typing import Mapping

import pytest

TRAKDIS = Path(__file__).resolve().parents[2] / "trakdis"

# floor of each part of trakdis: a part may import its own floor and the floors below it
FLOORS = {"utils": 0, "envs": 1, "transforms": 2, "modules": 3, "data": 3, "objectives": 4, "policies": 4,
          "optim": 4, "evaluation": 5, "training": 6, "teacher": 6, "student": 6, "encoder_training": 6, "method": 6}


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


# --------------------------------------------------------------------------- floors
def _part(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "trakdis" and parts[1] in FLOORS else None


def upward_imports(part: str, sources: Mapping[str, str]) -> dict[str, set[str]]:
    """``{module: the parts above part's floor it imports}`` of ``sources`` (``{module: source}``, the
    modules of ``part``, a package's ``__init__`` named ``<package>.__init__``)."""
    upward = {}
    for module, source in sources.items():
        for name in imported_modules(source, module):
            other = _part(name)
            if other is not None and FLOORS[other] > FLOORS[part]:
                upward.setdefault(module, set()).add(other)
    return upward


def test_every_part_of_trakdis_has_a_floor():
    parts = {p.name for p in TRAKDIS.iterdir() if (p / "__init__.py").exists()}
    parts |= {p.stem for p in TRAKDIS.glob("*.py") if p.name != "__init__.py"}
    assert parts == set(FLOORS)


@pytest.mark.parametrize("part", sorted(FLOORS))
def test_no_part_imports_a_floor_above_its_own(part):
    path = TRAKDIS / part
    files = sorted(path.glob("*.py")) if path.is_dir() else [path.with_suffix(".py")]
    assert upward_imports(part, {_relative_module(f): f.read_text() for f in files}) == {}


def test_the_floor_check_catches_an_upward_import():
    sources = {"trakdis.evaluation.protocol": "def f():\n    from trakdis.student import weight_copy_race\n",
               "trakdis.evaluation.__init__": "from .protocol import f\nfrom ..policies import load_policy\n"}
    assert upward_imports("evaluation", sources) == {"trakdis.evaluation.protocol": {"student"}}
    assert upward_imports("policies", {"trakdis.policies.acting": "from trakdis.evaluation import run_episodes\n"}) \
        == {"trakdis.policies.acting": {"evaluation"}}


# --------------------------------------------------------------------------- cycles
def module_graph(sources: Mapping[str, str]) -> dict[str, set[str]]:
    """``{module: the modules of sources it imports}`` of ``sources`` (``{module: source}``, a package's
    ``__init__`` named ``<package>.__init__``), counting every import of a module, inside functions and
    under ``if TYPE_CHECKING:`` too. Importing ``a.b.c`` runs the packages ``a`` and ``a.b`` as well,
    except the importing module's own packages (already being imported when it runs)."""
    names = {module.removesuffix(".__init__") for module in sources}
    graph = {}
    for module, source in sources.items():
        name = module.removesuffix(".__init__")
        own = {".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 1)}
        deps = set()
        for imported in imported_modules(source, module):
            while imported and imported not in names:  # `from pkg.mod import f`: the module pkg.mod
                imported = imported.rpartition(".")[0]
            parts = imported.split(".") if imported else []
            deps |= {".".join(parts[:i]) for i in range(1, len(parts) + 1)} & names - own
        graph[name] = deps - {name}
    return graph


def find_cycle(graph: Mapping[str, set[str]]) -> list[str]:
    """One cycle of ``graph``: its modules in import order, the first repeated at the end; ``[]`` if none."""
    done, path = set(), []

    def visit(module: str) -> list[str]:
        path.append(module)
        for dep in sorted(graph.get(module, ())):
            if dep in path:
                return path[path.index(dep):] + [dep]
            if dep not in done:
                cycle = visit(dep)
                if cycle:
                    return cycle
        done.add(path.pop())
        return []

    for module in sorted(graph):
        if module not in done:
            cycle = visit(module)
            if cycle:
                return cycle
    return []


def test_trakdis_has_no_import_cycle():
    files = sorted(TRAKDIS.rglob("*.py"))
    graph = module_graph({_relative_module(f): f.read_text() for f in files})
    assert len(graph) >= 50
    cycle = find_cycle(graph)
    assert not cycle, "an import cycle: " + " -> ".join(cycle)


def test_the_cycle_check_catches_a_cycle_hidden_in_a_function():
    sources = {"trakdis.evaluation.__init__": "from .protocol import EvalProtocol\n",
               "trakdis.evaluation.protocol": "def f():\n    from trakdis.policies import load_policy\n",
               "trakdis.policies": "from trakdis.evaluation.episodes import run_episodes\n",
               "trakdis.evaluation.episodes": "import torch\n"}
    assert find_cycle(module_graph(sources)) == ["trakdis.evaluation", "trakdis.evaluation.protocol",
                                                 "trakdis.policies", "trakdis.evaluation"]
    sources["trakdis.evaluation.protocol"] = "def f():\n    pass\n"  # without the function-local import: none
    assert find_cycle(module_graph(sources)) == []


def test_the_cycle_check_runs_the_packages_of_an_import():
    """``from trakdis.b.y import g`` runs ``trakdis/b/__init__.py``, which may import the importer back."""
    sources = {"trakdis.a.__init__": "", "trakdis.a.x": "from trakdis.b.y import g\n",
               "trakdis.b.__init__": "from trakdis.a.x import f\n", "trakdis.b.y": "",
               "trakdis.a.z": "from .x import f\n"}
    assert find_cycle(module_graph(sources)) == ["trakdis.a.x", "trakdis.b", "trakdis.a.x"]
    assert "trakdis.a" not in module_graph(sources)["trakdis.a.z"]  # its own package is already running
