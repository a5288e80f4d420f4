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
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError
from flyknot_app.run_summary import RunSummary
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
"""Executes one run: ``play(spec, out_dir, knots0, resume=, progress=, figure=)`` (the
runner's ``execute_run``; a module-level function, so that it reaches worker processes)."""


def _play(
    play: Play, job: RunJob, knots0: np.ndarray | None, progress: bool
) -> tuple[RunSummary, float]:
    """Execute one run; its summary and wall seconds."""
    t0 = time.perf_counter()
    summary = play(
        job.spec, job.out_dir, knots0, resume=job.resume, progress=progress, figure=job.figure
    )
    return summary, time.perf_counter() - t0


def _worker(args: tuple[Play, RunJob, np.ndarray | None]) -> tuple[RunSummary, float]:
    play, job, knots0 = args
    return _play(play, job, knots0, progress=False)


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
    executor: str = "process",
    workers: int = 1,
    address: str | None = None,
    progress: bool = False,
) -> Iterator[tuple[RunJob, RunSummary, float]]:
    """Run every job with ``play``; yield ``(job, summary, wall seconds)`` as each finishes.

    A job starts once the run it starts from has finished (its learned command is read from
    disk then); of the jobs that can start, the highest :func:`ranks` goes first. At most
    ``workers`` runs are in flight (on a Ray cluster at ``address``: every run that can start).

    Raises:
        ConfigError: An unknown executor, ``workers`` < 1, or runs that wait on each other.
    """
    if executor not in EXECUTORS:
        raise ConfigError("--executor", f"unknown executor {executor!r}", EXECUTORS)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError("--workers", f"must be an integer >= 1, got {workers!r}")
    ready = _Ready(jobs)
    if executor == "ray":
        yield from _on_ray(play, ready, len(jobs), workers, address)
    elif workers == 1 or len(jobs) == 1:
        yield from _in_process(play, ready, progress)
    else:
        yield from _on_pool(play, ready, len(jobs), workers)


def _check_stuck(ready: _Ready) -> None:
    if ready.stuck:
        raise ConfigError("start_from", "runs depend on each other in a cycle")


def _in_process(play: Play, ready: _Ready, progress: bool):
    while (job := ready.pop()) is not None:
        summary, wall = _play(play, job, _knots0(job), progress)
        ready.finished(job)
        yield job, summary, wall
    _check_stuck(ready)


def _on_pool(play: Play, ready: _Ready, n_jobs: int, workers: int):
    with ProcessPoolExecutor(max_workers=min(workers, n_jobs)) as pool:
        running: dict[Any, RunJob] = {}
        while True:
            while len(running) < workers and (job := ready.pop()) is not None:
                running[pool.submit(_worker, (play, job, _knots0(job)))] = job
            if not running:
                break
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in done:
                job = running.pop(fut)
                summary, wall = fut.result()
                ready.finished(job)
                yield job, summary, wall
    _check_stuck(ready)


def _on_ray(play: Play, ready: _Ready, n_jobs: int, workers: int, address: str | None):
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
    limit = workers if address is None else n_jobs
    running: dict[Any, RunJob] = {}
    while True:
        while len(running) < limit and (job := ready.pop()) is not None:
            running[task.remote((play, job, _knots0(job)))] = job
        if not running:
            break
        done, _ = ray.wait(list(running), num_returns=1)
        job = running.pop(done[0])
        summary, wall = ray.get(done[0])
        ready.finished(job)
        yield job, summary, wall
    _check_stuck(ready)
