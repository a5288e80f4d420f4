"""How well does the learner's rope model predict the lab (``flyknot model-check``)?

The inverse-model update trusts the linearised model M = dx(t_c)/dkappa (66 x 80). This
module measures the lab's own response to small knot changes and compares:

1. Play the command kappa in the lab without trial-to-trial variation; the evaluation instant
   t_e is the demonstration's t_c, or earlier if the markers are lost before it (the last
   instant with every marker tracked, less the fit half-window).
2. For n random arm directions d_j (knots 2..5 and the end knots of joints 1..6, with the
   start and end kept at rest), play kappa +- d_j and take the central difference of the
   measured rope state r_j = (x(kappa + d_j) - x(kappa - d_j)) / 2 (66,) [m, m/s].
3. For every candidate rope model, linearise about the base trial's measured joints and
   predict p_j = M d_j; :func:`agreement` compares p_j with r_j on the marker positions.
4. Identification (``--grid``): score every model of :func:`grid_models` and keep the one
   whose predictions point most nearly along the measured responses (:func:`best_model`).

Only a simulated lab can replay a trial without variation, so this is a tool of the
simulated lab (it lives outside ``learner/``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flyknot.errors import ConfigError, RecordError, check_positive
from flyknot.progress import bar_disable

__all__ = [
    "GRID_DAMPING",
    "GRID_STIFFNESS",
    "ModelAgreement",
    "agreement",
    "best_model",
    "check_models",
    "evaluation_time",
    "grid_models",
    "load_knots",
    "random_directions",
]

N_POS = 33  # marker position entries of the 66-dim state
FREE_KNOTS = (0, 2, 3, 4, 5, 7)  # knot 1 = knot 0 and knot 6 = knot 7 (rest at both ends)


@dataclass(frozen=True)
class ModelAgreement:
    """Agreement of one rope model with the measured responses.

    Attributes:
        stiffness: Model bending stiffness.
        damping: Model damping.
        end_mass: Model end mass.
        mean_cos: Mean cosine between predicted and measured position responses [-].
        min_cos: Smallest of those cosines [-].
        ratio: Mean norm ratio |predicted| / |measured| [-].
        rel_miss: |P - R| / |R| over all directions (Frobenius) [-]; 0 is perfect.
    """

    stiffness: float
    damping: float
    end_mass: float
    mean_cos: float
    min_cos: float
    ratio: float
    rel_miss: float


def agreement(predicted: np.ndarray, measured: np.ndarray) -> dict[str, float]:
    """Compare predicted and measured responses on the marker positions.

    Args:
        predicted: Model responses M d_j, shape (n, 66) [m, m/s].
        measured: Lab responses r_j, shape (n, 66) [m, m/s].

    Returns:
        ``mean_cos``, ``min_cos`` (cosine per direction), ``ratio`` (mean |p_j| / |r_j|) and
        ``rel_miss`` = |P - R|_F / |R|_F, all on the first 33 entries (positions).

    Raises:
        ConfigError: Shapes differ, are not (n, 66), or a measured response is zero.
    """
    P = np.asarray(predicted, dtype=float)
    R = np.asarray(measured, dtype=float)
    if P.ndim != 2 or P.shape[1] != 2 * N_POS or P.shape != R.shape:
        raise ConfigError(
            "responses", f"need two (n, 66) arrays of one shape, got {P.shape} and {R.shape}"
        )
    P, R = P[:, :N_POS], R[:, :N_POS]
    nr = np.linalg.norm(R, axis=1)
    npred = np.linalg.norm(P, axis=1)
    if np.any(nr == 0):
        raise ConfigError("measured", "a measured response is zero; use larger directions")
    cos = np.einsum("ij,ij->i", P, R) / np.maximum(npred * nr, 1e-300)
    return {
        "mean_cos": float(cos.mean()),
        "min_cos": float(cos.min()),
        "ratio": float(np.mean(npred / nr)),
        "rel_miss": float(np.linalg.norm(P - R) / np.linalg.norm(R)),
    }


def random_directions(n: int, seed: int, scale: float) -> np.ndarray:
    """``n`` random arm-knot directions, shape (n, 10, 8) [rad].

    Entries N(0, scale^2) on the free knots of joints 1-6 (:data:`FREE_KNOTS`; knot 1 copies
    knot 0 and knot 6 copies knot 7 so the command still starts and ends at rest); joint 7
    (it only twists the rope) and the base rows stay 0.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ConfigError("directions", f"must be an integer >= 1, got {n!r}")
    check_positive("step", scale)
    rng = np.random.default_rng(seed)
    d = np.zeros((n, 10, 8))
    d[:, :6, list(FREE_KNOTS)] = rng.normal(scale=scale, size=(n, 6, len(FREE_KNOTS)))
    d[:, :6, 1] = d[:, :6, 0]
    d[:, :6, 6] = d[:, :6, 7]
    return d


