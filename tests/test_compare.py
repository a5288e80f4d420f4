"""flyknot compare: several run directories side by side."""

from __future__ import annotations

import json

import pytest

from flyknot.errors import ConfigError
from flyknot_app import cli
from flyknot_app.reports.compare import compare, load_runset, mean_trials, ratios, seed_table


def _write(d, runs, name="summary.json"):
    """A scenario's summary.json (runs named ``r0``, ``r1``... unless named) or a
    baseline.json."""
    d.mkdir(parents=True)
    if name == "summary.json":
        runs = [{"name": f"r{i}", **r} for i, r in enumerate(runs)]
        doc = {"scenario": "s", "kind": "learn", "runs": runs}
    else:
        doc = {"runs": runs}
    (d / name).write_text(json.dumps(doc))
    return d


def test_table_and_figures(tmp_path, capsys):
    a = _write(
        tmp_path / "ilc",
        [
            {"costs": [0.6, 0.3], "trials_to_success": 2, "repeat_classes": ["knot", "unknot"]},
            {"costs": [0.5, None, 0.2], "trials_to_success": None, "repeat_classes": ["knot"]},
        ],
    )
    b = _write(
        tmp_path / "cma",
        [{"costs": [0.9, 0.8, 0.7, 0.4], "trials_to_success": 4, "repeats": []}],
        "baseline.json",
    )
    odd = _write(tmp_path / "odd", [{"costs": [1.0], "first_success": 0}])
    with pytest.raises(ConfigError, match=r"^summary.first_success: unknown field \(valid"):
        load_runset(odd)
    assert cli.main(["compare", str(a), str(b), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "| ilc | 1 of 2 | 2 (2-2) | 2/3 (21%-94%) |" in out
    assert "| cma | 1 of 1 | 4 (4-4) | - |" in out
    for f in ("compare.md", "compare_costs.png", "compare_trials.png", "compare_success.png"):
        assert (tmp_path / "out" / f).stat().st_size > 0


def test_a_directory_without_results_is_named(tmp_path):
    with pytest.raises(ConfigError, match=r"^RUN_DIR: '.*empty' holds neither summary.json"):
        compare([tmp_path / "empty"], tmp_path / "out")


def _runs(tts, n_used, extra):
    return [
        {"costs": [0.5] * (n if t is None else t), "trials_to_success": t, **extra(i)}
        for i, (t, n) in enumerate(zip(tts, n_used, strict=True))
    ]


def test_ilc_beside_each_baseline_seed_by_seed(tmp_path, capsys):
    ilc = _write(
        tmp_path / "ilc",
        _runs([2, 4, 3], [10] * 3, lambda i: {"name": f"rope1-seed{i}", "rope": 1, "seed": i}),
    )
    cma = tmp_path / "cma"
    cma.mkdir()
    runs = _runs(
        [12, None, 27],
        [30] * 3,
        lambda i: {"name": "cma", "seed": i, "repeats": ["knot", "unknot"]},
    )
    (cma / "baseline.json").write_text(json.dumps({"rope": 1, "runs": runs}))
    rnd = tmp_path / "random"
    rnd.mkdir()
    runs = _runs([6, 9, 3, 5], [30] * 4, lambda i: {"name": "random", "seed": i})
    (rnd / "baseline.json").write_text(json.dumps({"rope": 1, "runs": runs}))

    sets = [load_runset(d) for d in (ilc, cma, rnd)]
    assert [s.kind for s in sets] == ["ilc", "cma", "random"]
    assert sets[0].keys == ((1, 0), (1, 1), (1, 2))
    assert sets[1].trials == (12, 31, 27)  # no knot in 30 trials: counted as 31
    assert mean_trials(sets[1]) == (pytest.approx(70 / 3), True)
    (b, ref, r, kind, n), (b2, _, r2, kind2, n2) = ratios(sets)
    assert (b.label, ref.label, kind, n) == ("cma", "ilc", ">=", 3)
    assert r == pytest.approx((70 / 3) / 3)
    # random has a seed ILC lacks: the ratio is over the three pairs both have.
    assert (b2.label, kind2, n2) == ("random", "=", 3) and r2 == pytest.approx(6 / 3)

    text = seed_table(sets)
    lines = text.splitlines()
    assert lines[0] == "| rope, seed | ilc | cma | random |"
    assert "| rope 1, seed 1 | 4 | >30 | 9 |" in lines
    assert "| rope 1, seed 3 | - | - | 5 |" in lines
    assert "| mean trials until knot | 3 | >=23.3 | 5.75 |" in lines
    assert (
        "Mean trials until the first knot, cma / ilc: >= 7.78x (over 3 (rope, seed) pairs)" in text
    )
    assert "Mean trials until the first knot, random / ilc: 2x (over 3 (rope, seed) pairs)" in text

    assert cli.main(["compare", str(ilc), str(cma), str(rnd), "--out", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    assert "| cma | 2 of 3 | 19.5 (12-27) | 3/6 (19%-81%) |" in out  # success after the budget
    assert "cma / ilc: >= 7.78x" in out
    for f in ("compare_seeds.png", "compare_success.png"):
        assert (tmp_path / "o" / f).stat().st_size > 1000
    assert "![compare_seeds](compare_seeds.png)" in (tmp_path / "o" / "compare.md").read_text()


def test_without_ilc_no_ratio_is_stated(tmp_path):
    d = tmp_path / "ppo"
    d.mkdir()
    runs = _runs([None], [5], lambda i: {"name": "ppo", "seed": 0})
    (d / "baseline.json").write_text(json.dumps({"rope": 2, "runs": runs}))
    s = load_runset(d)
    assert s.kind == "ppo" and s.keys == ((2, 0),)
    assert ratios([s]) == [] and "Mean trials until the first knot," not in seed_table([s])
    assert "| rope 2, seed 0 | >5 |" in seed_table([s])
