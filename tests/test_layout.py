"""The shape of the code (ARCHITECTURE.md): data flows one way, no import cycles, the
datagen top level holds only packages and glue, modules and classes stay readable in one
sitting, and no test or bench imports a test file. Read from the source with `ast`; nothing is
imported."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("schemas", "datagen", "training", "drive", "experiments")

# Which of our packages each package may import: world -> ... -> shards on one side, the loader
# and model on the other, joined only by schemas; drive and experiments use both.
ALLOWED = {
    "schemas": set(),
    "datagen": {"schemas"},
    "training": {"schemas"},
    "drive": {"schemas", "datagen", "training"},
    "experiments": {"schemas", "datagen", "training", "drive"},
}
# datagen's stages, upstream first; a stage imports only its own and earlier stages.
DATAGEN_STAGES = (
    ("datagen.errors", "datagen.state"),
    ("datagen.world",),
    ("datagen.sensors",),
    ("datagen.labels",),
    ("datagen.episode",),
    ("datagen.dataset",),
    ("datagen.cli",),
)
# datagen/'s top level: the stage packages, the glue between them and the command line.
DATAGEN_TOP = {"__init__", "cli", "episode", "labels", "state", "errors"}

MAX_MODULE_LINES = 600
MAX_CLASS_LINES = 300
# Over the limits and being split by another change (issue 39); each entry says by whom.
SPLIT_PENDING: dict[str, str] = {}


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = path
    return mods


MODULES = _modules()


def _imports(path: Path, module: str) -> set[str]:
    """Every name `path` imports (at any depth: a lazy import inside a function counts).

    `from P import n` imports P itself as well as n: n is read from P's namespace, so when P is
    a package it goes through P/__init__.py and everything that imports, even where n is a
    submodule. `from P.m import n` and `import P.m` name the module m instead."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{parent}.{base}" if base else parent
            found.add(base)
            found.update(f"{base}.{a.name}" for a in node.names)  # a submodule, or in `base`
    return found


def _ours(name: str) -> str | None:
    """The module of ours `name` is (or is in): `datagen.world.World` -> `datagen.world`."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _graph() -> dict[str, set[str]]:
    graph = {}
    for module, path in MODULES.items():
        targets = {_ours(n) for n in _imports(path, module)}
        graph[module] = {t for t in targets if t and t != module}
    return graph


GRAPH = _graph()


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_import_graph_has_no_cycle():
    assert _cycles(GRAPH) == []


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_a_from_import_through_a_package_imports_its_init(tmp_path):
    source = tmp_path / "planning.py"
    source.write_text("from datagen.world import perception\nimport datagen.world.route\n")
    assert _imports(source, "datagen.world.planning") == {
        "datagen.world",  # the package's __init__, which imports every module of it
        "datagen.world.perception",
        "datagen.world.route",
    }


PACKAGES_IN_TREE = sorted(m for m, path in MODULES.items() if path.name == "__init__.py")


@pytest.mark.parametrize("package", PACKAGES_IN_TREE)
def test_no_package_imports_its_own_modules_in_a_circle(package):
    """Among a package's own modules and its __init__ (e.g. datagen/world/*.py), a sibling
    imported as `from datagen.world import perception` counts as importing the __init__ too."""
    own = {m for m in MODULES if m == package or m.rpartition(".")[0] == package}
    assert _cycles({m: GRAPH[m] & own for m in own}) == []


def test_data_flows_one_way_between_the_packages():
    wrong = sorted(
        f"{m} imports {t}"
        for m, targets in GRAPH.items()
        for t in targets
        if t.split(".")[0] not in ALLOWED[m.split(".")[0]] | {m.split(".")[0]}
    )
    assert wrong == []  # e.g. training never imports datagen, schemas nothing of ours


def _stage(module: str) -> int | None:
    for k, names in enumerate(DATAGEN_STAGES):
        if any(module == n or module.startswith(n + ".") for n in names):
            return k
    return None


def test_datagen_stages_import_only_upstream():
    wrong = sorted(
        f"{m} imports {t}"
        for m, targets in GRAPH.items()
        if _stage(m) is not None
        for t in targets
        if _stage(t) is not None and _stage(t) > _stage(m)
    )
    assert wrong == []


def test_every_datagen_module_belongs_to_a_stage():
    assert [m for m in MODULES if m.startswith("datagen.") and _stage(m) is None] == []


def test_datagen_top_level_holds_only_the_stage_packages_and_glue():
    top = {p.stem for p in (ROOT / "datagen").glob("*.py")}
    assert top <= DATAGEN_TOP, f"new top-level modules {top - DATAGEN_TOP}: put them in a package"


def _oversized() -> list[str]:
    found = []
    for path in MODULES.values():
        rel = path.relative_to(ROOT).as_posix()
        text = path.read_text()
        tree = ast.parse(text)
        stated = "Size:" in (ast.get_docstring(tree) or "")
        if text.count("\n") > MAX_MODULE_LINES and not stated and rel not in SPLIT_PENDING:
            found.append(f"{rel}: {text.count(chr(10))} lines")
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                lines = node.end_lineno - node.lineno + 1
                reason = "Size:" in (ast.get_docstring(node) or "")
                if lines > MAX_CLASS_LINES and not reason and rel not in SPLIT_PENDING:
                    found.append(f"{rel}: class {node.name} {lines} lines")
    return found


def test_no_module_or_class_is_oversized_without_a_stated_reason():
    """A module over 600 lines or a class over 300 says why in its docstring ("Size: ...")."""
    assert _oversized() == []


@pytest.mark.parametrize("folder", ["tests", "bench"])
def test_no_test_or_bench_imports_a_test_file(folder):
    wrong = []
    for path in sorted((ROOT / folder).glob("*.py")):
        for name in _imports(path, f"{folder}.{path.stem}"):
            if name.startswith(("tests.test_", "tests.conftest")):
                wrong.append(f"{path.name} imports {name}")
    assert wrong == []  # shared helpers: tests/conftest.py fixtures, tests/scenes.py, ...
