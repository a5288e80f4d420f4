"""The layout is the architecture: who may import whom, checked statically on the source.

- ``flyknot/`` (core: records, errors, constants, limits, demonstrations, knot topology,
  geometry, rest criterion) imports none of the other packages, nor MuJoCo or CasADi.
- ``flyknot_sim/`` (the simulated lab) and ``flyknot_hw/`` (the real lab) import the core
  only: neither imports the other, the learner or the application.
- ``learner/`` imports the core only and never reads the simulator-only ``truth`` of a record.
- ``flyknot_app/`` (CLI, runner, reports, gym env, viewer, benchmarks) alone imports every
  runtime package.
- ``flyknot_tools/`` (offline demonstration searches, rope-model studies) may import anything;
  no runtime package imports it.
- No runtime module reads the tests' data; no module is longer than :data:`MAX_LINES`.

A new top-level package fails :func:`test_every_package_has_a_rule` until it gets a rule, so a
new file or package cannot slip past. Imports inside functions count too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

CORE, SIM, HW, LEARNER, APP, TOOLS = (
    "flyknot",
    "flyknot_sim",
    "flyknot_hw",
    "learner",
    "flyknot_app",
    "flyknot_tools",
)
ALLOWED = {
    CORE: {CORE},
    SIM: {CORE, SIM},
    HW: {CORE, HW},
    LEARNER: {CORE, LEARNER},
    APP: {CORE, SIM, HW, LEARNER, APP},
    TOOLS: {CORE, SIM, HW, LEARNER, APP, TOOLS},
}
"""For each package: the packages of ours it may import."""
RUNTIME = (CORE, SIM, HW, LEARNER, APP)
FORBIDDEN_THIRD_PARTY = {CORE: {"mujoco", "casadi"}}
"""Heavy dependencies a package must not pull in (the real lab's core needs no simulator)."""
MAX_LINES = 600
"""No module longer than this (the layout issue's "no module over ~600 lines")."""


def _packages() -> list[str]:
    return sorted(
        p.name
        for p in ROOT.iterdir()
        if p.is_dir() and (p / "__init__.py").is_file() and not p.name.startswith(".")
    )


def _files(pkg: str) -> list[Path]:
    return sorted((ROOT / pkg).rglob("*.py"))


ALL_FILES = [(pkg, f) for pkg in _packages() for f in _files(pkg)]


def _imported(path: Path, pkg: str) -> list[tuple[int, str]]:
    """(line, top-level module) of every import in the file; relative ones are ``pkg``."""
    tree = ast.parse(path.read_text())
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name.split(".")[0]) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                out.append((node.lineno, pkg))
            elif node.module:
                out.append((node.lineno, node.module.split(".")[0]))
    return out


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def test_every_package_has_a_rule():
    pkgs = _packages()
    assert {CORE, SIM, LEARNER, APP, TOOLS} <= set(pkgs)
    unknown = [p for p in pkgs if p not in ALLOWED]
    assert not unknown, f"packages without an import rule in tests/test_boundary.py: {unknown}"
    for pkg in pkgs:
        assert _files(pkg), f"{pkg}/ holds no Python files"


@pytest.mark.parametrize(("pkg", "path"), ALL_FILES, ids=lambda x: getattr(x, "name", x))
def test_imports_follow_the_layout(pkg, path):
    ours = set(ALLOWED)
    for line, mod in _imported(path, pkg):
        if mod in ours:
            assert mod in ALLOWED[pkg], f"{_rel(path)}:{line} ({pkg}) imports {mod}"
        assert mod not in FORBIDDEN_THIRD_PARTY.get(pkg, ()), f"{_rel(path)}:{line} imports {mod}"


@pytest.mark.parametrize(("pkg", "path"), ALL_FILES, ids=lambda x: getattr(x, "name", x))
def test_modules_stay_small(pkg, path):
    n = len(path.read_text().splitlines())
    assert n <= MAX_LINES, f"{_rel(path)} has {n} lines (at most {MAX_LINES})"


RUNTIME_FILES = [(pkg, f) for pkg, f in ALL_FILES if pkg in RUNTIME]


@pytest.mark.parametrize(("pkg", "path"), RUNTIME_FILES, ids=lambda x: getattr(x, "name", x))
def test_runtime_code_reads_no_test_or_shared_data(pkg, path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            v = node.value
            assert "tests/data" not in v, f"{_rel(path)}:{node.lineno} names tests/data"
            assert "../shared" not in v, f"{_rel(path)}:{node.lineno} names ../shared"


LEARNER_FILES = [f for pkg, f in ALL_FILES if pkg == LEARNER]


@pytest.mark.parametrize("path", LEARNER_FILES, ids=lambda p: p.name)
def test_learner_never_reads_truth(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            assert node.attr != "truth", f"{path.name}:{node.lineno} reads .truth"
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            assert node.value != "truth", f"{path.name}:{node.lineno} names 'truth'"
        if isinstance(node, ast.keyword):
            assert node.arg != "with_truth", f"{path.name}:{node.lineno} loads truth"


def test_the_checker_sees_hidden_and_relative_imports(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text(
        "import numpy\n"
        "def f():\n"
        "    from flyknot_sim import lab\n"
        "    import learner.ilc\n"
        "    from . import sibling\n"
        "    return lab\n"
    )
    assert _imported(probe, APP) == [(1, "numpy"), (3, "flyknot_sim"), (4, "learner"), (5, APP)]


def _module_of(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def _type_only(tree: ast.AST) -> set[int]:
    """Line numbers of imports inside ``if TYPE_CHECKING:`` blocks (no runtime import)."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            lines |= {n.lineno for b in node.body for n in ast.walk(b) if hasattr(n, "lineno")}
    return lines


def _module_graph(pkg: str, *, typing: bool = True) -> dict[str, set[str]]:
    """Module -> modules of the same package it imports (any depth, in functions too; with
    ``typing``, the imports under ``if TYPE_CHECKING:`` count as well: two modules that only
    name each other's types are still one room split in two)."""
    mods = {_module_of(f): f for f in _files(pkg)}
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, f in mods.items():
        tree = ast.parse(f.read_text())
        skip = set() if typing else _type_only(tree)
        for node in ast.walk(tree):
            if node.__class__ not in (ast.Import, ast.ImportFrom) or node.lineno in skip:
                continue
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:
                    parent = (
                        m.split(".")[: -node.level] if f.name != "__init__.py" else m.split(".")
                    )
                    base = ".".join([*parent, *([node.module] if node.module else [])])
                targets = [f"{base}.{a.name}" for a in node.names] + [base]
            graph[m] |= {t for t in targets if t in mods and t != m}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected sets of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


@pytest.mark.parametrize("pkg", [CORE, SIM, HW, LEARNER, APP, TOOLS])
def test_no_import_circle_inside_a_package(pkg):
    assert _cycles(_module_graph(pkg)) == []
    assert _cycles(_module_graph(pkg, typing=False)) == []


def test_the_circle_finder_finds_a_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
