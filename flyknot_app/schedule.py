"""Runs of one or more scenarios on a pool of workers, each as soon as it can start.

A run can start when the run it starts from (``start_from``, same scenario) has finished.
Among the runs that can start, the one heading the longest chain of remaining work goes first
(list scheduling by upward rank, the longest-processing-time rule with dependencies), so the
pool's last minutes are not one long run on one worker while the others idle. A run's work
is estimated by the trials it may play (:func:`expected_trials`); the estimate only orders the
runs, and a run's result does not depend on when or where it runs.

Three executors: this process (one worker), a local process pool, Ray tasks (a local Ray with
``workers`` CPUs, or the cluster at ``address``).
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError
from flyknot_app.reports.run_summary import RunSummary
from flyknot_app.scenario import RunSpec

__all__ = ["EXECUTORS", "RunJob", "expected_trials", "ranks", "run_jobs"]

EXECUTORS = ("process", "ray")


@dataclass(frozen=True)
class RunJob:
    """One run of a scenario, as the scheduler hands it to a worker.

    Attributes:
        scenario: The scenario's key (its output directory, unique among the jobs).
        spec: The run.
        out_dir: The scenario's output directory.
        resume: Continue the run from what is on disk.
        figure: Draw the run's critical-point figure for the report.
    """

    scenario: str
    spec: RunSpec
    out_dir: Path
    resume: bool
    figure: bool

    @property
    def key(self) -> tuple[str, str]:
        """(scenario, run name): unique among the jobs."""
        return self.scenario, self.spec.name


def expected_trials(spec: RunSpec) -> float:
    """Trials a run may play: ``max_trials * average`` learning plays (one play when
    ``max_trials`` is 0), the confirmation plays, then ``repeats``."""
    learner = spec.learner
    learning = max(1, learner.max_trials) * learner.average
    confirm = 0 if learner.confirm is None else learner.confirm[1]
    return float(learning + confirm + spec.repeats)


def ranks(jobs: Sequence[RunJob]) -> dict[tuple[str, str], float]:
    """Upward rank of each job: its own expected trials plus the largest rank among the runs
    that start from it (the work on the longest chain it heads).

    Raises:
        ConfigError: Runs that start from each other in a cycle.
    """
    children: dict[tuple[str, str], list[RunJob]] = {j.key: [] for j in jobs}
    for j in jobs:
        if j.spec.start_from is not None:
            children[(j.scenario, j.spec.start_from)].append(j)
    rank: dict[tuple[str, str], float] = {}
    visiting: set[tuple[str, str]] = set()

    def rank_of(job: RunJob) -> float:
        if job.key in visiting:
            raise ConfigError("start_from", "runs depend on each other in a cycle")
        if job.key not in rank:
            visiting.add(job.key)
            below = [rank_of(c) for c in children[job.key]]
            visiting.discard(job.key)
            rank[job.key] = expected_trials(job.spec) + max(below, default=0.0)
        return rank[job.key]

    for j in jobs:
        rank_of(j)
    return rank


def _knots0(job: RunJob) -> np.ndarray | None:
    """The learned command of the run ``job`` starts from, or None."""
    if job.spec.start_from is None:
        return None
    return np.load(job.out_dir / "runs" / job.spec.start_from / "final_knots.npy")


Play = Callable[..., RunSummary]
"""Executes one run: ``play(spec, out_dir, knots0, resume=, progress=)`` (the runner's
``play_run``; a module-level function, so that it reaches worker processes)."""

Finish = Callable[..., None]
"""A finished run's post-run work: ``finish(spec, out_dir, summary, figure=)`` (the runner's
``finish_run``), scheduled as its own task."""


def _task(
    play: Play,
    finish: Finish | None,
    job: RunJob,
    knots0: np.ndarray | None,
    summary: RunSummary | None,
    progress: bool = False,
) -> tuple[RunSummary, float]:
    """One task: the run (``summary`` None) or its post-run work; the summary and wall
    seconds."""
    t0 = time.perf_counter()
    if summary is None:
        summary = play(job.spec, job.out_dir, knots0, resume=job.resume, progress=progress)
    elif finish is not None:
        finish(job.spec, job.out_dir, summary, figure=job.figure)
    return summary, time.perf_counter() - t0


def _worker(args: tuple) -> tuple[RunSummary, float]:
    return _task(*args)


class _Ready:
    """Jobs whose run can start, highest rank first (ties in the given order)."""

    def __init__(self, jobs: Sequence[RunJob]):
        keys = {j.key for j in jobs}
        for j in jobs:
            if j.spec.start_from is not None and (j.scenario, j.spec.start_from) not in keys:
                raise ConfigError(
                    f"run {j.spec.name!r} start_from", f"no run {j.spec.start_from!r} to start from"
                )
        self._rank = ranks(jobs)
        self._order = {j.key: i for i, j in enumerate(jobs)}
        self._waiting = list(jobs)
        self._ready: list[RunJob] = []
        self._done: set[tuple[str, str]] = set()
        self._running = 0
        self._release()

    def _release(self) -> None:
        now = [
            j
            for j in self._waiting
            if j.spec.start_from is None or (j.scenario, j.spec.start_from) in self._done
        ]
        self._waiting = [j for j in self._waiting if j not in now]
        self._ready.extend(now)
        self._ready.sort(key=lambda j: (-self._rank[j.key], self._order[j.key]))

    @property
    def job_keys(self) -> list[tuple[str, str]]:
        """(scenario, run name) of every job, in the given order."""
        return list(self._order)

    def pop(self) -> RunJob | None:
        """The next job to start (now counted as running), or None when none can start now."""
        if not self._ready:
            return None
        self._running += 1
        return self._ready.pop(0)

    def finished(self, job: RunJob) -> None:
        """``job`` has finished: the runs that start from it can start."""
        self._done.add(job.key)
        self._running -= 1
        self._release()

    @property
    def stuck(self) -> bool:
        """Nothing runs, nothing can start and runs are left: they wait on each other in a
        cycle."""
        return not self._ready and not self._running and bool(self._waiting)


def run_jobs(
    jobs: Sequence[RunJob],
    play: Play,
    *,
    finish: Finish | None = None,
    executor: str = "process",
    workers: int = 1,
    address: str | None = None,
    progress: bool = False,
) -> Iterator[tuple[RunJob, RunSummary, float]]:
    """Run every job with ``play`` (then ``finish``); yield ``(job, summary, wall seconds)``
    as each has finished both.

    A job starts once the run it starts from has finished (its learned command is read from
    disk then); of the jobs that can start, the highest :func:`ranks` goes first. A run's
    ``finish`` is a task of its own, started when no run can start (short post-run work fills
    the pool's idle workers while the last runs end), or before other runs once its
    scenario's runs have all ended (the scenario's report waits on it). At most ``workers``
    tasks are in flight (on a Ray cluster at ``address``: every task that can start).

    Raises:
        ConfigError: An unknown executor, ``workers`` < 1, or runs that wait on each other.
    """
    if executor not in EXECUTORS:
        raise ConfigError("--executor", f"unknown executor {executor!r}", EXECUTORS)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError("--workers", f"must be an integer >= 1, got {workers!r}")
    ready = _Ready(jobs)
    if executor == "ray":
        yield from _on_ray(play, finish, ready, len(jobs), workers, address)
    elif workers == 1 or len(jobs) == 1:
        yield from _in_process(play, finish, ready, progress)
    else:
        yield from _on_pool(play, finish, ready, len(jobs), workers)


def _check_stuck(ready: _Ready) -> None:
    if ready.stuck:
        raise ConfigError("start_from", "runs depend on each other in a cycle")


def _in_process(play: Play, finish: Finish | None, ready: _Ready, progress: bool):
    while (job := ready.pop()) is not None:
        summary, wall = _task(play, finish, job, _knots0(job), None, progress)
        ready.finished(job)
        if finish is not None:
            wall += _task(play, finish, job, None, summary)[1]
        yield job, summary, wall
    _check_stuck(ready)


Submit = Callable[[tuple], Any]
"""Starts :func:`_worker` on its arguments; a handle of the running task."""
WaitOne = Callable[[list], tuple[Any, tuple[RunSummary, float]]]
"""Waits for one of the handles to finish; it and its result."""


def _drive(
    play: Play, finish: Finish | None, ready: _Ready, limit: int, submit: Submit, wait_one: WaitOne
):
    """Keep ``limit`` tasks in flight; yield each run once it and its post-run work are done
    (its wall seconds summed). Which task starts next: the post-run work of a scenario whose
    runs have all ended (its report waits on it), else a run that can start, else the oldest
    post-run work."""
    running: dict[Any, tuple[RunJob, float | None]] = {}  # handle -> job, its run's seconds
    unfinished: list[tuple[RunJob, RunSummary, float]] = []
    runs_left = Counter(scenario for scenario, _ in ready.job_keys)

    def post_first() -> tuple[RunJob, RunSummary, float] | None:
        for i, item in enumerate(unfinished):
            if runs_left[item[0].scenario] == 0:
                return unfinished.pop(i)
        return None

    while True:
        while len(running) < limit:
            if (item := post_first()) is not None:
                running[submit((play, finish, item[0], None, item[1]))] = (item[0], item[2])
            elif (job := ready.pop()) is not None:
                running[submit((play, finish, job, _knots0(job), None))] = (job, None)
            elif unfinished:
                job, summary, wall = unfinished.pop(0)
                running[submit((play, finish, job, None, summary))] = (job, wall)
            else:
                break
        if not running:
            break
        handle, (summary, wall) = wait_one(list(running))
        job, run_wall = running.pop(handle)
        if run_wall is not None:
            yield job, summary, run_wall + wall
            continue
        ready.finished(job)
        runs_left[job.scenario] -= 1
        if finish is None:
            yield job, summary, wall
        else:
            unfinished.append((job, summary, wall))
    _check_stuck(ready)


def _on_pool(play: Play, finish: Finish | None, ready: _Ready, n_jobs: int, workers: int):
    with ProcessPoolExecutor(max_workers=min(workers, n_jobs)) as pool:

        def wait_one(handles: list) -> tuple[Any, tuple[RunSummary, float]]:
            done, _ = wait(handles, return_when=FIRST_COMPLETED)
            fut = next(iter(done))
            return fut, fut.result()

        yield from _drive(play, finish, ready, workers, lambda a: pool.submit(_worker, a), wait_one)


def _on_ray(
    play: Play, finish: Finish | None, ready: _Ready, n_jobs: int, workers: int, address: str | None
):
    try:
        import ray
    except ImportError:
        raise ConfigError("--executor", "ray is not installed: pip install -e '.[ray]'") from None
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
        if address is None:
            kwargs["num_cpus"] = workers
        ray.init(address=address, **kwargs)
    task = ray.remote(num_cpus=1)(_worker)

    def wait_one(handles: list) -> tuple[Any, tuple[RunSummary, float]]:
        done, _ = ray.wait(handles, num_returns=1)
        return done[0], ray.get(done[0])

    limit = workers if address is None else 2 * n_jobs  # a cluster: every task that can start
    yield from _drive(play, finish, ready, limit, task.remote, wait_one)
