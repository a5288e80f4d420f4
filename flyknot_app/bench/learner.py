"""``flyknot bench learner``: wall times of one ILC update on a realistic problem.

The problem: a smooth 0.8 s command from the xArm 7 home pose
q = (0, -0.247, 0, 0.909, 0, 1.15644, 0) rad with the base offset (0, 0, 1.0) m (joint speeds up
to 2 rad/s, accelerations up to 16 rad/s^2), the paper's rope model, t_c = 0.45 s. The "real
system" is the model itself (:func:`learner.system_model.model_record`) and the target comes
from the model under a perturbed command, so the numbers measure the learner's computation
only. The QP has the paper's weights, the follow-through terms and the paper's limits.

Reported (each the best of ``repeats`` runs, in seconds):
    rollout_s       model rollout driven by the measured joints, up to t_c
    rollout_numpy_s the same with the step's Newton iteration in NumPy instead of compiled
    compiled_over_numpy  rollout_numpy_s / rollout_s (measured in the same run)
    compiled_max_dx |x_compiled - x_numpy| over the rollout's states [m, m/s]
    linearise_s     M = dx(t_c)/dkappa by the implicit function theorem (80 columns)
    linearise_numpy_s  the same with the propagation in NumPy instead of compiled
    qp_build_s      follow-through terms + all limit rows + the QP of the first round
    qp_osqp_s       solving that QP with OSQP
    qp_clarabel_s   solving that QP with Clarabel
    update_s        the whole :func:`learner.update.ilc_update` call (error, rollout,
                    linearise, follow-through, limit rows, build, Clarabel solve, checks)
    update_interpreted_s  the same with the robot model in CasADi's interpreter instead of
                    compiled C (:mod:`learner.native`)
    native_over_interpreted  update_interpreted_s / update_s (measured in the same run)
    native_max_dknots  |new knots compiled - new knots interpreted| (0: bit for bit)
    fd_jacobian_s   the same M by central differences of 160 model rollouts up to t_c
    ift_over_fd     fd_jacobian_s / linearise_s (how many times faster the IFT is)
    fd_rel_err      ||M_ift - M_fd|| / ||M_fd||
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from flyknot.errors import ConfigError
from flyknot.progress import bar_disable
from flyknot.record import TrialRecord
from learner import rope_sensitivity
from learner.bezier import BezierCommand
from learner.follow_through import follow_through_terms
from learner.inverse_qp import InverseModelWeights, build_inverse_qp
from learner.kinematics import RobotModel
from learner.limit_rows import initial_active_rows, limit_rows, subset_rows
from learner.qp_solve import solve_qp
from learner.rope_model import RopeModelParams, _StepSolver
from learner.system_model import (
    critical_step,
    linearise,
    model_demonstration,
    model_record,
    rollout_from_joints,
    simulate_command,
)
from learner.target import DemoTarget
from learner.update import UpdateSettings, ilc_update

HOME = np.array([0.0, -0.247, 0.0, 0.909, 0.0, 1.15644, 0.0])  # [rad]
BASE = np.array([0.0, 0.0, 1.0])  # [m]
T_BENCH = 0.8  # [s]
T_C = 0.45  # [s]
_PROFILE = np.array([0.0, 0.0, 0.2, 1.0, 1.0, 0.2, 0.0, 0.0])  # rest at both ends
_AMPLITUDE = np.array([0.8, 0.4, 0.5, -0.6, 0.7, -0.5, 0.3])  # [rad]
FD_EPS = 1e-6  # [rad or m] central-difference step

KEYS = (
    "rollout_s",
    "rollout_numpy_s",
    "compiled_over_numpy",
    "compiled_max_dx",
    "linearise_s",
    "linearise_numpy_s",
    "qp_build_s",
    "qp_osqp_s",
    "qp_clarabel_s",
    "update_s",
    "update_interpreted_s",
    "native_over_interpreted",
    "native_max_dknots",
    "fd_jacobian_s",
    "ift_over_fd",
    "fd_rel_err",
)


def bench_command() -> BezierCommand:
    """The benchmark command: q = HOME + amplitude * profile over the 8 knots, base (0, 0, 1)."""
    knots = np.zeros((10, 8))
    knots[:7] = HOME[:, None] + _AMPLITUDE[:, None] * _PROFILE[None, :]
    knots[7:] = BASE[:, None]
    return BezierCommand(knots, T_BENCH)


def _best(fn: Callable[[], object], repeats: int, warm: bool = True) -> tuple[float, object]:
    """Best wall time of ``repeats`` calls of ``fn`` [s] and its last result; ``warm`` first
    calls it once untimed (compiled kernels are built, or loaded from numba's cache, at
    their first call in a process)."""
    if warm:
        fn()
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def bench_learner(repeats: int = 1, progress: bool = True) -> dict:
    """Time the pieces of one ILC update (module docstring); best of ``repeats`` each.

    Args:
        repeats: Runs per measurement (>= 1).
        progress: Show a progress bar.

    Returns:
        A dict with the keys in :data:`KEYS` plus ``problem`` (sizes and settings).
    """
    from tqdm import tqdm

    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ConfigError("repeats", f"must be an integer >= 1, got {repeats!r}")
    bar = tqdm(total=10, desc="bench learner", disable=bar_disable(progress), unit="stage")
    pb = _Problem.make()
    bar.update()
    res: dict = {}
    ro = _time_rollouts(pb, repeats, res)
    bar.update()
    M = _time_linearisations(pb, ro, repeats, res)
    bar.update()
    qp = _time_qp(pb, M, repeats, res, bar)
    upd = _time_updates(pb, repeats, res, bar)
    res["fd_jacobian_s"], M_fd = _best(lambda: _fd_jacobian(pb), 1, warm=False)
    bar.update()
    bar.close()
    res["ift_over_fd"] = res["fd_jacobian_s"] / res["linearise_s"]
    res["fd_rel_err"] = float(np.linalg.norm(M - M_fd) / np.linalg.norm(M_fd))
    res["problem"] = {
        "T_s": pb.command.T,
        "t_c_s": T_C,
        "model_steps_to_t_c": pb.k_c,
        "qp_rows_first_round": int(qp.m),
        "limit_rows_total": upd.n_limit_rows_total,
        "update_status": upd.qp_status,
        "update_rounds": upd.limit_rounds,
        "update_timings_s": dict(upd.timings),
        "repeats": repeats,
    }
    return res


@dataclass(frozen=True)
class _Problem:
    """The benchmark's update problem (module docstring): the robot and rope models, the
    played command, its record on the model, the target and the critical step."""

    robot: RobotModel
    params: RopeModelParams
    weights: InverseModelWeights
    command: BezierCommand
    target: DemoTarget
    record: TrialRecord
    k_c: int

    @staticmethod
    def make() -> _Problem:
        """The fixed problem: the target is the model's motion under the command's knots
        moved by 0.03 rad (seed 0)."""
        robot, params = RobotModel.from_mjcf(), RopeModelParams()
        command = bench_command()
        T = command.T
        rng = np.random.default_rng(0)
        star = command.knots.copy()
        star[:7, 1:] += 0.03 * rng.standard_normal((7, 7))
        target = DemoTarget.from_demonstration(
            model_demonstration(BezierCommand(star, T), T_C, robot, params)
        )
        record = model_record(command, robot, params)
        k_c = critical_step(T_C, params.dt, T)
        return _Problem(robot, params, InverseModelWeights(), command, target, record, k_c)

    def rollout(self):
        """The rope model driven by the record's joints to t_c."""
        r, c = self.record, self.command
        return rollout_from_joints(
            r.t_joint, r.q_meas, c.base_offset, self.robot, self.params, c.T, n_steps=self.k_c
        )

    def update(self, robot: RobotModel):
        """One ILC update with ``robot``."""
        settings = UpdateSettings(weights=self.weights)
        return ilc_update(self.record, self.command, self.target, robot, self.params, settings)


