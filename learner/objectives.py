"""The objectives of the inverse-model QP: which measured errors it fits, a registry.

* ``"critical"`` (:class:`CriticalPoint`, the paper's): the rope state at the critical point
  alone, e = x_meas(t_c) - x_demo(t_c) (66,) [m, m/s], fitted by ||M(t_c) dk - e||_Q^2; when
  the record lost tracking before t_c, the latest earlier model step where both the record and
  the demonstration have markers (within ``fallback_s``).
* ``"equal"`` (:class:`EqualWeights`, the paper's baseline): every pre-collision model step
  t_k <= t_c where both have markers, weighted alike: (1/S) sum_k ||M(t_k) dk - e_k||_Q^2.
* ``"launch"`` (:class:`CriticalAndLaunch`): the critical point and a second one chosen from
  the demonstration, the launch t_l (the pre-collision step where the hand moves fastest, the
  flick that throws the loop): ||M(t_c) dk - e_c||_Q^2 + ||M(t_l) dk - e_l||_Q^2.

An objective reads the record (:meth:`errors`) and hands the QP builder its terms
(:meth:`qp_terms`); :func:`learner.update.ilc_update` does the rest the same way for every
objective. Adding one is one class and one line in :data:`OBJECTIVES`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from flyknot.errors import ConfigError, RecordError
from flyknot.record import TrialRecord
from learner.critical_state import MarkerFitParams, critical_state_from_record
from learner.target import STATE_DIM, TIME_TOL, DemoTarget


@dataclass(frozen=True)
class ErrorTerms:
    """The measured errors an objective fits.

    Attributes:
        err: x_meas - x_demo at the critical point used (66,) [m, m/s]; NaN for an objective
            that does not need it when tracking was lost there.
        k_c: Model step of that critical point.
        t_eff: Its time [s]: t_c, or the fallback's.
        samples: ``((k, e_k), ...)``: the errors at other model steps the objective fits.
    """

    err: np.ndarray
    k_c: int
    t_eff: float
    samples: tuple[tuple[int, np.ndarray], ...] = field(default_factory=tuple)


def _mean_critical_error(
    records: Sequence[TrialRecord], base: np.ndarray, target: DemoTarget, fit: MarkerFitParams
) -> np.ndarray:
    """mean_i (x_i(t_c) - x_demo(t_c)) over the first record and those of the others that
    kept tracking to t_c (each play's noise averages out).

    Raises:
        RecordError: the first record lost tracking before t_c.
    """
    errs = [critical_state_from_record(records[0], target.t_c, base, fit) - target.x_c]
    for other in records[1:]:
        try:
            errs.append(critical_state_from_record(other, target.t_c, base, fit) - target.x_c)
        except RecordError:
            continue
    return np.mean(errs, axis=0)


def error_at(
    record: TrialRecord, target: DemoTarget, base: np.ndarray, fit: MarkerFitParams, t: float
) -> np.ndarray:
    """x_meas(t) - x_demo(t) (66,) [m, m/s] at t = t_c or at a model step t_k < t_c.

    Raises:
        RecordError: the record lost tracking before t, or t is neither t_c nor a step
            where the demonstration's markers exist.
    """
    if abs(t - target.t_c) < TIME_TOL:
        x_demo = target.x_c
    else:
        k = int(np.argmin(np.abs(target.t[: len(target.x_pre)] - t)))
        if abs(target.t[k] - t) > TIME_TOL or not np.all(np.isfinite(target.x_pre[k])):
            raise RecordError(f"no demonstration state at t = {t:.3f} s")
        x_demo = target.x_pre[k]
    return critical_state_from_record(record, float(t), base, fit) - x_demo


def fallback_critical_point(
    record: TrialRecord,
    target: DemoTarget,
    base: np.ndarray,
    fit: MarkerFitParams,
    fallback_s: float,
) -> tuple[int, np.ndarray]:
    """The latest model step k with t_c - fallback_s <= t_k < t_c (by default any step) where
    the record's and the demonstration's marker states both exist, and the error there,
    x_meas(t_k) - x_demo(t_k).

    Raises:
        RecordError: no such step (tracking lost before t_c - fallback_s).
    """
    grid = target.t
    for k in range(len(target.x_pre) - 1, -1, -1):
        if grid[k] >= target.t_c - TIME_TOL:
            continue
        if grid[k] < target.t_c - fallback_s - TIME_TOL:
            break
        if not np.all(np.isfinite(target.x_pre[k])):
            continue
        try:
            x = critical_state_from_record(record, float(grid[k]), base, fit)
        except RecordError:
            continue
        return k, x - target.x_pre[k]
    raise RecordError(
        f"tracking lost before t_c = {target.t_c:.3f} s and no state within "
        f"{fallback_s:.3f} s before it"
    )


@dataclass(frozen=True)
class CriticalPoint:
    """The paper's critical-point objective (module docstring)."""

    name: str = "critical"
    description: str = "the rope state at the critical point t_c alone (the paper's)"
    takes_jacobian: bool = True
    """A Jacobian measured or corrected elsewhere may replace the model's M(t_c)."""

    def errors(
        self,
        records: Sequence[TrialRecord],
        base: np.ndarray,
        target: DemoTarget,
        k_c: int,
        fit: MarkerFitParams,
        fallback_s: float,
    ) -> ErrorTerms:
        """e at t_c (averaged over ``records``, the trial's first), or at the fallback step."""
        try:
            return ErrorTerms(_mean_critical_error(records, base, target, fit), k_c, target.t_c)
        except RecordError:
            k, err = fallback_critical_point(records[0], target, base, fit, fallback_s)
            return ErrorTerms(err, k, float(target.t[k]))

    def qp_terms(self, terms: ErrorTerms, M_at: Callable[[int], np.ndarray], M_c) -> dict:
        """The builder's critical-point term."""
        return {"M_crit": M_c, "err_crit": terms.err}

    def fit_times(self, target: DemoTarget) -> tuple[float, ...]:
        """The times [s] whose rope state the objective fits (a measured Jacobian is taken
        there): (t_c,)."""
        return (target.t_c,)


@dataclass(frozen=True)
class EqualWeights:
    """Every pre-collision sample weighted alike (the paper's baseline; module docstring)."""

    name: str = "equal"
    description: str = "every pre-collision sample weighted alike (the paper's baseline)"
    takes_jacobian: bool = False

    def errors(
        self,
        records: Sequence[TrialRecord],
        base: np.ndarray,
        target: DemoTarget,
        k_c: int,
        fit: MarkerFitParams,
        fallback_s: float,
    ) -> ErrorTerms:
        """e_k at every pre-collision model step with markers in both (and e at t_c, NaN if
        lost there).

        Raises:
            RecordError: no such step.
        """
        try:
            err = _mean_critical_error(records, base, target, fit)
        except RecordError:
            err = np.full(STATE_DIM, np.nan)
        samples = []
        for k, x_demo in enumerate(target.x_pre):
            if not np.all(np.isfinite(x_demo)):
                continue
            try:
                x_meas = critical_state_from_record(records[0], float(target.t[k]), base, fit)
            except RecordError:
                continue
            samples.append((k, x_meas - x_demo))
        if not samples:
            raise RecordError(
                "no pre-collision model step has markers in both the record and the "
                "demonstration (equal objective)"
            )
        return ErrorTerms(err, k_c, target.t_c, tuple(samples))

    def qp_terms(self, terms: ErrorTerms, M_at: Callable[[int], np.ndarray], M_c) -> dict:
        """The builder's equally weighted terms, one per sample."""
        return {"equal": [(M_at(k), e) for k, e in terms.samples]}


def launch_step(target: DemoTarget) -> int:
    """k_l = argmax_k ||v_hand(t_k)|| over the pre-collision steps t_k < t_c where the
    demonstration has markers: the flick that throws the loop (model step index).

    Raises:
        RecordError: no pre-collision step before t_c has markers.
    """
    t = target.t[: len(target.x_pre)]
    usable = np.all(np.isfinite(target.x_pre), axis=1) & (t < target.t_c - TIME_TOL)
    if not np.any(usable):
        raise RecordError("no pre-collision step before t_c has markers (launch objective)")
    speed = np.linalg.norm(target.hand_at(t)[2], axis=1)  # (S,) [m/s]
    return int(np.argmax(np.where(usable, speed, -np.inf)))


@dataclass(frozen=True)
class CriticalAndLaunch(CriticalPoint):
    """The critical point and the launch, weighted alike (module docstring)."""

    name: str = "launch"
    description: str = (
        "the rope state at t_c and at the launch (the hand's fastest pre-collision step)"
    )

    def errors(
        self,
        records: Sequence[TrialRecord],
        base: np.ndarray,
        target: DemoTarget,
        k_c: int,
        fit: MarkerFitParams,
        fallback_s: float,
    ) -> ErrorTerms:
        """e at t_c as :class:`CriticalPoint`'s, and e_l at the launch step (first record).

        Raises:
            RecordError: the record lost tracking before the launch.
        """
        at_c = super().errors(records, base, target, k_c, fit, fallback_s)
        k_l = launch_step(target)
        x_l = critical_state_from_record(records[0], float(target.t[k_l]), base, fit)
        return ErrorTerms(at_c.err, at_c.k_c, at_c.t_eff, ((k_l, x_l - target.x_pre[k_l]),))

    def qp_terms(self, terms: ErrorTerms, M_at: Callable[[int], np.ndarray], M_c) -> dict:
        """The critical-point term and the launch as one more point of the same weight."""
        return {
            **super().qp_terms(terms, M_at, M_c),
            "points": [(M_at(k), e) for k, e in terms.samples],
        }

    def fit_times(self, target: DemoTarget) -> tuple[float, ...]:
        """(t_c, t_l) [s]: the critical point and the launch."""
        return (target.t_c, float(target.t[launch_step(target)]))


OBJECTIVES = {o.name: o for o in (CriticalPoint(), EqualWeights(), CriticalAndLaunch())}
"""Every objective, by the name the ``objective`` option gives."""


def objective_kind(name: object) -> CriticalPoint | EqualWeights:
    """The registered objective ``name``; the error lists the valid ones."""
    if not isinstance(name, str) or name not in OBJECTIVES:
        raise ConfigError("objective", f"unknown value {name!r}", list(OBJECTIVES))
    return OBJECTIVES[name]


__all__ = [
    "OBJECTIVES",
    "CriticalAndLaunch",
    "CriticalPoint",
    "EqualWeights",
    "ErrorTerms",
    "fallback_critical_point",
    "launch_step",
    "objective_kind",
]
