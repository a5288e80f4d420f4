"""Tests of flyknot_app/schedule.py: which run goes first, dependencies, and several scenarios
on one pool giving the runs they give alone."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from flyknot.errors import ConfigError
from flyknot_app.runner import execute_run, run_scenario, run_scenarios
from flyknot_app.scenario import parse_scenario
from flyknot_app.schedule import RunJob, _Ready, expected_trials, ranks, run_jobs


def _jobs(doc: dict, scenario: str = "s") -> list[RunJob]:
    scen = parse_scenario(doc, name=scenario)
    return [RunJob(scenario, spec, Path(scenario), False, False) for spec in scen.runs]


def test_expected_trials_counts_learning_confirmation_and_repeats():
    (a, b, c) = _jobs(
        {
            "run": [
                {"name": "a", "max_trials": 10, "repeats": 40},
                {"name": "b", "max_trials": 10, "average": 2, "confirm": [3, 4], "repeats": 2},
                {"name": "c", "max_trials": 0, "repeats": 7},
            ]
        }
    )
    assert expected_trials(a.spec) == 50.0
    assert expected_trials(b.spec) == 20.0 + 4.0 + 2.0
    assert expected_trials(c.spec) == 8.0  # the initial command's one play, then 7


def test_a_chain_is_ranked_by_the_work_it_heads():
    jobs = _jobs(
        {
            "defaults": {"max_trials": 10},
            "run": [
                {"name": "d", "max_trials": 25},
                {"name": "c", "start_from": "b"},
                {"name": "b", "start_from": "a"},
                {"name": "a"},
            ],
        }
    )
    by_name = {key[1]: r for key, r in ranks(jobs).items()}
    assert by_name == {"a": 30.0, "b": 20.0, "c": 10.0, "d": 25.0}


def test_runs_start_highest_rank_first_and_only_after_the_run_they_start_from():
    jobs = _jobs(
        {
            "defaults": {"max_trials": 10},
            "run": [
                {"name": "d", "max_trials": 25},
                {"name": "e", "max_trials": 25},
                {"name": "c", "start_from": "b"},
                {"name": "b", "start_from": "a"},
                {"name": "a"},
            ],
        }
    )
    ready = _Ready(jobs)
    first = [ready.pop().spec.name for _ in range(3)]
    assert first == ["a", "d", "e"]  # ranks 30, 25, 25 (d before e: the given order)
    assert ready.pop() is None and not ready.stuck  # b waits for a
    ready.finished(next(j for j in jobs if j.spec.name == "a"))
    assert ready.pop().spec.name == "b"
    assert ready.pop() is None
    ready.finished(next(j for j in jobs if j.spec.name == "b"))
    assert ready.pop().spec.name == "c"
    assert ready.pop() is None and not ready.stuck


def test_runs_that_wait_on_each_other_are_refused_before_any_plays():
    jobs = _jobs({"run": [{"name": "a", "start_from": "b"}, {"name": "b", "start_from": "a"}]})
    with pytest.raises(ConfigError, match=r"^start_from: runs depend on each other in a cycle$"):
        list(run_jobs(jobs, execute_run))


def test_a_run_cannot_start_from_another_scenarios_run():
    jobs = _jobs({"run": [{"name": "a"}]}, "s") + _jobs(
        {"run": [{"name": "a"}, {"name": "b", "start_from": "a"}]}, "t"
    )
    bad = RunJob("s", jobs[2].spec, Path("s"), False, False)
    with pytest.raises(ConfigError, match=r"^run 'b' start_from: no run 'a' to start from$"):
        _Ready([jobs[1], bad])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"executor": "dask"}, "--executor: unknown executor 'dask' (valid choices: process, ray)"),
        ({"workers": 0}, "--workers: must be an integer >= 1, got 0"),
    ],
)
def test_bad_executor_settings_are_named(kwargs, message):
    with pytest.raises(ConfigError) as err:
        list(run_jobs(_jobs({"run": [{"name": "a"}]}), execute_run, **kwargs))
    assert str(err.value) == message


def _tiny(name: str, runs: list[dict]) -> object:
    defaults = {"max_trials": 0, "settle_s": 0.2, "rope": 1}
    return parse_scenario({"defaults": defaults, "run": runs}, name=name)


def _untimed(summary: dict) -> dict:
    """A scenario summary without the runs' wall times."""
    runs = [{k: v for k, v in r.items() if k != "wall_s"} for r in summary["runs"]]
    return {**summary, "runs": runs}


