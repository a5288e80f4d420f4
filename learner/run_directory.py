"""The files of one learning run (:class:`RunDirectory`) and its ledger lines (TrialSummary).

:func:`learner.ilc.learn` writes everything as it happens, so a run interrupted at any point
resumes from the ledger without losing or repeating a trial.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from flyknot.errors import RecordError
from flyknot.record import TrialRecord, atomic_write_text

if TYPE_CHECKING:
    from learner.update import UpdateResult


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
        """Append one attempt to the ledger (the commit point of a resumed run), flushed and
        synced: a line is on disk whole, or it is the last line, cut short (dropped here
        before the next line is written)."""
        p = self.path / "ledger.jsonl"
        if p.is_file():
            text = p.read_bytes()
            if text and not text.endswith(b"\n"):
                with open(p, "r+b") as f:
                    f.truncate(text.rfind(b"\n") + 1)
        with open(p, "a") as f:
            f.write(json.dumps(asdict(summary)) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def ledger(self) -> list[TrialSummary]:
        """Every attempt written so far, in order; a last line cut short by a kill is not
        written (its attempt runs again).

        Raises:
            RecordError: A line before the last is not a ledger line (the message names it).
        """
        p = self.path / "ledger.jsonl"
        if not p.is_file():
            return []
        text = p.read_text()
        lines = text.splitlines()
        out = []
        for n, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            try:
                out.append(TrialSummary(**json.loads(line)))
            except (ValueError, TypeError) as e:
                if n == len(lines) and not text.endswith("\n"):
                    break  # the write of the last attempt was cut short
                raise RecordError(f"{str(p)!r} line {n} is not a ledger line ({e})") from e
        return out

    def save_update(self, k: int, update: UpdateResult) -> None:
        """Save the update computed after trial ``k`` (atomically): the one place an update
        becomes plain data (``update_0000.json``: docs/run-directory.md)."""
        info = {
            "trial": k,
            "solved": update.solved,
            "status": update.qp_status,
            "cost_before": update.cost_before,
            "predicted_cost_after": update.predicted_cost_after,
            "err": update.err.tolist(),
            "dkappa": update.dkappa.tolist(),
            "new_knots": update.new_knots.tolist(),
            "timings": dict(update.timings),
            "limit_rounds": update.limit_rounds,
            "t_eff": update.t_eff,
            "sampled_violation": update.sampled_violation,
        }
        atomic_write_text(self.path / f"update_{k:04d}.json", json.dumps(info, indent=2))

    def load_update(self, k: int) -> dict[str, Any] | None:
        """The update computed after trial ``k``, or None if there is none."""
        p = self.path / f"update_{k:04d}.json"
        return json.loads(p.read_text()) if p.is_file() else None


def written_record(stem: Path | None) -> TrialRecord | None:
    """The record a killed run left at ``stem``, or None when it is absent or unreadable (a
    file cut short: the trial is played again, on the same trial index of the cell). The
    learner's view: the record without the simulator's truth."""
    if stem is None or not stem.with_name(stem.name + ".json").is_file():
        return None
    try:
        return TrialRecord.load(stem)
    except RecordError:
        return None


__all__ = ["RunDirectory", "TrialSummary", "written_record"]
