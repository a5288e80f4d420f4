"""Why the trials of each rope ended as they did, for ``docs/results.md``.

The failure anatomy (:mod:`flyknot_app.anatomy`) of a paper scenario's runs, pooled over the
lab seeds and grouped by rope: the learning trials of ``03-ropes`` and the repeats of
``04-success-rate`` (:data:`BY_ROPE`). Each run's own anatomy stays in its scenario's
``report.md``.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from flyknot.errors import FlyknotError
from flyknot_app.anatomy.diagnosis import DESCRIPTIONS, LABELS
from flyknot_app.anatomy.report import Anatomy, explain_directory, plot_anatomy

__all__ = ["BY_ROPE", "anatomy_by_rope", "anatomy_figures", "anatomy_section"]

BY_ROPE = {"03-ropes": "learning", "04-success-rate": "repeats"}
"""The scenarios whose anatomy ``docs/results.md`` shows by rope, and which of their trials:
``learning`` (the learning trials) or ``repeats`` (the learned commands' repeats)."""


_WHAT = {"learning": "learning trials", "repeats": "learned commands' repeats"}


def _rope_key(rope: object) -> tuple[int, str]:
    """Paper ropes by id, then a user's ropes by name."""
    return (0, f"{rope:09d}") if isinstance(rope, int) else (1, str(rope))


def anatomy_by_rope(scenario_dir: str | Path, part: str) -> Anatomy | None:
    """The diagnoses of ``part`` (``learning`` or ``repeats``) of every run under
    ``scenario_dir``, each grouped as its run's rope (``rope R``), the ropes in order; None
    when the directory holds no summary or no such trials."""
    scenario_dir = Path(scenario_dir)
    try:
        doc = json.loads((scenario_dir / "summary.json").read_text())
        anatomy = explain_directory(scenario_dir)
    except (OSError, ValueError, FlyknotError):
        return None
    rope_of = {r["name"]: r["rope"] for r in doc.get("runs", [])}
    kept = []
    for d in anatomy.diagnoses:
        run, _, rest = d.group.partition("/")
        if run in rope_of and (rest == "repeats") == (part == "repeats"):
            kept.append((_rope_key(rope_of[run]), replace(d, group=f"rope {rope_of[run]}")))
    if not kept:
        return None
    kept.sort(key=lambda pair: pair[0])  # stable: each rope's trials keep their order
    return Anatomy(f"{scenario_dir.name} ({part})", tuple(d for _, d in kept))


def anatomy_figures(out: str | Path, folder: str | Path, prefix: str) -> dict[str, str]:
    """Draw each :data:`BY_ROPE` scenario's anatomy by rope into ``folder`` as
    ``<scenario>-anatomy.png``; keyed ``<scenario>-anatomy``, each picture's path as the
    document links it, ``prefix/<file>``."""
    found = {}
    for name, part in BY_ROPE.items():
        anatomy = anatomy_by_rope(Path(out) / name, part)
        if anatomy is not None:
            path = plot_anatomy(anatomy, Path(folder) / f"{name}-anatomy.png", anatomy.source)
            found[f"{name}-anatomy"] = f"{prefix}/{path.name}"
    return found


def anatomy_section(out: str | Path, name: str, pictures: dict[str, str] | None) -> list[str]:
    """The lines under scenario ``name``'s table: its trials' anatomy by rope, a row per rope
    with the count of each outcome that occurs, and its figure when ``pictures`` has one
    (none for a scenario outside :data:`BY_ROPE`)."""
    part = BY_ROPE.get(name)
    anatomy = None if part is None else anatomy_by_rope(Path(out) / name, part)
    if anatomy is None:
        return []
    used = [lab for lab in LABELS if anatomy.counts()[lab]]
    lines = [
        f"Why the {_WHAT[part]} of `{name}` ended as they did, by rope, over every seed "
        f"(`flyknot explain OUT/{name}`): "
        + "; ".join(f"`{lab}` {DESCRIPTIONS[lab]}" for lab in used)
        + ".",
        "",
        "| rope | trials | " + " | ".join(used) + " |",
        "|---|---" + "|---" * len(used) + "|",
    ]
    for group in anatomy.groups():
        c = anatomy.counts(group)
        lines.append(
            f"| {group} | {sum(c.values())} | " + " | ".join(str(c[u]) for u in used) + " |"
        )
    picture = (pictures or {}).get(f"{name}-anatomy")
    if picture is not None:
        lines += ["", f"![the anatomy of `{name}` by rope]({picture})"]
    return [*lines, ""]
