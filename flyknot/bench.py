"""``flyknot bench``: speed figures measured in one run, printed as text or JSON."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence

from flyknot.errors import ConfigError


def bench_sim(ropes: Sequence[int] | None = None, repeats: int = 1, progress: bool = True) -> dict:
    """Wall seconds per simulated second of a fast trial (robot + rope + self-contact).

    The trial is the showcase swing (0.8 s, joint speeds up to 2.7 rad/s) plus the lab's
    default settling time, run by :class:`flyknot_sim.lab.SimLab` exactly as a learning trial
    is. Each rope is timed ``repeats`` times; the best is kept (least disturbed by other
    load on the machine).
    """
    from tqdm import tqdm

    from flyknot_sim.commands import swing_command
    from flyknot_sim.lab import LabParams, SimLab
    from flyknot_sim.rope import load_rope_table

    table = load_rope_table()
    ropes = sorted(table) if not ropes else list(ropes)
    for r in ropes:
        if r not in table:
            raise ConfigError("rope", f"unknown rope id {r}", sorted(table))
    command = swing_command()
    out = []
    for r in tqdm(ropes, desc="bench sim", disable=not progress, unit="rope"):
        lab = SimLab(LabParams(rope=r))
        best = float("inf")
        sim_s = 0.0
        for _ in range(repeats):
            t0 = time.perf_counter()
            rec = lab.run(command)
            wall = time.perf_counter() - t0
            sim_s = float(rec.metadata["sim_duration_s"])
            best = min(best, wall)
        out.append(
            {
                "rope": r,
                "wall_per_sim_s": best / sim_s,
                "realtime_factor": sim_s / best,
                "sim_s": sim_s,
                "segments": table[r].n_segments,
            }
        )
    return {"ropes": out}


def main(what: str, *, as_json: bool = False, ropes=None, repeats: int = 1) -> int:
    """Run one benchmark and print it."""
    if repeats < 1:
        raise ConfigError("repeats", f"must be >= 1, got {repeats}")
    if what == "sim":
        res = bench_sim(ropes, repeats, progress=not as_json)
        if as_json:
            print(json.dumps(res))
        else:
            print(f"{'rope':>4} {'segments':>8} {'wall s / sim s':>15} {'x real time':>12}")
            for row in res["ropes"]:
                print(
                    f"{row['rope']:>4} {row['segments']:>8} {row['wall_per_sim_s']:>15.3f} "
                    f"{row['realtime_factor']:>12.1f}"
                )
        return 0
    if what == "learner":
        from learner.bench import bench_learner, format_learner

        res = bench_learner(repeats=repeats, progress=not as_json)
        print(json.dumps(res) if as_json else format_learner(res))
        return 0
    raise ConfigError("bench", f"unknown benchmark {what!r}", ["sim", "learner"])
