"""The files of one learning run (:class:`RunDirectory`) and its ledger lines (TrialSummary).

:func:`learner.ilc.learn` writes everything as it happens, so a run interrupted at any point
resumes from the ledger without losing or repeating a trial.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np


@dataclass(frozen=True)
class TrialSummary:
    """One trial of a learning run, as written to ``ledger.jsonl``."""

    trial: int
    attempt: int
    fault: str | None
    knot: str | None
    tracking_lost: bool
    cost: float | None
    update_solved: bool | None
    update_status: str | None
    predicted_cost_after: float | None
    action: str
    wall_s: float
    t_eff: float | None = None
    confirm: int | None = None
    average: int | None = None
    verdict: dict[str, Any] | None = None

    @property
    def success(self) -> bool:
        """The trial ran without fault and its verdict (``Verdict.to_json``) is a knot in the
        hanging rope (class ``"knot"``); a trial without a verdict never counts."""
        return self.fault is None and self.verdict is not None and self.verdict["klass"] == "knot"


class RunDirectory:
    """Files of one learning run, written as they happen.

    Layout::

        manifest.json              what was run (free-form, written once)
        knots_0000.npy             kappa_k before trial k (10, 8)
        trial_0000_a0.{npz,json,truth.npz}   the record of trial k, attempt a
        update_0000.json           the update computed after trial k
        ledger.jsonl               one line per attempt (TrialSummary), the resume point
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)

    def knots_path(self, k: int) -> Path:
        """File of the command played in trial ``k``."""
        return self.path / f"knots_{k:04d}.npy"

    def record_stem(self, k: int, attempt: int) -> Path:
        """Stem of the record files of trial ``k``, attempt ``attempt``."""
        return self.path / f"trial_{k:04d}_a{attempt}"

    def write_manifest(self, manifest: dict[str, Any]) -> None:
        """Write what was run (once, at the start)."""
        (self.path / "manifest.json").write_text(json.dumps(manifest, indent=2, sort_keys=True))

    def save_knots(self, k: int, knots: np.ndarray) -> None:
        """Save the command of trial ``k`` (10, 8) atomically (write, then rename)."""
        tmp = self.path / f".knots_{k:04d}.tmp.npy"
        np.save(tmp, np.asarray(knots))
        tmp.replace(self.knots_path(k))

    def load_knots(self, k: int) -> np.ndarray:
        """The command of trial ``k``, (10, 8)."""
        return np.load(self.knots_path(k))

    def append_ledger(self, summary: TrialSummary) -> None:
        """Append one attempt to the ledger (the commit point of a resumed run)."""
        with open(self.path / "ledger.jsonl", "a") as f:
            f.write(json.dumps(asdict(summary)) + "\n")

    def ledger(self) -> list[TrialSummary]:
        """Every attempt written so far, in order."""
        p = self.path / "ledger.jsonl"
        if not p.is_file():
            return []
        out = []
        for line in p.read_text().splitlines():
            if line.strip():
                out.append(TrialSummary(**json.loads(line)))
        return out

    def save_update(self, k: int, info: dict[str, Any]) -> None:
        """Save the update computed after trial ``k``."""
        (self.path / f"update_{k:04d}.json").write_text(json.dumps(info, indent=2))

    def load_update(self, k: int) -> dict[str, Any] | None:
        """The update computed after trial ``k``, or None if there is none."""
        p = self.path / f"update_{k:04d}.json"
        return json.loads(p.read_text()) if p.is_file() else None


__all__ = ["RunDirectory", "TrialSummary"]