def test_two_scenarios_on_one_pool_give_what_each_gives_alone(egl, tmp_path):
    guesses = tmp_path / "guesses"
    guesses.mkdir()
    x = _tiny("x", [{"name": "a", "seed": 0}, {"name": "b", "start_from": "a", "seed": 1}])
    y = _tiny("y", [{"name": "c", "seed": 2}])

    def where(root: str, name: str) -> Path:
        d = tmp_path / root / name
        d.mkdir(parents=True)
        (d / "initial_guess").symlink_to(guesses, target_is_directory=True)
        return d

    together = run_scenarios(
        [(x, where("one", "x")), (y, where("one", "y"))], workers=2, progress=False
    )
    alone = [run_scenario(s, where("two", s.name), progress=False) for s in (x, y)]
    for done, single in zip(together, alone, strict=True):
        assert _untimed(done.summary.to_json()) == _untimed(single.to_json())
        assert done.run_s > 0 and done.done_s > 0
    for name in ("x", "y"):
        summary = json.loads((tmp_path / "one" / name / "summary.json").read_text())
        assert _untimed(summary) == _untimed(
            json.loads((tmp_path / "two" / name / "summary.json").read_text())
        )
        assert (tmp_path / "one" / name / "report.md").is_file()
    with pytest.raises(ConfigError, match=r"^out_dir: two scenarios would write into the same"):
        run_scenarios([(x, tmp_path / "z"), (y, tmp_path / "z")])


class _Clock:
    """A pool of simulated workers: a task ends ``duration`` after it starts; ``wait_one``
    returns the earliest to end and moves the clock there."""

    def __init__(self, durations: dict[tuple[str, str], float]):
        self.durations, self.now, self.log = durations, 0.0, []
        self._tasks: list[tuple[float, float, str, str, object]] = []  # start, end, kind, ...

    def submit(self, args: tuple) -> int:
        from flyknot_app.schedule import _task

        play, finish, job, knots0, summary = args
        kind, name = ("run" if summary is None else "finish"), job.spec.name
        self.log.append((self.now, "start", kind, name))
        summary = _task(play, finish, job, knots0, summary)[0]
        end = self.now + self.durations[kind, name]
        self._tasks.append((self.now, end, kind, name, summary))
        return len(self._tasks) - 1

    def wait_one(self, handles: list) -> tuple[int, tuple]:
        h = min(handles, key=lambda k: self._tasks[k][1])
        start, end, kind, name, summary = self._tasks[h]
        self.now = end
        self.log.append((end, "end", kind, name))
        return h, (summary, end - start)


def test_post_run_work_is_its_own_task_and_fills_idle_workers():
    from flyknot_app.schedule import _drive

    jobs = _jobs(
        {
            "defaults": {"max_trials": 10},
            "run": [{"name": "a", "max_trials": 25}, {"name": "b"}, {"name": "c"}],
        }
    )
    clock = _Clock(
        {("run", "a"): 10.0, ("run", "b"): 2.0, ("run", "c"): 2.0}
        | {("finish", n): 1.0 for n in "abc"}
    )
    finished = []

    def play(spec, out_dir, knots0, *, resume, progress):
        return f"summary {spec.name}"

    def finish(spec, out_dir, summary, *, figure):
        finished.append((spec.name, summary))

    out = list(_drive(play, finish, _Ready(jobs), 2, clock.submit, clock.wait_one))
    # a (rank 25) and b start; c waits for a free worker, then the finishes of b and c run
    # beside a: the second worker is busy until 6 s, a and its finish end at 11 s
    assert [(j.spec.name, s, w) for j, s, w in out] == [
        ("b", "summary b", 3.0),
        ("c", "summary c", 3.0),
        ("a", "summary a", 11.0),
    ]
    starts = [(t, kind, name) for t, e, kind, name in clock.log if e == "start"]
    assert starts == [
        (0.0, "run", "a"),
        (0.0, "run", "b"),
        (2.0, "run", "c"),  # a run before the waiting finish of b
        (4.0, "finish", "b"),
        (5.0, "finish", "c"),
        (10.0, "finish", "a"),
    ]
    assert finished == [("b", "summary b"), ("c", "summary c"), ("a", "summary a")]


