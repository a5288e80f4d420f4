"""Tests of learner/native.py: the robot model's batches in compiled code equal CasADi's
interpreter bit for bit, the cache is reused, and a missing or failing compiler leaves the
interpreter in charge with the reason said.

These tests need a C compiler (``cc``, or ``$CC``); ``.ci/run`` installs one when it is missing.
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from flyknot.constants import XARM7_XML
from flyknot.errors import ConfigError
from learner.kinematics import RobotModel
from learner.native import NativeUnavailableError, cache_dir, compile_batch

CHAIN7 = Path(__file__).parent / "data" / "chain7.xml"
PATHS = [pytest.param(CHAIN7, id="chain7"), pytest.param(XARM7_XML, id="xarm7")]


@pytest.fixture(scope="module")
def xarm() -> RobotModel:
    return RobotModel.from_mjcf(XARM7_XML)


def _inputs(sizes: tuple[int, ...], m: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.uniform(-2.0, 2.0, (m, n)) for n in sizes]


@pytest.mark.parametrize("key", ["tip", "tip_jac", "tau", "tau_jac", "tau_jvp", "tip_omega"])
def test_every_flat_function_equals_the_interpreter_bit_for_bit(c_compiler, xarm, key, tmp_path):
    fun = xarm._flat[key]
    batch = compile_batch(fun, cache=tmp_path)
    x = _inputs(batch.n_in, 23, seed=len(key))
    ref = fun.map(23, "serial")(*(xi.T for xi in x))
    ref = ref if isinstance(ref, tuple) else (ref,)
    got = batch(*x)
    assert len(got) == len(ref)
    for y, r in zip(got, ref, strict=True):
        np.testing.assert_array_equal(y, np.asarray(r).T)


@pytest.mark.parametrize("path", PATHS)
def test_the_model_methods_are_the_same_native_or_interpreted(c_compiler, path):
    fast = RobotModel.from_mjcf(path)
    slow = RobotModel.from_mjcf(path, native=False)
    rng = np.random.default_rng(3)
    q, qd, qdd, dq, dqd, dqdd = (rng.uniform(-1.5, 1.5, (31, 7)) for _ in range(6))
    pairs = [
        (fast.tip_states(q, qd), slow.tip_states(q, qd)),
        (fast.tip_jacobians(q, qd), slow.tip_jacobians(q, qd)),
        ((fast.torques(q, qd, qdd),), (slow.torques(q, qd, qdd),)),
        (fast.torque_jacobians(q, qd, qdd), slow.torque_jacobians(q, qd, qdd)),
        (
            (fast.torque_jvp(q, qd, qdd, dq, dqd, dqdd),),
            (slow.torque_jvp(q, qd, qdd, dq, dqd, dqdd),),
        ),
        ((fast.tip_angular_jacobians(q),), (slow.tip_angular_jacobians(q),)),
    ]
    for a, b in pairs:
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
    assert all(v is not None for v in fast._native.values()) and len(fast._native) == 6
    assert slow._native == {}


def test_a_compiled_library_is_built_once_and_reused(c_compiler, xarm, tmp_path):
    first = compile_batch(xarm._flat["tau"], cache=tmp_path)
    stamp = first.path.stat().st_mtime_ns
    second = compile_batch(xarm._flat["tau"], cache=tmp_path)
    assert second.path == first.path and second.path.stat().st_mtime_ns == stamp
    assert [p.name for p in tmp_path.iterdir()] == [first.path.name]


def test_without_a_compiler_the_model_warns_and_interprets(monkeypatch, tmp_path):
    import learner.kinematics

    monkeypatch.setattr(learner.kinematics, "_NATIVE", {})  # nothing compiled in this process
    monkeypatch.setenv("CC", "no-such-cc")
    monkeypatch.setenv("FLYKNOT_CACHE", str(tmp_path))
    robot = RobotModel.from_mjcf(CHAIN7)
    with pytest.raises(NativeUnavailableError) as err:
        compile_batch(robot._flat["tau"])
    assert str(err.value) == "no C compiler 'no-such-cc' on the PATH (set CC to one)"
    q = np.full((4, 7), 0.3)
    with pytest.warns(UserWarning, match="robot model in CasADi's interpreter: no C compiler"):
        tau = robot.torques(q, q, q)
    np.testing.assert_array_equal(tau, RobotModel.from_mjcf(CHAIN7, native=False).torques(q, q, q))
    assert robot._native == {"tau": None}
    assert not any(tmp_path.rglob("*.so"))


def test_a_failing_compiler_is_reported(monkeypatch, tmp_path, xarm):
    monkeypatch.setenv("CC", "false")
    with pytest.raises(NativeUnavailableError, match=r"^/.*false failed: "):
        compile_batch(xarm._flat["tip"], cache=tmp_path)
    assert not any(tmp_path.rglob("*.so"))


def test_only_sx_functions_compile(tmp_path):
    x = ca.MX.sym("x", 2)
    with pytest.raises(NativeUnavailableError, match=r"^f is not an SX function$"):
        compile_batch(ca.Function("f", [x], [2 * x]), cache=tmp_path)


def test_a_batch_names_an_input_of_the_wrong_shape(c_compiler, xarm, tmp_path):
    batch = compile_batch(xarm._flat["tau"], cache=tmp_path)
    with pytest.raises(ConfigError, match=r"^tau_flat input 1: expected \(5, 7\), got \(5, 6\)$"):
        batch(np.zeros((5, 7)), np.zeros((5, 6)), np.zeros((5, 7)))


def test_the_cache_directory_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("FLYKNOT_CACHE", str(tmp_path / "a"))
    assert cache_dir() == tmp_path / "a" / "native"
    monkeypatch.delenv("FLYKNOT_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "b"))
    assert cache_dir() == tmp_path / "b" / "flyknot" / "native"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "c"))
    assert cache_dir() == tmp_path / "c" / ".cache" / "flyknot" / "native"


def test_a_model_that_has_compiled_its_batches_pickles(xarm):
    import pickle

    q = np.full((3, 7), 0.2)
    tau = xarm.torques(q, q, q)
    copy = pickle.loads(pickle.dumps(xarm))
    assert copy._native == {} and copy.native
    np.testing.assert_array_equal(copy.torques(q, q, q), tau)


def test_models_of_one_chain_share_their_compiled_batches(c_compiler):
    a, b = RobotModel.from_mjcf(CHAIN7), RobotModel.from_mjcf(CHAIN7)
    q = np.full((2, 7), 0.1)
    a.torques(q, q, q)
    assert b._native is a._native and b._native["tau"] is not None
    other = RobotModel.from_mjcf(CHAIN7, include_armature=False)  # another inverse dynamics
    assert other._native is not a._native
    np.testing.assert_array_equal(other.torques(q, q, q), other.torques(q, q, q))
    assert not np.array_equal(other.torques(q, q, q), a.torques(q, q, q))
