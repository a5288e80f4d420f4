"""How the held end is closed, measured: free rays vs the tube, over recorded trials.

``flyknot-tools closure-study DIR ... [--json]`` reads the final rope of every trial under the
given run or replay directories (faulted trials skipped) and counts, per closure, how many of
the 31 ray closures name the most frequent knot type:

* ``free``: both ends closed by parallel rays (:func:`flyknot.knot.closure_votes`);
* ``tube``: the held end continued along the tube into the arm, the free end by rays
  (:func:`flyknot.verdict.with_tube`), the closure :mod:`flyknot.verdict` uses.

A near-tie (a share near 1/2) is a closure whose answer depends on the direction: the rope is
threaded at one of its ends. The table gives the histogram of the top share for each closure
and the classes the verdict then gives (``docs/judge.md``).
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.knot import DEFAULT_DIRECTIONS, closure_votes
from flyknot.verdict import JudgeParams, judge_centreline, with_tube
from flyknot_app.anatomy.trials import load_record
from flyknot_app.judging import final_frame, rejudge_directory

BINS = ((0, 12), (13, 18), (19, 20), (21, 24), (25, 28), (29, 30), (31, 31))
"""Bins of the top knot type's vote count (of 31) in the table."""


def _top(votes: dict[str, int]) -> int:
    return max(votes.values())


def study(directories: Sequence[str | Path]) -> dict[str, Any]:
    """Top-share histograms of both closures and the verdict classes over the trials."""
    params = JudgeParams()
    rows = []
    for d in directories:
        for r in rejudge_directory(d):
            if r.fault is not None or r.new is None:
                continue
            points = _final_points(r)
            free = closure_votes(points, n_directions=DEFAULT_DIRECTIONS)
            tube = closure_votes(with_tube(points, None, params.tube_length_m))
            rows.append(
                {
                    "trial": f"{Path(d).name}/{r.name}",
                    "free": free,
                    "tube": tube,
                    "klass": judge_centreline(points).klass,
                }
            )

    def histogram(key: str) -> dict[str, int]:
        tops = [_top(x[key]) for x in rows]
        return {f"{a}-{b}": sum(a <= t <= b for t in tops) for a, b in BINS}

    return {
        "trials": len(rows),
        "free": histogram("free"),
        "tube": histogram("tube"),
        "classes": dict(Counter(x["klass"] for x in rows)),
        "rows": rows,
    }


def _final_points(row) -> np.ndarray:
    """The rope at the end of a re-judged trial (its truth centreline's last finite frame)."""
    if row.kind == "replay":
        with np.load(row.path, allow_pickle=False) as z:
            return final_frame(z["centreline"])
    return final_frame(load_record(row.path).truth["centreline"])


def format_study(result: dict[str, Any]) -> str:
    """The histogram table (markdown)."""
    lines = [
        f"{result['trials']} trials; votes (of {DEFAULT_DIRECTIONS}) for the most frequent "
        "knot type",
        "",
        "| closure | " + " | ".join(result["free"]) + " |",
        "|---|" + "---|" * len(result["free"]),
    ]
    for key in ("free", "tube"):
        lines.append(f"| {key} | " + " | ".join(str(v) for v in result[key].values()) + " |")
    lines += ["", "classes: " + ", ".join(f"{k} {v}" for k, v in sorted(result["classes"].items()))]
    return "\n".join(lines)


def run(directories: Sequence[str], as_json: bool) -> str:
    """What ``flyknot-tools closure-study`` prints."""
    result = study(directories)
    if as_json:
        return json.dumps(result, indent=1)
    return format_study(result)
