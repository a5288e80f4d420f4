"""The learner's measuring sticks: the oracle Jacobian and the reachable floor."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from flyknot.errors import ConfigError
from flyknot_app.cells import check_oracle, oracle_provider
from flyknot_app.diagnose.floor import FloorParams, cost_parts
from flyknot_app.diagnose.oracle import LabJacobian, central_difference, knot_groups
from learner.inverse_qp import base_equality_rows, rest_equality_rows
from learner.jacobians import JACOBIANS, jacobian_kind, provided_jacobian
from learner.update import UpdateSettings


def feasible_update(rng: np.random.Generator) -> np.ndarray:
    """A random knot update (10, 8) that the QP's equality rows allow (rest, constant base)."""
    dk = rng.normal(size=(10, 8))
    dk[:7, 1] = dk[:7, 0]
    dk[:7, 6] = dk[:7, 7]
    dk[7:] = dk[7:, :1]
    return dk


def test_knot_groups_are_the_qp_s_free_directions():
    groups = knot_groups()
    assert len(groups) == 7 * 6 + 3
    E = np.vstack([base_equality_rows("constant"), rest_equality_rows()])
    for row, knots in groups:
        d = np.zeros((10, 8))
        d[row, list(knots)] = 1.0
        assert np.allclose(E @ d.ravel(), 0.0), (row, knots)
    # together with the equality rows' null space they span it: 80 - 24 free dimensions
    null = 80 - np.linalg.matrix_rank(E)
    assert null == len(groups)


def test_central_difference_sides():
    x0, xp, xm = np.zeros(3), np.array([2.0, 0, 0]), np.array([-1.0, 0, 0])
    assert np.allclose(central_difference(x0, xp, xm, 0.5), [3.0, 0, 0])
    assert np.allclose(central_difference(x0, xp, None, 0.5), [4.0, 0, 0])
    assert np.allclose(central_difference(x0, None, xm, 0.5), [2.0, 0, 0])
    assert np.allclose(central_difference(x0, None, None, 0.5), 0.0)