def test_without_a_finish_a_run_is_yielded_when_it_ends():
    from flyknot_app.schedule import _drive

    jobs = _jobs({"run": [{"name": n, "max_trials": 5} for n in "abc"]})
    clock = _Clock({("run", "a"): 3.0, ("run", "b"): 1.0, ("run", "c"): 1.0})

    def play(spec, out_dir, knots0, *, resume, progress):
        return spec.name

    drive = _drive(play, None, _Ready(jobs), 2, clock.submit, clock.wait_one)
    assert [(j.spec.name, s, w) for j, s, w in drive] == [
        ("b", "b", 1.0),
        ("c", "c", 1.0),
        ("a", "a", 3.0),
    ]
    assert [e[2] for e in clock.log if e[1] == "start"] == ["run"] * 3


def test_a_runs_post_run_work_is_done_once(monkeypatch, tmp_path):
    from flyknot_app import runner
    from flyknot_app.anatomy.report import store_diagnoses  # noqa: F401 (the patched module)

    calls = []
    monkeypatch.setattr(
        "flyknot_app.anatomy.report.store_diagnoses", lambda d: calls.append(("diag", d))
    )
    monkeypatch.setattr(
        "flyknot_app.judging.draw_run_knots", lambda d, root: calls.append(("knots", d))
    )
    spec = parse_scenario({"run": [{"name": "a"}]}, name="x").runs[0]
    run_dir = tmp_path / "runs" / "a"
    run_dir.mkdir(parents=True)
    runner.finish_run(spec, tmp_path, "summary")
    assert calls == [("diag", run_dir), ("knots", run_dir)]
    assert (run_dir / runner.FINISHED).is_file()
    runner.finish_run(spec, tmp_path, "summary")  # a resumed scenario: already done
    assert len(calls) == 2


def test_a_scenario_whose_runs_have_ended_gets_its_post_run_work_first():
    """Its report waits on that work; another scenario's runs wait instead."""
    from flyknot_app.schedule import _drive

    x = _jobs({"run": [{"name": "a", "max_trials": 10}]}, "x")
    y = _jobs({"run": [{"name": n, "max_trials": 5} for n in ("b", "c", "d")]}, "y")
    clock = _Clock(
        {("run", "a"): 1.0, ("run", "b"): 4.0, ("run", "c"): 4.0, ("run", "d"): 4.0}
        | {("finish", n): 1.0 for n in "abcd"}
    )

    def play(spec, out_dir, knots0, *, resume, progress):
        return spec.name

    def finish(spec, out_dir, summary, *, figure):
        return None

    out = list(_drive(play, finish, _Ready(x + y), 2, clock.submit, clock.wait_one))
    starts = [(t, kind, name) for t, e, kind, name in clock.log if e == "start"]
    assert starts[:4] == [
        (0.0, "run", "a"),  # rank 10 (a's 10 trials) before the 5-trial runs
        (0.0, "run", "b"),
        (1.0, "finish", "a"),  # x has no run left: its post-run work before y's run c
        (2.0, "run", "c"),
    ]
    assert out[0][0].spec.name == "a" and out[0][2] == 2.0
