"""The error family: exact messages, and errors that survive a trip through a worker process."""

from __future__ import annotations

import pickle
from concurrent.futures import ProcessPoolExecutor

import pytest

from flyknot.errors import ConfigError, FlyknotError, SolverError, check_choice


def _raise_config() -> None:
    check_choice("objective", "fast", ("critical", "equal"))


@pytest.mark.parametrize(
    "err",
    [
        ConfigError("gain", "must lie in (0, 1], got 2"),
        ConfigError("objective", "unknown value 'x'", ["critical", "equal"]),
        SolverError("clarabel", "MaxIterations", "after 200 iterations"),
        SolverError("osqp", "primal infeasible"),
    ],
)
def test_errors_pickle_with_their_fields(err):
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is type(err) and str(back) == str(err)
    assert back.__dict__ == err.__dict__


def test_a_worker_error_reaches_the_parent_intact():
    with ProcessPoolExecutor(max_workers=1) as pool, pytest.raises(ConfigError) as e:
        pool.submit(_raise_config).result()
    assert str(e.value) == "objective: unknown value 'fast' (valid choices: critical, equal)"
    assert isinstance(e.value, FlyknotError) and e.value.choices == ["critical", "equal"]
