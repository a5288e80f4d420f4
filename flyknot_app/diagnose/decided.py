"""Where the knot is decided: the time at which the rope states of tying and untying trials part.

A measuring stick (``flyknot diagnose decided DIR ...``). Given trials of commands near one
another (the repeats of a command under the lab's trial-to-trial variation, or the trials of
learning runs near their floor), split them by their verdict (class ``knot`` against every
other class) and compare their rope states over time. At each time t, with p_i(t) (33,) the
11 marker positions [m] of trial i:

    d(t) = |mean_{i in knot} p_i(t) - mean_{j not knot} p_j(t)|          class distance [m]
    s(t) = sqrt( (sum_knot |p_i - mean_knot|^2 + sum_not |p_j - mean_not|^2) / (n - 2) )
                                                                         within-class spread [m]
    r(t) = d(t) / s(t)                                                   separation [-]

The knot is decided where r(t) first reaches ``threshold`` (default 1: the classes are as far
apart as their own scatter) and stays there. A critical point placed before that time sees
states that do not yet tell tying from not tying; one after it is where an objective can
steer. The markers are the lab's (NaN after tracking is lost: such a time is skipped when
fewer than two trials of a class remain), or, in a simulated lab, its ground truth
(``truth=True``) to look past the first self-contact.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flyknot.errors import ConfigError, check_positive


@dataclass(frozen=True)
class Separation:
    """The separation of tying and untying trials over time.

    Attributes:
        t: Times (k,) [s] on the markers' clock (0 at the command's start).
        distance: d(t) (k,) [m]; NaN where a class has fewer than two trials.
        spread: s(t) (k,) [m].
        ratio: r(t) (k,) [-].
        n_knot: Trials that tied.
        n_other: Trials that did not.
        t_decided: The first time from which r(t) >= threshold to the end, or None.
        threshold: The threshold used.
    """

    t: np.ndarray
    distance: np.ndarray
    spread: np.ndarray
    ratio: np.ndarray
    n_knot: int
    n_other: int
    t_decided: float | None
    threshold: float

    def to_json(self) -> dict:
        """Plain data."""
        return {
            "t": self.t.round(4).tolist(),
            "distance": np.round(self.distance, 4).tolist(),
            "spread": np.round(self.spread, 4).tolist(),
            "ratio": np.round(self.ratio, 3).tolist(),
            "n_knot": self.n_knot,
            "n_other": self.n_other,
            "t_decided": self.t_decided,
            "threshold": self.threshold,
        }


def class_separation(knot: np.ndarray, other: np.ndarray) -> tuple[float, float]:
    """(d, s) of two classes of states, (n_a, D) and (n_b, D) [m] (module docstring).

    Raises:
        ConfigError: A class has fewer than two states.
    """
    knot, other = np.asarray(knot, dtype=float), np.asarray(other, dtype=float)
    if len(knot) < 2 or len(other) < 2:
        raise ConfigError("trials", "each class needs at least two trials")
    mk, mo = knot.mean(axis=0), other.mean(axis=0)
    within = np.sum((knot - mk) ** 2) + np.sum((other - mo) ** 2)
    spread = float(np.sqrt(within / (len(knot) + len(other) - 2)))
    return float(np.linalg.norm(mk - mo)), spread


def separation(
    t: np.ndarray, states: np.ndarray, tied: np.ndarray, threshold: float = 1.0
) -> Separation:
    """r(t) of trials' states (n, k, D) [m] at times t (k,) [s], split by ``tied`` (n,).

    Trials with a NaN state at a time are left out there; a time with fewer than two trials
    in a class gets NaN.
    """
    check_positive("threshold", threshold)
    t, states, tied = np.asarray(t, float), np.asarray(states, float), np.asarray(tied, bool)
    if states.ndim != 3 or states.shape[:2] != (tied.size, t.size):
        raise ConfigError("states", f"need shape (n, {t.size}, D) for {tied.size} trials")
    dist, spread = np.full(t.size, np.nan), np.full(t.size, np.nan)
    for k in range(t.size):
        ok = np.all(np.isfinite(states[:, k]), axis=1)
        a, b = states[ok & tied, k], states[ok & ~tied, k]
        if len(a) >= 2 and len(b) >= 2:
            dist[k], spread[k] = class_separation(a, b)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = dist / spread
    return Separation(
        t, dist, spread, ratio, int(tied.sum()), int((~tied).sum()),
        decided_time(t, ratio, threshold), float(threshold),
    )  # fmt: skip


def decided_time(t: np.ndarray, ratio: np.ndarray, threshold: float) -> float | None:
    """The first time from which every finite ratio is >= threshold, or None."""
    finite = np.isfinite(ratio)
    if not finite.any():
        return None
    below = np.flatnonzero(finite & (ratio < threshold))
    last_finite = np.flatnonzero(finite)[-1]
    if below.size and below[-1] == last_finite:
        return None
    start = 0 if below.size == 0 else below[-1] + 1
    after = np.flatnonzero(finite[start:])
    return float(t[start + after[0]])


def record_stems(paths: Sequence[str | Path]) -> list[Path]:
    """Every trial record under ``paths`` (directories searched recursively, or stems)."""
    stems: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            stems += sorted(q.with_suffix("") for q in p.rglob("*.json") if _is_record(q))
        elif _is_record(p.with_suffix(".json")):
            stems.append(p.with_suffix(""))
        else:
            raise ConfigError("DIR", f"{str(p)!r} is neither a directory nor a trial record")
    if not stems:
        raise ConfigError("DIR", "no trial records found under " + ", ".join(map(str, paths)))
    return stems


def _is_record(json_path: Path) -> bool:
    return json_path.is_file() and json_path.with_suffix(".npz").is_file()


def velocity_weight(lead_s: float, w_crit_pos: float) -> float:
    """w_crit_vel = w_crit_pos dt^2 [s^2/m^2]: a marker's velocity error weighed as the position
    error it makes in ``lead_s`` = dt [s] (from the first self-contact to where the knot is
    decided), for the critical cost's position weight ``w_crit_pos`` [1/m^2]."""
    check_positive("lead_s", lead_s)
    check_positive("w_crit_pos", w_crit_pos)
    return float(w_crit_pos * lead_s**2)


