"""PPO (stable-baselines3) on the tick-level env: runs where the ``rl`` extra is installed."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip(
    "stable_baselines3",
    reason="the rl extra is not installed: pip install torch==2.13.0 (the CPU wheel: "
    "--index-url https://download.pytorch.org/whl/cpu) && pip install -e '.[rl]'",
)

from flyknot.record import TrialRecord
from flyknot_app.baselines import BaselineParams, run_baseline, write_results
from flyknot_app.gym.tick_env import FlyknotTickEnv
from flyknot_sim.commands import SWING_AMPLITUDE, swing_command

# 41 ticks of a gentle swing, inside every limit: a few PPO episodes take seconds. Its t_c
# lies beyond the record, so every cost is the fault penalty: no knot, the whole budget is used.
CMD = swing_command(duration=0.16, amplitude=0.02 * SWING_AMPLITUDE)


def make(tmp_path) -> FlyknotTickEnv:
    return FlyknotTickEnv(
        command=CMD, base_offset=np.zeros(3), settle_s=0.05, record_dir=str(tmp_path)
    )


def test_ppo_books_one_trial_per_episode_and_replays_its_best(tmp_path):
    env = make(tmp_path / "a")
    res = run_baseline("ppo", env, BaselineParams(budget=5, repeats=2), seed=1)
    assert res.name == "ppo" and res.seed == 1
    assert len(res.knots) == len(res.rewards) == len(res.costs) == 5 and not any(res.knots)
    assert res.trials_to_success is None and res.costs == [env.fault_penalty] * 5
    assert res.repeats == ["unknot", "unknot"] and res.success_rate == 0.0
    # The lab's seed is the baseline's; its trials are the episodes, then the repeats (the
    # last training episode's auto-reset opened one more trial, never played).
    records = sorted((tmp_path / "a" / "seed_1").glob("trial_*.json"))
    assert [p.stem for p in records] == [f"trial_{i:05d}" for i in (0, 1, 2, 3, 4, 6, 7)]
    recs = [TrialRecord.load(p.with_suffix("")) for p in records]
    assert all(r.fault is None for r in recs)  # the low-pass keeps exploration in the limits
    # Every episode is its own exploration around the initial command.
    offsets = [r.q_cmd[: CMD.n] - CMD.q for r in recs[:5]]
    assert all(np.abs(o).max() > 1e-4 for o in offsets)
    assert not np.allclose(offsets[0], offsets[1])
    # The repeats replay the best episode's targets (all rewards tie: the first episode).
    for rep in recs[5:]:
        np.testing.assert_array_equal(rep.q_cmd[: CMD.n], recs[0].q_cmd[: CMD.n])
    path = write_results(tmp_path / "out", [res], BaselineParams(budget=5, repeats=2), 1)
    assert "| ppo | 1 | >5 | 10 | 0/2 (0%-66%) |" in path.read_text()
    doc = json.loads((tmp_path / "out" / "baseline.json").read_text())
    assert doc["runs"][0]["name"] == "ppo" and len(doc["runs"][0]["knots"]) == 5


def test_ppo_stops_at_its_first_knot(tmp_path, monkeypatch):
    from flyknot.record import TrialRecord as Rec

    # The third trial of the lab ties (a stand-in verdict: the short command cannot).
    real = Rec.succeeded
    monkeypatch.setattr(
        Rec, "succeeded", property(lambda r: r.metadata["trial_index"] == 2 or real.fget(r))
    )
    env = make(tmp_path)
    res = run_baseline("ppo", env, BaselineParams(budget=10, repeats=1), seed=0)
    assert res.knots == [False, False, True] and res.trials_to_success == 3
    assert res.rewards[2] == env.knot_bonus - env.fault_penalty


def test_the_same_seed_trains_the_same_way(tmp_path):
    a = run_baseline("ppo", make(tmp_path / "a"), BaselineParams(budget=3), seed=4)
    b = run_baseline("ppo", make(tmp_path / "b"), BaselineParams(budget=3), seed=4)
    ra = [TrialRecord.load(p.with_suffix("")) for p in sorted((tmp_path / "a").rglob("*.json"))]
    rb = [TrialRecord.load(p.with_suffix("")) for p in sorted((tmp_path / "b").rglob("*.json"))]
    assert a.rewards == b.rewards and len(ra) == len(rb) == 3
    for x, y in zip(ra, rb, strict=True):
        np.testing.assert_array_equal(x.q_cmd, y.q_cmd)