def _time_rollouts(pb: _Problem, repeats: int, res: dict):
    """The rollout with the compiled and the NumPy Newton step; the compiled one's result."""
    res["rollout_s"], ro = _best(pb.rollout, repeats)
    _StepSolver.compiled = False
    try:
        res["rollout_numpy_s"], ro_np = _best(pb.rollout, repeats)
    finally:
        _StepSolver.compiled = True
    res["compiled_over_numpy"] = res["rollout_numpy_s"] / res["rollout_s"]
    res["compiled_max_dx"] = float(np.abs(ro.traj.x - ro_np.traj.x).max())
    return ro


def _time_linearisations(pb: _Problem, ro, repeats: int, res: dict) -> np.ndarray:
    """M(t_c) compiled and by the NumPy loop; the compiled one."""
    T, k_c = pb.command.T, pb.k_c
    res["linearise_s"], M = _best(lambda: linearise(ro, T, [k_c])[0], repeats)
    rope_sensitivity.COMPILED = False
    try:
        res["linearise_numpy_s"], _ = _best(lambda: linearise(ro, T, [k_c])[0], repeats)
    finally:
        rope_sensitivity.COMPILED = True
    return M


def _time_qp(pb: _Problem, M: np.ndarray, repeats: int, res: dict, bar):
    """The QP's build (follow-through terms, limit rows, assembly) and its OSQP and Clarabel
    solves; the QP."""
    c, target, robot = pb.command, pb.target, pb.robot
    err = np.zeros(66)  # values do not change the timing; the update below uses the real one

    def build():
        t_ft = np.concatenate([[T_C], target.t[target.t > T_C + 1e-9]])
        follow = follow_through_terms(c.knots, c.T, t_ft, T_C, *target.hand_at(t_ft), robot)
        rows = limit_rows(c.knots, c.T, c.sample_times(), robot)
        sub = subset_rows(rows, initial_active_rows(rows, 0.5))
        return build_inverse_qp(
            M_crit=M, err_crit=err, weights=pb.weights, follow=follow, limits=sub
        )

    res["qp_build_s"], qp = _best(build, repeats)
    bar.update()
    res["qp_osqp_s"], _ = _best(lambda: solve_qp(qp, "osqp"), repeats)
    bar.update()
    res["qp_clarabel_s"], _ = _best(lambda: solve_qp(qp, "clarabel"), repeats)
    bar.update()
    return qp


