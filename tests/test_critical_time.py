"""Critical time from markers alone (learner.critical_time)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.constants import DEMOS_DIR
from flyknot.demo import Demonstration
from flyknot.errors import RecordError
from learner.critical_time import (
    detect_critical_time,
    first_self_approach,
    first_tracking_loss,
    polyline_self_distance,
)


def test_distance_of_parallel_and_crossing_segments():
    # Segment 0 and segment 2 of a U: parallel at 0.05 m.
    u = np.array([[0, 0, 0], [1, 0, 0], [1, 0.05, 0], [0, 0.05, 0]], dtype=float)
    assert polyline_self_distance(u) == pytest.approx(0.05)
    # A Z folded over itself: segment 2 crosses segment 0.
    z = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0]], dtype=float)
    assert polyline_self_distance(z) == pytest.approx(0.0, abs=1e-12)


@given(st.lists(st.floats(-1, 1), min_size=15, max_size=15))
@settings(max_examples=80, deadline=None)
def test_distance_matches_dense_sampling(coords):
    p = np.asarray(coords).reshape(5, 3)
    d = polyline_self_distance(p)
    s = np.linspace(0, 1, 201)[:, None]
    best = np.inf
    for i in range(4):
        a = p[i] + s * (p[i + 1] - p[i])
        for j in range(i + 2, 4):
            b = p[j] + s * (p[j + 1] - p[j])
            best = min(best, np.min(np.linalg.norm(a[:, None] - b[None], axis=2)))
    assert d <= best + 1e-9
    assert d >= best - 0.02  # the grid's resolution on segments up to 3.5 m long


def test_cues_on_constructed_tracks():
    t = np.arange(5) * 0.1
    hand = np.zeros((5, 3))
    markers = np.zeros((5, 11, 3))
    markers[:, :, 2] = -0.1 * np.arange(1, 12)  # hanging straight
    assert first_self_approach(t, hand, markers, 0.009) is None
    assert first_tracking_loss(t, markers) is None
    markers[3, 10] = markers[3, 2] + [0.005, 0, 0]  # the end touches the rope at t = 0.3
    assert first_self_approach(t, hand, markers, 0.009) == pytest.approx(0.3)
    markers[4, 5] = np.nan
    assert first_tracking_loss(t, markers) == pytest.approx(0.4)


@pytest.mark.parametrize("name", ["fast", "slow", "swipe", "inverse", "robot"])
def test_shipped_demonstrations_within_25_ms(name):
    demo = Demonstration.load(DEMOS_DIR / f"{name}.npz")
    found = detect_critical_time(demo, 0.009)
    assert found.t_c == pytest.approx(demo.t_c, abs=0.025)


def test_bad_points_name_the_problem():
    with pytest.raises(RecordError) as e:
        polyline_self_distance(np.zeros((3, 3)))
    assert str(e.value) == "points must have shape (..., k, 3) with k >= 4, got (3, 3)"


def test_demo_critical_reports_every_shipped_demonstration(tmp_path, capsys):
    import json

    from flyknot_app import demo_cli

    assert demo_cli.main(["demo", "critical", str(DEMOS_DIR), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    rows = {Path(r["file"]).stem: r for r in out["rows"]}
    assert set(rows) == {"fast", "slow", "swipe", "inverse", "robot"} | {
        f"{v}-paced" for v in ("fast", "slow", "swipe", "inverse")
    }
    for name, r in rows.items():
        demo = Demonstration.load(DEMOS_DIR / f"{name}.npz")
        assert r["t_c"] == demo.t_c
        assert r["error_ms"] == pytest.approx(1000 * (r["detected"] - demo.t_c), abs=0.06)
    assert out["summary"]["n"] == len(list(DEMOS_DIR.glob("*.npz")))
    assert abs(out["summary"]["worst_ms"]) == max(abs(r["error_ms"]) for r in rows.values())
    # a replay without self-contact records no t_c: counted, not compared
    with np.load(DEMOS_DIR / "fast.npz") as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    meta["t_c"] = None
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "replay_000.npz", **arrays)
    assert demo_cli.main(["demo", "critical", str(tmp_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["summary"]["no_contact"] == 1 and out["summary"]["n"] == 0
    assert out["rows"][0]["detected"] is not None and out["rows"][0]["error_ms"] is None


def test_critical_summary_statistics_and_errors(tmp_path, capsys):
    from flyknot_app import demo_cli
    from flyknot_app.demo_cli import critical_summary

    rows = [{"t_c": 1.0, "detected": 1.0, "error_ms": e} for e in (-30.0, 1.0, 2.0, 5.0)]
    rows.append({"t_c": 1.0, "detected": None, "error_ms": None})
    s = critical_summary(rows)
    assert s["n"] == 4 and s["no_detection"] == 1 and s["no_contact"] == 0
    assert s["median_ms"] == 1.5 and s["median_abs_ms"] == 3.5 and s["worst_ms"] == -30.0
    assert s["p90_abs_ms"] == pytest.approx(np.percentile([30, 1, 2, 5], 90))
    assert demo_cli.main(["demo", "critical", str(tmp_path / "none.npz")]) == 2
    assert (
        capsys.readouterr()
        .err.strip()
        .endswith(f"path: no file or directory {str(tmp_path / 'none.npz')!r}")
    )
    assert demo_cli.main(["demo", "critical", str(tmp_path)]) == 2
    assert f"path: no .npz files in {tmp_path}" in capsys.readouterr().err


def test_demo_critical_write_gives_a_capture_its_detected_t_c(tmp_path, capsys):
    import json

    from flyknot_app import demo_cli

    with np.load(DEMOS_DIR / "slow.npz") as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    meta["t_c"] = None  # a capture whose critical time nobody marked
    arrays["meta"] = np.array(json.dumps(meta))
    src = tmp_path / "capture.npz"
    np.savez(src, **arrays)
    out = tmp_path / "marked.npz"
    assert demo_cli.main(["demo", "critical", str(src), "--write", str(out), "--json"]) == 0
    row = json.loads(capsys.readouterr().out)["rows"][0]
    demo = Demonstration.load(out)
    assert demo.t_c == row["detected"]
    assert demo.t_c == pytest.approx(Demonstration.load(DEMOS_DIR / "slow.npz").t_c, abs=0.025)
    assert demo.metadata["t_c_source"] == f"markers/{row['cue']}"
    assert demo.metadata["t_c_recorded"] is None
    np.testing.assert_array_equal(demo.markers, arrays["markers"])
    assert demo_cli.main(["demo", "critical", str(DEMOS_DIR), "--write", str(out)]) == 2
    assert (
        capsys.readouterr()
        .err.strip()
        .endswith(
            f"--write: needs exactly one input file, got {len(list(DEMOS_DIR.glob('*.npz')))}"
        )
    )
    bad = tmp_path / "x.npz"
    np.savez(bad, t=np.zeros(3))
    assert demo_cli.main(["demo", "critical", str(bad)]) == 2
    assert "is not a demonstration file" in capsys.readouterr().err