def test_oracle_of_a_linear_lab_is_exact_on_every_feasible_update(monkeypatch):
    """With x(kappa) = A vec(kappa), M dkappa = A dkappa for every update the QP allows."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(66, 80))
    oracle = LabJacobian.__new__(LabJacobian)
    oracle.params = FloorParams().oracle
    oracle.plays, oracle.t_c = 0, 0.8
    monkeypatch.setattr(oracle, "state", lambda knots, T, times: A @ knots.ravel(), raising=False)
    M = LabJacobian.__call__(oracle, rng.normal(size=(10, 8)), 1.0)[0.8]
    for _ in range(5):
        dk = feasible_update(rng)
        assert np.allclose(M @ dk.ravel(), A @ dk.ravel())
    # the columns of tied knots carry nothing of their own
    assert np.all(M[:, 1] == 0.0) and np.all(M[:, 7 * 8 + 1 : 7 * 8 + 8] == 0.0)


def test_oracle_takes_every_fitted_time_from_the_same_plays(monkeypatch):
    """x(kappa, t) = A_t vec(kappa) at two times: each M(t) is its own A_t, and the plays are
    one nominal and two per knot group, as for t_c alone."""
    rng = np.random.default_rng(4)
    A = {0.5: rng.normal(size=(66, 80)), 0.8: rng.normal(size=(66, 80))}
    oracle = LabJacobian.__new__(LabJacobian)
    oracle.params, oracle.plays, oracle.t_c = FloorParams().oracle, 0, 0.8

    def state(knots, T, times):
        oracle.plays += 1
        return np.concatenate([A[t] @ knots.ravel() for t in times])

    monkeypatch.setattr(oracle, "state", state, raising=False)
    M = LabJacobian.__call__(oracle, rng.normal(size=(10, 8)), 1.0, (0.8, 0.5))
    assert list(M) == [0.8, 0.5] and oracle.plays == 1 + 2 * len(knot_groups())
    for t in M:
        dk = feasible_update(rng)
        assert np.allclose(M[t] @ dk.ravel(), A[t] @ dk.ravel())


def test_jacobian_registry_and_settings():
    assert set(JACOBIANS) == {"model", "oracle", "secant"}
    assert not jacobian_kind("model").needs_provider
    assert jacobian_kind("oracle").needs_provider
    with pytest.raises(ConfigError) as e:
        UpdateSettings(jacobian="broyden")
    assert (
        str(e.value)
        == "jacobian: unknown Jacobian source 'broyden' (valid choices: model, oracle, secant)"
    )
    with pytest.raises(ConfigError) as e:
        UpdateSettings(jacobian="oracle", objective="equal")
    assert str(e.value) == "jacobian: 'oracle' is for the critical objective only"
    assert provided_jacobian("model", None, np.zeros((10, 8)), 1.0, (0.5,)) is None
    with pytest.raises(ConfigError, match="needs a cell that can measure it"):
        provided_jacobian("oracle", None, np.zeros((10, 8)), 1.0, (0.5,))
    got = provided_jacobian(
        "oracle",
        lambda k, T, times: {t: np.full((66, 80), T + t) for t in times},
        np.zeros((10, 8)),
        2.0,
        (0.5, 0.25),
    )
    assert list(got) == [0.5, 0.25] and np.all(got[0.5] == 2.5) and np.all(got[0.25] == 2.25)


def test_oracle_refused_on_a_real_cell():
    with pytest.raises(ConfigError) as e:
        check_oracle("xarm")
    assert str(e.value) == (
        "jacobian: 'oracle' replays commands without variation, which only a simulated lab "
        "can; this run's cell is 'xarm' (valid choices: sim)"
    )
    with pytest.raises(ConfigError, match=r"cell is 'xarm' \(dry run\)"):
        check_oracle("xarm", dry_run=True)
    check_oracle("sim")


def test_oracle_run_on_the_real_lab_is_one_line_and_writes_nothing(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "flyknot_app", "run", "quick", "--cell", "assets/lab_example.toml",
         "--set", "jacobian=oracle", "--out", str(out)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "'oracle' replays commands without variation" in lines[0]
    assert not out.exists()


def test_floor_params_and_cost_parts():
    with pytest.raises(ConfigError) as e:
        FloorParams(budget=0)
    assert str(e.value) == "budget: must be an integer >= 1, got 0"
    with pytest.raises(ConfigError) as e:
        FloorParams(grow=1.0)
    assert str(e.value) == "grow: must be > 1, got 1.0"
    err = np.concatenate([np.full(33, 0.1), np.full(33, 2.0)])
    pos, vel = cost_parts(err, 25.0, 0.00375)
    assert pos == pytest.approx(25.0 * 33 * 0.01)
    assert vel == pytest.approx(0.00375 * 33 * 4.0)


@pytest.mark.slow
def test_oracle_predicts_the_lab_s_own_response():
    """Finite-difference check of the oracle: M(t) d against the lab's central difference
    along a random feasible direction d at t_c and at the launch t_l (rope 1, the robot
    demonstration's initial command)."""
    from flyknot_app.cells import SimCellSpec
    from flyknot_app.runner import prepare_target
    from learner.objectives import objective_kind
    from learner.rope_model import RopeModelParams

    _, target = prepare_target("robot", RopeModelParams().dt, (0.25, 0.0))
    knots = np.load("assets/demos/seeds/robot_command.npz")["knots"]
    oracle = oracle_provider("sim", SimCellSpec(rope=1), target.t_c)
    times = objective_kind("launch").fit_times(target)
    M = oracle(knots, target.T, times)
    assert oracle.plays == 1 + 2 * len(knot_groups())
    d = 0.004 * feasible_update(np.random.default_rng(0))
    xp, xm = oracle.state(knots + d, target.T, times), oracle.state(knots - d, target.T, times)
    measured = ((xp - xm) / 2).reshape(len(times), 66)
    for i, t in enumerate(times):
        predicted = M[t] @ d.ravel()
        rel = np.linalg.norm(predicted[:33] - measured[i, :33]) / np.linalg.norm(measured[i, :33])
        assert rel < 0.15, (t, rel)


@pytest.mark.slow
def test_an_oracle_run_updates_with_the_lab_s_jacobian(egl, tmp_path):
    """`flyknot run quick --set jacobian=oracle --set objective=critical`: the first update is
    the QP solved with the oracle's Jacobian about the initial command, bit for bit (the
    oracle plays without variation, so measuring it again gives the same matrix). Both sides
    run in fresh processes, as a run does."""
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "flyknot_app", "run", "quick", "--set", "jacobian=oracle",
         "--set", "objective=critical", "--set", "max_trials=1", "--set", "step=gain",
         "--set", "gain=0.5", "--set", "weights.w_control=5", "--set", "follow_through=false",
         "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    learning = out / "runs" / "rope1" / "learning"
    check = subprocess.run(
        [sys.executable, "-c", _ORACLE_UPDATE, str(learning)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert check.returncode == 0, check.stderr
    assert check.stdout.strip().splitlines()[-1] == "0.0"  # |knots1 - (knots0 - 0.5 dk)|


_ORACLE_UPDATE = """
import json
import sys
from pathlib import Path
import numpy as np
from flyknot.record import TrialRecord
from flyknot_app.cells import SimCellSpec, oracle_provider
from flyknot_app.runner import prepare_target
from learner.bezier import BezierCommand
from learner.inverse_qp import InverseModelWeights
from learner.kinematics import RobotModel
from learner.rope_model import RopeModelParams
from learner.update import UpdateSettings, ilc_update

learning = Path(sys.argv[1])
knots0, knots1 = np.load(learning / "knots_0000.npy"), np.load(learning / "knots_0001.npy")
record = TrialRecord.load(learning / "trial_0000_a0")
rope_model = RopeModelParams(stiffness=2.0, damping=0.0)
_, target = prepare_target("fast-paced", rope_model.dt, (0.25, 0.0))
M = oracle_provider("sim", SimCellSpec(rope=1, settle_s=0.5), target.t_c)(knots0, target.T)
run = json.loads((learning.parent / "result.json").read_text())
weights = InverseModelWeights(**run["weights"])  # the run's own, as the scenario set them
settings = UpdateSettings(weights=weights, jacobian="oracle", follow_through=False)
command = BezierCommand(knots0, target.T)
res = ilc_update(record, command, target, RobotModel.from_mjcf(), rope_model, settings, jacobian=M)
print(float(np.abs(knots1 - (knots0 - 0.5 * np.asarray(res.dkappa))).max()))
"""


def test_the_floor_scores_with_the_objective_s_weights(tmp_path, capsys):
    """`flyknot diagnose floor --demo` costs the start with the scenarios' weights, or with
    ``--w-crit-vel``: the same play (the lab without variation), its velocity part scaled by
    the weights' ratio; a budget under one Jacobian (91 plays) plays the start alone."""
    import json

    from flyknot_app.cli import main

    a, b = tmp_path / "a.json", tmp_path / "b.json"
    base = ["diagnose", "floor", "--demo", "fast-paced", "--budget", "1", "--json"]
    assert main([*base, "--out", str(a)]) == 0
    assert main([*base, "--out", str(b), "--w-crit-vel", "0.00375"]) == 0
    A, B = json.loads(a.read_text()), json.loads(b.read_text())
    assert A["plays"] == B["plays"] == 1
    assert (A["w_crit_pos"], A["w_crit_vel"], B["w_crit_vel"]) == (25.0, 0.1, 0.00375)
    assert A["position_part"] == B["position_part"]
    assert A["velocity_part"] == pytest.approx(B["velocity_part"] * 0.1 / 0.00375)
    assert A["cost"] == pytest.approx(A["position_part"] + A["velocity_part"])
    capsys.readouterr()
    bad = tmp_path / "bad" / "f.json"
    assert main([*base, "--out", str(bad), "--w-crit-vel", "-1"]) == 2
    assert capsys.readouterr().err == (
        "flyknot: error: w_crit_vel: must be a finite number >= 0, got -1.0\n"
    )
    assert not bad.parent.exists()  # refused before any work
    assert main(["diagnose", "floor", str(tmp_path), "--w-crit-vel", "0.1"]) == 2
    assert capsys.readouterr().err == (
        "flyknot: error: --w-crit-vel: a run's floor uses the run's own weights; give --demo\n"
    )


def test_a_run_s_floor_takes_the_run_s_weights(tmp_path):
    import json

    from flyknot_app.diagnose.cli import _objective_weights, _run_inputs

    (tmp_path / "learning").mkdir()
    np.save(tmp_path / "learning" / "knots_0000.npy", np.zeros((10, 8)))
    weights = {"w_crit_pos": 20.0, "w_crit_vel": 0.3}
    opts = {"demo": "fast-paced", "follow_through_s": 0.25, "path_frac": 0.0, "rope": 1,
            "seed": 0, "weights": weights}  # fmt: skip
    (tmp_path / "result.json").write_text(json.dumps(opts))
    w = _objective_weights(_run_inputs(tmp_path))
    assert (w.w_crit_pos, w.w_crit_vel, w.w_control) == (20.0, 0.3, 0.5)
    del opts["weights"]
    (tmp_path / "result.json").write_text(json.dumps(opts))
    with pytest.raises(ConfigError) as e:
        _objective_weights(_run_inputs(tmp_path))
    assert str(e.value) == "RUN_DIR: the run's result.json names no QP weights ('weights')"
