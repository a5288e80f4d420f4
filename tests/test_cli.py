"""The command line: one-word knot output, bench JSON shape, clean errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flyknot.constants import REPO_ROOT
from flyknot_app.cli import main

KNOTS = REPO_ROOT / "tests" / "data" / "knots"


@pytest.mark.parametrize(
    ("name", "word"),
    [
        ("overhand_41.csv", "trefoil"),
        ("figure_eight_41.npy", "4_1"),
        ("slip_41.npy", "unknot"),
        ("free_end_above_hand_60.npy", "unknot"),
    ],
)
def test_knot_prints_exactly_one_word(capsys, name, word):
    assert main(["knot", str(KNOTS / name)]) == 0
    assert capsys.readouterr().out == f"{word}\n"


def test_knot_straight_rope(tmp_path, capsys):
    p = tmp_path / "line.npy"
    np.save(p, np.column_stack([np.zeros(30), np.zeros(30), -np.linspace(0, 1.1, 30)]))
    assert main(["knot", str(p)]) == 0
    assert capsys.readouterr().out == "unknot\n"


def test_knot_errors_are_one_line(tmp_path, capsys):
    assert main(["knot", str(tmp_path / "missing.npy")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("flyknot: error: ") and err.count("\n") == 1
    p = tmp_path / "c.txt"
    p.write_text("1,2,3\n")
    assert main(["knot", str(p)]) == 2
    assert "valid choices: .csv, .npy" in capsys.readouterr().err


def test_bench_sim_json_shape(capsys):
    assert main(["bench", "sim", "--json", "--ropes", "6"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert list(out) == ["ropes"] and out["ropes"][0]["rope"] == 6
    for lab in ("before", "elastic", "pyramidal", "numpy", "no_links", "now"):
        row = out["ropes"][0][lab]
        assert row["realtime_factor"] == pytest.approx(1 / row["wall_per_sim_s"])
        assert row["sim_s_per_trial"] > 0.8  # the swing itself lasts 0.8 s
    rope = out["ropes"][0]  # the same trial with either drag: the same simulated time
    assert rope["numpy"]["sim_s_per_trial"] == rope["now"]["sim_s_per_trial"]


def test_bench_sim_times_the_chain_without_its_links_too():
    from flyknot_app.bench.sim import _lab_variants

    chain, _ = _lab_variants(6)
    bare = chain["no_links"]["rope"]
    assert (bare.id, bare.link_friction_radius, bare.lock_angle) == (6, 0.0, 0.0)
    assert "no_links" not in _lab_variants(1)[0]  # a cord has no links


def test_bench_sim_times_the_tube_held_inextensible_too():
    from flyknot_app.bench.sim import _lab_variants

    tube, _ = _lab_variants(7)
    rigid = tube["inextensible"]["rope"]
    assert (rigid.id, rigid.stretch_modulus) == (7, 0.0)
    assert list(tube)[-2:] == ["inextensible", "now"]
    assert "inextensible" not in _lab_variants(6)[0]  # the chain does not stretch


def test_bench_rejects_unknown_rope(capsys):
    assert main(["bench", "sim", "--ropes", "8"]) == 2
    assert "unknown rope id 8" in capsys.readouterr().err


def test_bench_learner_json_keys(capsys):
    assert main(["bench", "learner", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in (
        "rollout_s",
        "linearise_s",
        "qp_build_s",
        "qp_osqp_s",
        "qp_clarabel_s",
        "update_s",
        "update_interpreted_s",
        "fd_jacobian_s",
    ):
        assert out[key] > 0, key
    # (the speed-ups are reported, not asserted: no test asserts a time)
    assert out["ift_over_fd"] > 0 and out["compiled_over_numpy"] > 0
    assert out["fd_rel_err"] < 1e-4 and out["compiled_max_dx"] < 1e-8
    assert out["native_over_interpreted"] > 0 and out["native_max_dknots"] == 0.0


def test_default_run_dir_never_overwrites(tmp_path, monkeypatch):
    from flyknot_app.cli import _default_run_dir

    monkeypatch.chdir(tmp_path)
    assert _default_run_dir("quick", False).as_posix() == "runs/quick"
    for d in ("runs/quick", "runs/quick-2"):
        (tmp_path / d).mkdir(parents=True)
        (tmp_path / d / "manifest.json").write_text("{}")
    assert _default_run_dir("quick", False).as_posix() == "runs/quick-3"
    assert _default_run_dir("quick", True).as_posix() == "runs/quick-2"


def test_knot_verdict_line(capsys):
    assert main(["knot", str(KNOTS / "overhand_41.csv"), "--verdict"]) == 0
    assert capsys.readouterr().out.startswith("knot (trefoil 30/31, 0.")
    assert main(["knot", str(KNOTS / "free_end_above_hand_60.npy"), "--verdict"]) == 0
    assert capsys.readouterr().out == "wrapped_at_grip (unknot 31/31, 0.00 m down)\n"


def _subparsers(parser):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield name, sub
                yield from ((f"{name} {n}", s) for n, s in _subparsers(sub))


def test_every_rope_option_takes_a_name():
    from flyknot_app.cli import build_parser
    from flyknot_app.scenario import parse_rope_arg

    with_rope = {
        name: action.type
        for name, sub in _subparsers(build_parser())
        for action in sub._actions
        if "--rope" in action.option_strings
    }
    assert {"trial", "showcase", "model-check", "baseline", "demo replay"} <= set(with_rope)
    assert all(t is parse_rope_arg for t in with_rope.values()), with_rope


@pytest.mark.parametrize(
    ("repeats", "order"),
    [(1, [1, 2]), (2, [1, 2, 2, 1]), (3, [1, 2, 2, 1, 1, 2])],
)
def test_bench_sweep_alternates_worker_counts(repeats, order):
    from flyknot_app.bench.sim import sweep_order

    assert sweep_order(repeats) == order


def test_bench_sweep_order_rejects_no_repeats():
    from flyknot.errors import ConfigError
    from flyknot_app.bench.sim import sweep_order

    with pytest.raises(ConfigError, match="repeats: must be >= 1, got 0"):
        sweep_order(0)


def test_bench_sweep_speedup_is_a_ratio_of_means():
    from flyknot_app.bench.sim import sweep_speedups

    out = sweep_speedups({"ray": {1: [100.0, 80.0], 2: [40.0, 60.0]}})
    assert out["ray_wall_s_1"] == 90.0 and out["ray_wall_s_2"] == 50.0
    assert out["ray_walls_s_2"] == [40.0, 60.0]
    assert out["ray_speedup"] == pytest.approx(1.8)