def _time_updates(pb: _Problem, repeats: int, res: dict, bar):
    """The whole update with the compiled and the interpreted robot model; the compiled
    one's result."""
    res["update_s"], upd = _best(lambda: pb.update(pb.robot), repeats)
    bar.update()
    interpreted = RobotModel.from_mjcf(native=False)
    res["update_interpreted_s"], upd_i = _best(lambda: pb.update(interpreted), repeats)
    res["native_over_interpreted"] = res["update_interpreted_s"] / res["update_s"]
    res["native_max_dknots"] = float(np.abs(upd.new_knots - upd_i.new_knots).max())
    bar.update()
    return upd


def _fd_jacobian(pb: _Problem) -> np.ndarray:
    """M(t_c) by central differences of the model over the 80 knot values, (66, 80)."""
    c, k_c = pb.command, pb.k_c
    out = np.empty((66, 80))
    for col in range(80):
        e = np.zeros(80)
        e[col] = FD_EPS
        e = e.reshape(10, 8)
        xp = simulate_command(c.knots + e, c.T, pb.robot, pb.params, n_steps=k_c).x[k_c]
        xm = simulate_command(c.knots - e, c.T, pb.robot, pb.params, n_steps=k_c).x[k_c]
        out[:, col] = (xp - xm) / (2.0 * FD_EPS)
    return out


def format_learner(res: dict) -> str:
    """A small text table of :func:`bench_learner`'s result."""
    labels = {
        "rollout_s": "rollout to t_c",
        "rollout_numpy_s": "rollout, NumPy Newton",
        "linearise_s": "linearise (IFT)",
        "linearise_numpy_s": "linearise, NumPy loop",
        "qp_build_s": "QP build",
        "qp_osqp_s": "QP solve, OSQP",
        "qp_clarabel_s": "QP solve, Clarabel",
        "update_s": "full update",
        "update_interpreted_s": "update, CasADi interpreter",
        "fd_jacobian_s": "M by finite differences",
    }
    lines = [f"{'step':<26} {'ms':>10}"]
    for key, label in labels.items():
        lines.append(f"{label:<26} {1e3 * res[key]:>10.1f}")
    lines.append(f"{'compiled over NumPy':<26} {res['compiled_over_numpy']:>9.1f}x")
    lines.append(f"{'compiled vs NumPy max dx':<26} {res['compiled_max_dx']:>10.1e}")
    lines.append(f"{'native over interpreter':<26} {res['native_over_interpreted']:>9.1f}x")
    lines.append(f"{'native vs interp. max dk':<26} {res['native_max_dknots']:>10.1e}")
    lines.append(f"{'IFT speed-up over FD':<26} {res['ift_over_fd']:>9.0f}x")
    lines.append(f"{'IFT vs FD rel. error':<26} {res['fd_rel_err']:>10.1e}")
    prob = res.get("problem", {})
    if prob:
        lines.append(
            f"(T = {prob['T_s']:g} s, t_c = {prob['t_c_s']:g} s, {prob['model_steps_to_t_c']} "
            f"model steps, {prob['qp_rows_first_round']} QP rows of "
            f"{prob['limit_rows_total']} limit rows, status {prob['update_status']})"
        )
    return "\n".join(lines)


__all__ = ["KEYS", "bench_command", "bench_learner", "format_learner"]