def lead_after_contact(t_decided: float | None, contacts: np.ndarray, w_crit_pos: float) -> dict:
    """How long after the trials' median first self-contact ``contacts`` (n,) [s] the knot is
    decided, and the velocity weight for that lead (:func:`velocity_weight`); ``{}`` when the
    records do not know their contacts or the knot is decided at or before them."""
    known = contacts[np.isfinite(contacts)]
    if t_decided is None or known.size == 0:
        return {}
    t_contact = float(np.median(known))
    if t_decided <= t_contact:
        return {}
    lead = t_decided - t_contact
    return {
        "t_contact": round(t_contact, 4),
        "lead_s": round(lead, 4),
        "w_crit_vel": round(velocity_weight(lead, w_crit_pos), 5),
    }


def trial_states(
    stems: Sequence[Path], t: np.ndarray, *, truth: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The marker positions (n, k, 33) [m] of each record at times t (linear interpolation,
    NaN outside its samples or where lost), whether each tied (n,) and its first self-contact
    time (n,) [s] (NaN where the record does not know it: a real lab's); faulted and unjudged
    records are left out."""
    from flyknot.record import TrialRecord

    states, tied, contacts = [], [], []
    for stem in stems:
        rec = TrialRecord.load(stem, with_truth=truth)
        if rec.fault is not None or rec.verdict is None:
            continue
        if truth:
            if not rec.truth:
                raise ConfigError("--truth", f"{str(stem)!r} has no ground truth (not simulated)")
            tm, m = rec.truth["t_truth"], rec.truth["markers"]
        else:
            tm, m = rec.t_marker, rec.markers
        flat = m.reshape(len(tm), -1)
        cols = [np.interp(t, tm, flat[:, c], left=np.nan, right=np.nan) for c in range(33)]
        states.append(np.stack(cols, axis=1))
        tied.append(rec.succeeded)
        contacts.append(np.nan if rec.first_contact_time is None else rec.first_contact_time)
    return np.array(states), np.array(tied, dtype=bool), np.array(contacts, dtype=float)


__all__ = [
    "Separation",
    "class_separation",
    "decided_time",
    "lead_after_contact",
    "record_stems",
    "separation",
    "trial_states",
    "velocity_weight",
]
