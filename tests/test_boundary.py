"""The learner sees only what the real lab measures.

``learner/`` must not import the simulated lab nor read the simulator-only ``truth`` part of
a record. Checked statically on the source, so a new file cannot slip past.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

LEARNER = Path(__file__).resolve().parents[1] / "learner"
FILES = sorted(LEARNER.rglob("*.py"))


def test_there_is_learner_code():
    assert FILES, "learner/ holds no Python files"


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_learner_does_not_import_the_simulator(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module]
        for n in names:
            assert not n.startswith("flyknot_sim"), f"{path.name} imports {n}"


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_learner_never_reads_truth(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            assert node.attr != "truth", f"{path.name}:{node.lineno} reads .truth"
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            assert node.value != "truth", f"{path.name}:{node.lineno} names 'truth'"
        if isinstance(node, ast.keyword):
            assert node.arg != "with_truth", f"{path.name}:{node.lineno} loads truth"
