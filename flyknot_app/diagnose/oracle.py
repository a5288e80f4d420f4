"""The oracle Jacobian: the simulated lab's own M(t) = dx(t)/dkappa, measured.

A measuring stick for the learner (``jacobian = "oracle"``, :mod:`learner.jacobians`): the
same objective and QP as the paper's update, with the rope model's linearisation replaced by
the lab's response, so a run with it bounds what any model-based ILC can do on that objective.

For knots kappa and every free knot group g (the columns the QP's equality rows let move):

    M[:, g] = (x(kappa + h e_g) - x(kappa - h e_g)) / (2 h)        (66,) [m/rad, m/s/rad]

x(kappa) (66,) is the rope state the learner measures (:func:`critical_state_from_record`:
11 marker positions [m] and velocities [m/s] in the demonstration frame) at each time the
objective fits (t_c, and t_l for the launch objective: every time from the same plays),
played in a copy of the lab without trial-to-trial variation, capture noise or tracking
loss, and cut ``tail_s`` after the last of them (the state then does not depend on what the
arm does later). A side
that faults (the step crosses a limit) falls back to the one-sided difference; a group with
neither side gives a zero column. The free groups: per arm joint, knots {0, 1}, 2, 3, 4, 5,
{6, 7} (the command starts and ends at rest: :func:`learner.inverse_qp.rest_equality_rows`),
and each base row as a whole (constant within a trial); a group's response goes in the
column of its first knot, the others' columns are zero, so M dkappa is exact for every
update the QP allows.

Only a simulated lab can replay a command without variation: on a real cell the oracle is
refused (:func:`flyknot_app.cells.oracle_provider`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from flyknot.constants import COMMAND_RATE_HZ, N_JOINTS, N_KNOTS, N_ROWS
from flyknot.errors import RecordError, check_positive
from flyknot.record import JointCommand, TrialRecord

STATE_DIM = 66
ARM_GROUPS = ((0, 1), (2,), (3,), (4,), (5,), (6, 7))
"""Knots of an arm row that move together (rest at both ends)."""


@dataclass(frozen=True)
class OracleParams:
    """How the oracle measures M(t).

    Attributes:
        step: Finite-difference step h on each knot group [rad] (base rows: [m]).
        tail_s: The command is played to the last fitted time + tail_s [s] (the marker
            fit's window is 25 ms on each side of it).
    """

    step: float = 0.01
    tail_s: float = 0.06

    def __post_init__(self) -> None:
        check_positive("oracle.step", self.step)
        check_positive("oracle.tail_s", self.tail_s)


def knot_groups() -> list[tuple[int, tuple[int, ...]]]:
    """The free (row, knots) groups of an update, in column order of their first knot."""
    arm = [(r, g) for r in range(N_JOINTS) for g in ARM_GROUPS]
    return arm + [(r, tuple(range(N_KNOTS))) for r in range(N_JOINTS, N_ROWS)]


def central_difference(
    x0: np.ndarray, xp: np.ndarray | None, xm: np.ndarray | None, h: float
) -> np.ndarray:
    """(xp - xm) / 2h, or the one-sided difference when one side is missing, or zeros."""
    if xp is not None and xm is not None:
        return (xp - xm) / (2.0 * h)
    if xp is not None:
        return (xp - x0) / h
    if xm is not None:
        return (x0 - xm) / h
    return np.zeros_like(x0)


class LabJacobian:
    """M(t) of a simulated lab by finite differences (module docstring).

    A :data:`learner.jacobians.JacobianProvider`: ``LabJacobian(...)(knots, T)``.
    """

    def __init__(self, lab_params, t_c: float, params: OracleParams = OracleParams()):
        from flyknot_sim.lab import SimLab, VariationParams
        from flyknot_sim.mocap import MocapParams

        check_positive("t_c", t_c)
        quiet = dataclasses.replace(
            lab_params,
            variation=VariationParams.none(),
            mocap=MocapParams(noise_std=0.0, loss_mode="none"),
            settle_s=0.0,
            brake_s=0.0,
        )
        self.lab = SimLab(quiet)
        self.t_c = float(t_c)
        self.params = params
        self.plays = 0
        """Commands played so far."""

    def play(self, knots: np.ndarray, T: float, until: float | None = None) -> TrialRecord:
        """The record of ``knots`` played to ``until`` (default t_c) + ``tail_s`` [s] without
        variation."""
        from learner.bezier import BezierCommand

        until = self.t_c if until is None else until
        command = BezierCommand(knots, T).joint_command()
        n = min(command.n, int(np.ceil((until + self.params.tail_s) * COMMAND_RATE_HZ)) + 1)
        self.plays += 1
        return self.lab.run(JointCommand(np.asarray(command.q)[:n], command.rate_hz))

    def state(self, knots: np.ndarray, T: float, times: tuple[float, ...]) -> np.ndarray | None:
        """x(kappa) at each of ``times`` stacked, (P * 66,) [m, m/s], from one play; None when
        it faulted before the last of them."""
        from learner.critical_state import critical_state_from_record

        record = self.play(knots, T, max(times))
        try:
            return np.concatenate(
                [critical_state_from_record(record, t, knots[N_JOINTS:, 0]) for t in times]
            )
        except RecordError:
            return None

    def __call__(
        self, knots: np.ndarray, T: float, times: tuple[float, ...] | None = None
    ) -> dict[float, np.ndarray]:
        """{t: M(t) (66, 80)} about ``knots`` (10, 8) for a command of duration ``T`` [s] at
        each of ``times`` [s] (default: t_c alone), all from the same plays.

        Raises:
            RecordError: The command itself faults before the last of ``times``.
        """
        times = (self.t_c,) if times is None else tuple(float(t) for t in times)
        knots = np.asarray(knots, dtype=float)
        x0 = self.state(knots, T, times)
        if x0 is None:
            raise RecordError("the oracle's nominal play faulted before the fitted times")
        h = self.params.step
        M = np.zeros((len(times) * STATE_DIM, N_ROWS * N_KNOTS))
        for row, group in knot_groups():
            d = np.zeros((N_ROWS, N_KNOTS))
            d[row, list(group)] = h
            xp, xm = self.state(knots + d, T, times), self.state(knots - d, T, times)
            M[:, row * N_KNOTS + group[0]] = central_difference(x0, xp, xm, h)
        return {t: M[i * STATE_DIM : (i + 1) * STATE_DIM] for i, t in enumerate(times)}


__all__ = ["ARM_GROUPS", "LabJacobian", "OracleParams", "central_difference", "knot_groups"]