def evaluation_time(t_marker: np.ndarray, markers: np.ndarray, t_c: float, dt: float) -> float:
    """t_c, or the last model step before the markers are lost less a 30 ms margin.

    Args:
        t_marker: Marker times, shape (m,) [s].
        markers: Markers, shape (m, 11, 3) [m] (NaN where lost).
        t_c: The demonstration's critical time [s].
        dt: Model step [s].

    Returns:
        The evaluation instant [s], a multiple of ``dt``.

    Raises:
        RecordError: The markers are lost within the first 60 ms.
    """
    ok = np.all(np.isfinite(markers), axis=(1, 2))
    lost = np.flatnonzero(~ok & (t_marker > 0))
    t_end = t_c if lost.size == 0 else min(t_c, float(t_marker[lost[0]]) - 0.03)
    if t_end < 0.06:
        raise RecordError(f"markers lost at {t_end + 0.03:.3f} s, too early to compare")
    return math.floor(t_end / dt + 1e-9) * dt


def check_models(
    demo: str,
    rope: int | str,
    models: Sequence[tuple[float, ...]],
    *,
    knots: np.ndarray | None = None,
    window: tuple[float, float] = (0.035, 0.05),
    n_directions: int = 8,
    step: float = 0.01,
    seed: int = 1,
    progress: bool = False,
) -> dict:
    """Measure the lab's responses and score each rope model (module docstring).

    Args:
        demo: Demonstration name or path (its target gives t_c and T).
        rope: Rope id of the lab, or a rope's name.
        models: (stiffness, damping) or (stiffness, damping, end mass) of each model to score
            (other model parameters: :class:`learner.rope_model.RopeModelParams`' defaults).
        knots: Command to linearise about (default: the demonstration's initial guess).
        window: Demonstration window (follow-through [s], path fraction at t_0).
        n_directions: Random directions.
        step: Std of each direction entry [rad].
        seed: Seed of the directions.
        progress: Show a progress bar.

    Returns:
        ``{"t_eval", "t_c", "response_norms", "models": [ModelAgreement as dict, ...]}``.
    """
    from dataclasses import asdict
    from tempfile import TemporaryDirectory

    from tqdm import tqdm

    from flyknot_app.runner import initial_knots, prepare_target
    from flyknot_app.scenario import check_demo
    from flyknot_sim.lab import LabParams, SimLab, VariationParams
    from learner.bezier import BezierCommand
    from learner.critical_state import critical_state_from_record
    from learner.kinematics import RobotModel
    from learner.rope_model import RopeModelParams
    from learner.system_model import critical_step, linearise, rollout_from_joints

    if not models:
        raise ConfigError("models", "give at least one (stiffness, damping) pair")
    check_demo(demo)
    names = ("stiffness", "damping", "end_mass")
    rope_models = [
        RopeModelParams(**{n: float(v) for n, v in zip(names, m, strict=False)}) for m in models
    ]
    dt = rope_models[0].dt
    _, target = prepare_target(demo, dt, window)
    robot = RobotModel.from_mjcf()
    # Only markers up to t_f are compared and no knot is judged: a fixed 1.5 s wait.
    lab = SimLab(LabParams(rope=rope, variation=VariationParams.none(), settle_s=1.5))
    if knots is None:
        with TemporaryDirectory() as tmp:
            knots, _ = initial_knots(demo, Path(tmp), robot, dt, float(lab.base_pose[2]), window)
    knots = np.asarray(knots, dtype=float)
    T = target.T
    dirs = random_directions(n_directions, seed, step)
    bar = tqdm(
        total=1 + 2 * n_directions, desc="model-check", unit="trial", disable=bar_disable(progress)
    )

    def play(k: np.ndarray):
        rec = lab.run(BezierCommand(k, T).joint_command())
        bar.update(1)
        if rec.fault is not None:
            raise RecordError(f"the command faulted: {rec.fault}; use smaller --step")
        return rec

    base = play(knots)
    t_eval = evaluation_time(base.t_marker, base.markers, target.t_c, dt)
    meas = []
    for d in dirs:
        xp = critical_state_from_record(play(knots + d), t_eval, knots[7:, 0])
        xm = critical_state_from_record(play(knots - d), t_eval, knots[7:, 0])
        meas.append(0.5 * (xp - xm))
    bar.close()
    R = np.array(meas)
    k_e = critical_step(t_eval, dt, T)
    rows = []
    for rp in rope_models:
        ro = rollout_from_joints(base.t_joint, base.q_meas, knots[7:, 0], robot, rp, T, n_steps=k_e)
        M = linearise(ro, T, [k_e])[0]
        P = dirs.reshape(n_directions, -1) @ M.T
        rows.append(
            asdict(
                ModelAgreement(
                    stiffness=rp.stiffness,
                    damping=rp.damping,
                    end_mass=rp.end_mass,
                    **agreement(P, R),
                )
            )
        )
    return {
        "demo": demo,
        "rope": rope,
        "t_c": float(target.t_c),
        "t_eval": float(t_eval),
        "response_norms": np.linalg.norm(R[:, :N_POS], axis=1).round(4).tolist(),
        "models": rows,
    }


