"""``flyknot bench``: speed figures measured in one run, printed as text or JSON."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence

from flyknot.errors import ConfigError
from flyknot.progress import bar_disable


def elastic_rope(rope_id: int):
    """Rope ``rope_id`` of the purely elastic table the lab used before the validation suite
    (``assets/ropes_elastic.toml``: no frictional bending couple, impratio 1) and that table's
    simulation settings."""
    from flyknot.constants import ASSETS_DIR
    from flyknot_sim.rope_table import load_rope_table, load_sim_settings

    path = ASSETS_DIR / "ropes_elastic.toml"
    return load_rope_table(path)[rope_id], load_sim_settings(path)


LABS = ("before", "elastic", "pyramidal", "numpy", "no_links", "inextensible", "now")
"""The labs ``flyknot bench sim`` times, in its order (:func:`_lab_variants`); ``no_links``
only for a rope with links (a chain's link friction or lock-up), ``inextensible`` only for a
rope that stretches (a ``stretch_modulus``)."""


def _lab_variants(rope_id: int):
    """Five labs: ``before`` (a fixed 1.5 s settle, no air drag, 1 deg sway, the elastic
    rope), ``elastic`` (the lab's defaults with the elastic rope table, :func:`elastic_rope`),
    ``pyramidal`` (the lab's defaults with MuJoCo's pyramidal friction cone instead of the
    elliptic one), ``numpy`` (the lab's defaults with the air drag and the self-contact scan
    computed by NumPy instead of the compiled kernels, :data:`flyknot_sim.aero.COMPILED` and
    :data:`flyknot_sim.rope_handle.COMPILED`: the same trials), for a chain ``no_links``
    (the lab's defaults without the links' friction and lock-up), for a rope that stretches
    ``inextensible`` (the lab's defaults with its edges held hard) and ``now`` (the lab's
    defaults)."""
    from dataclasses import replace

    from flyknot_sim.aero import AeroParams
    from flyknot_sim.lab import LabParams, VariationParams
    from flyknot_sim.rope_table import get_rope, load_sim_settings

    rope, settings = elastic_rope(rope_id)
    before = {
        "rope": rope,
        "settings": settings,
        "settle_s": 1.5,
        "aero": AeroParams(enabled=False),
        "variation": VariationParams(sway_deg=1.0, rest_start=False),
    }
    elastic = {"rope": rope, "settings": settings}
    pyramidal = {"rope": rope_id, "settings": replace(load_sim_settings(), cone="pyramidal")}
    variants = {
        "before": before,
        "elastic": elastic,
        "pyramidal": pyramidal,
        "numpy": {"rope": rope_id},
        "now": {"rope": rope_id},
    }
    lab_rope = get_rope(rope_id)
    if lab_rope.link_friction_radius > 0 or lab_rope.lock_angle > 0:
        bare = replace(lab_rope, link_friction_radius=0.0, lock_angle=0.0)
        variants["no_links"] = {"rope": bare}
    if lab_rope.stretch_modulus > 0:
        variants["inextensible"] = {"rope": replace(lab_rope, stretch_modulus=0.0)}
    return {name: variants[name] for name in LABS if name in variants}, LabParams


def bench_sim(ropes: Sequence[int] | None = None, repeats: int = 1, progress: bool = True) -> dict:
    """Wall seconds per simulated second, and simulated seconds per trial, of a fast trial.

    The trial is the showcase swing (0.8 s, joint speeds up to 2.7 rad/s) and the settle,
    run by :class:`flyknot_sim.lab.SimLab` exactly as a learning trial is, in five labs
    measured in the same run: ``before`` (the fixed 1.5 s settle, no drag, the elastic rope),
    ``elastic`` (the lab's defaults with the elastic rope table of ``assets/ropes_elastic.toml``),
    ``pyramidal`` (the lab's defaults with the pyramidal friction cone), ``numpy`` (the lab's
    defaults with the drag and the self-contact scan in NumPy instead of compiled: the same
    records) and ``now`` (the lab's
    defaults: air drag, settle until the rope is at rest, capped, the frictional bending
    couple, the elliptic cone and impratio 10 of ``assets/ropes.toml``). Each
    is timed ``repeats`` times per rope (trials 0, 1, ... of seed 0); the best wall time per
    simulated second is kept (least disturbed by other load), the simulated seconds are
    averaged.
    """
    from tqdm import tqdm

    import flyknot_sim.aero as aero
    import flyknot_sim.rope_handle as rope_handle
    from flyknot_sim.commands import swing_command
    from flyknot_sim.lab import SimLab
    from flyknot_sim.rope_table import load_rope_table

    table = load_rope_table()
    ropes = sorted(table) if not ropes else list(ropes)
    for r in ropes:
        if r not in table:
            raise ConfigError("rope", f"unknown rope id {r}", sorted(table))
    command = swing_command()
    out = []
    for r in tqdm(ropes, desc="bench sim", disable=bar_disable(progress), unit="rope"):
        row: dict = {"rope": r, "segments": table[r].n_segments}
        variants, lab_params = _lab_variants(r)
        for name, kw in variants.items():
            lab = SimLab(lab_params(**kw))
            best = float("inf")
            sims = []
            for _ in range(repeats):
                aero.COMPILED = rope_handle.COMPILED = name != "numpy"
                t0 = time.perf_counter()
                try:
                    rec = lab.run(command)
                finally:
                    aero.COMPILED = rope_handle.COMPILED = True
                wall = time.perf_counter() - t0
                sim_s = float(rec.metadata["sim_duration_s"])
                sims.append(sim_s)
                best = min(best, wall / sim_s)
            row[name] = {
                "wall_per_sim_s": best,
                "realtime_factor": 1.0 / best,
                "sim_s_per_trial": sum(sims) / len(sims),
            }
        out.append(row)
    return {"ropes": out}


def sweep_order(repeats: int) -> list[int]:
    """Worker counts in the order a sweep is timed: 1, 2, then 2, 1, then 1, 2, ...

    The order alternates (ABBA) so that a drift of a shared machine's speed over the
    benchmark's minutes falls on both counts alike instead of on the second one.
    """
    if repeats < 1:
        raise ConfigError("repeats", f"must be >= 1, got {repeats}")
    return [w for r in range(repeats) for w in ((1, 2) if r % 2 == 0 else (2, 1))]


def sweep_speedups(walls: dict[str, dict[int, list[float]]]) -> dict:
    """Per executor: its sweeps' wall seconds on 1 and on 2 workers (each list and its mean)
    and the speed-up, mean(1 worker) / mean(2 workers)."""
    out: dict = {}
    for executor, by_workers in walls.items():
        means = {w: sum(ts) / len(ts) for w, ts in by_workers.items()}
        for w in (1, 2):
            out[f"{executor}_wall_s_{w}"] = means[w]
            out[f"{executor}_walls_s_{w}"] = list(by_workers[w])
        out[f"{executor}_speedup"] = means[1] / means[2]
    return out


def bench_sweep(runs: int = 8, trials: int = 3, repeats: int = 1, progress: bool = True) -> dict:
    """Wall time of a seed sweep of learning runs on 1 and on 2 workers, for both executors.

    The sweep: ``learn-rope1`` at lab seeds 0 .. runs - 1, ``trials`` learning trials each
    (no stop at the first knot, so every run plays them all). Each executor (a local process
    pool, Ray tasks on a local Ray with that many CPUs) runs it ``repeats`` times on each
    worker count, in :func:`sweep_order`, one after the other in this process, from the same
    cached initial guess (made once before, not timed; Ray's start-up is not timed either).
    """
    import contextlib
    import io
    import tempfile
    from pathlib import Path

    try:
        import ray
    except ImportError:
        raise ConfigError("bench sweep", "needs ray: pip install -e '.[ray]'") from None

    from flyknot_app.runner import run_scenario
    from flyknot_app.scenario import expand_seeds, load_scenario

    overrides = {"max_trials": trials, "stop_at_success": False}
    scen = expand_seeds(load_scenario("learn-rope1", overrides), list(range(runs)))
    walls: dict[str, dict[int, list[float]]] = {}
    quiet = contextlib.redirect_stdout(io.StringIO())  # the runner's line per run
    with tempfile.TemporaryDirectory() as tmp, quiet:
        one = expand_seeds(load_scenario("learn-rope1", {"max_trials": 0}), [0])
        run_scenario(one, Path(tmp) / "warm", progress=False)  # the initial guess, cached
        cache = Path(tmp) / "warm" / "initial_guess"
        for executor in ("process", "ray"):
            walls[executor] = {1: [], 2: []}
            for i, workers in enumerate(sweep_order(repeats)):
                if executor == "ray":
                    ray.shutdown()
                    ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
                d = Path(tmp) / f"{executor}{i}"
                d.mkdir()
                (d / "initial_guess").symlink_to(cache, target_is_directory=True)
                t0 = time.perf_counter()
                run_scenario(scen, d, workers=workers, executor=executor, progress=False)
                walls[executor][workers].append(time.perf_counter() - t0)
        ray.shutdown()
    return {"runs": runs, "trials": trials, "repeats": repeats, **sweep_speedups(walls)}


BENCHMARKS = ("sim", "learner", "sweep", "protocol")
"""What ``flyknot bench`` measures."""


def main(
    what: str,
    *,
    as_json: bool = False,
    ropes=None,
    repeats: int = 1,
    workers: int = 2,
    quick: bool = False,
    out: str | None = None,
) -> int:
    """Run one benchmark and print it."""
    if repeats < 1:
        raise ConfigError("repeats", f"must be >= 1, got {repeats}")
    if what == "sim":
        res = bench_sim(ropes, repeats, progress=not as_json)
        if as_json:
            print(json.dumps(res))
        else:
            print(
                f"{'rope':>4} {'lab':>12} {'wall s / sim s':>15} {'x real time':>12} "
                f"{'sim s / trial':>14}"
            )
            for row in res["ropes"]:
                for name in (n for n in LABS if n in row):
                    v = row[name]
                    print(
                        f"{row['rope']:>4} {name:>12} {v['wall_per_sim_s']:>15.3f} "
                        f"{v['realtime_factor']:>12.1f} {v['sim_s_per_trial']:>14.2f}"
                    )
                for base in (b for b in LABS[1:-1] if b in row):
                    ratio = row["now"]["wall_per_sim_s"] / row[base]["wall_per_sim_s"]
                    print(f"{row['rope']:>4} now / {base}, wall s per sim s: {ratio:.2f}")
        return 0
    if what == "learner":
        from flyknot_app.bench.learner import bench_learner, format_learner

        res = bench_learner(repeats=repeats, progress=not as_json)
        print(json.dumps(res) if as_json else format_learner(res))
        return 0
    if what == "sweep":
        res = bench_sweep(repeats=repeats, progress=not as_json)
        if as_json:
            print(json.dumps(res))
        else:
            print(
                f"{res['runs']} learning runs of {res['trials']} trials (learn-rope1, seeds), "
                f"{res['repeats']} sweep(s) per worker count, means:"
            )
            for ex in ("process", "ray"):
                print(
                    f"  {ex:>7}: 1 worker {res[f'{ex}_wall_s_1']:.1f} s, 2 workers "
                    f"{res[f'{ex}_wall_s_2']:.1f} s, speed-up {res[f'{ex}_speedup']:.2f}x"
                )
        return 0
    if what == "protocol":
        from flyknot_app.bench.protocol import bench_protocol, format_protocol

        res = bench_protocol(workers=workers, quick=quick, progress=not as_json, keep=out)
        print(json.dumps(res) if as_json else format_protocol(res))
        return 0
    raise ConfigError("bench", f"unknown benchmark {what!r}", list(BENCHMARKS))
