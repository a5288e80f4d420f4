"""The README's two commands: the main job, and the test command CI runs."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _first_block() -> list[str]:
    text = (ROOT / "README.md").read_text()
    match = re.search(r"```bash\n(.*?)```", text, re.DOTALL)
    assert match, "README has no bash block"
    return [line for line in match.group(1).splitlines() if line.strip()]


def test_the_readme_opens_with_exactly_two_commands():
    lines = _first_block()
    assert len(lines) == 2
    assert lines[0].endswith("flyknot run learn-rope1")


def test_the_test_command_is_what_ci_runs_and_installs_the_browser():
    assert _first_block()[1] == "bash .ci/run"
    ci = (ROOT / ".ci" / "run").read_text()
    packages = (ROOT / ".ci" / "system-packages").read_text()
    assert "bash .ci/system-packages" in ci
    assert "chromium-driver" in packages and "apt-get install" in packages
    assert "pytest -q -n 2" in ci
    assert '"$status" -eq 5' in ci  # pytest's "no tests" exit fails CI


def test_code_and_docs_say_what_is_not_what_was():
    """No history narration (an issue's or a session's number, "the old", "before it
    existed", "ends today", "since the table above") in the packages, tests, README, docs,
    data."""
    pattern = re.compile(
        r"\b(issue|session) [0-9]+|\bthe old\b|before it existed|ends today|"
        r"since the table above",
        re.IGNORECASE,
    )
    roots = ["flyknot", "flyknot_sim", "flyknot_hw", "learner", "flyknot_app", "flyknot_tools"]
    files = [ROOT / "README.md"]
    for d in ["docs", "scenarios", "assets", "tests", *roots]:
        files += [p for p in (ROOT / d).rglob("*") if p.suffix in (".py", ".md", ".toml")]
    files = [p for p in files if p.resolve() != Path(__file__).resolve()]  # names them
    hits = [
        f"{p.relative_to(ROOT)}:{n}"
        for p in files
        for n, line in enumerate(p.read_text().splitlines(), 1)
        if pattern.search(line)
    ]
    assert hits == []