GRID_STIFFNESS = (1.0, 2.0, 3.0, 5.0, 10.0, 30.0, 100.0, 1e3, 1e4, 1e5)
"""Bending stiffnesses [N m / rad] of the identification grid (``flyknot model-check --grid``):
from the paper's 1e5 down to a rope that droops under its own weight."""
GRID_DAMPING = (0.0, 0.01, 0.05, 0.5, 5.0, 50.0)
"""Bending dampings [N m s / rad] of the identification grid, up to the paper's 50."""


KNOTS_SUFFIXES = (".npy", ".npz")
"""Files ``--knots`` reads: knots (10, 8) alone (a run's ``final_knots.npy``) or an ``.npz``
with an array ``knots`` (``assets/demos/seeds/robot_command.npz``)."""


def load_knots(path: str | Path) -> np.ndarray:
    """The command knots (10, 8) of ``flyknot model-check --knots`` (:data:`KNOTS_SUFFIXES`).

    Raises:
        ConfigError: A missing file, another extension, or content that is no finite (10, 8)
            array of numbers; the message names the file.
    """
    from flyknot.errors import CommandError
    from flyknot_app.trial_cli import read_npy, read_npz
    from learner.bezier import check_knots

    path = Path(path)
    if not path.is_file():
        raise ConfigError("--knots", f"no file {str(path)!r}")
    if path.suffix not in KNOTS_SUFFIXES:
        raise ConfigError("--knots", f"{str(path)!r}: unknown extension", KNOTS_SUFFIXES)
    try:
        knots = read_npy(path) if path.suffix == ".npy" else read_npz(path, ("knots",))["knots"]
        return check_knots(knots, field=f"{str(path)!r} knots")
    except (CommandError, ConfigError) as e:
        raise ConfigError("--knots", str(e)) from None


def grid_models() -> list[tuple[float, float]]:
    """Every (stiffness, damping) pair of :data:`GRID_STIFFNESS` x :data:`GRID_DAMPING`."""
    return [(k, c) for k in GRID_STIFFNESS for c in GRID_DAMPING]


def best_model(res: dict) -> dict:
    """The scored model of :func:`check_models`' result whose predicted responses point most
    nearly along the measured ones (the highest mean cosine; the first of equals)."""
    return max(res["models"], key=lambda r: r["mean_cos"])


def format_table(res: dict) -> str:
    """The result of :func:`check_models` as a text table."""
    lines = [
        f"demo {res['demo']}, rope {res['rope']}: t_c {res['t_c']:.3f} s, "
        f"compared at {res['t_eval']:.3f} s; measured |response| per direction [m]: "
        + ", ".join(f"{v:.3f}" for v in res["response_norms"]),
        f"{'stiffness':>10} {'damping':>8} {'end mass':>8} {'mean cos':>9} {'min cos':>8} "
        f"{'ratio':>6} {'rel miss':>8}",
    ]
    best = best_model(res)
    for r in res["models"]:
        lines.append(
            f"{r['stiffness']:>10g} {r['damping']:>8g} {r['end_mass']:>8g} {r['mean_cos']:>9.2f} "
            f"{r['min_cos']:>8.2f} {r['ratio']:>6.2f} {r['rel_miss']:>8.2f}"
            + ("  <- best" if r is best else "")
        )
    lines.append(
        f"best: stiffness {best['stiffness']:g}, damping {best['damping']:g}, end mass "
        f"{best['end_mass']:g} (mean cos {best['mean_cos']:.2f}); use it with --set "
        "rope_model.stiffness=K --set rope_model.damping=B --set rope_model.end_mass=M"
    )
    return "\n".join(lines)
