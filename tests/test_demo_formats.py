"""Tests of the lab demonstration loaders and writers (flyknot.demo_formats)."""

from __future__ import annotations

from pathlib import Path

import ezc3d
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from flyknot.demo import Demonstration
from flyknot.demo_formats import (
    CSV_COLUMNS,
    DEFAULT_HAND_CLUSTER,
    HAND_LABELS,
    ROPE_LABELS,
    fit_rigid,
    hand_markers_from_pose,
    hand_pose_from_markers,
    load_demo_c3d,
    load_demo_csv,
    save_demo_c3d,
    save_demo_csv,
)
from flyknot.errors import RecordError

RATE = 200.0


def make_demo(k: int = 120, t_start: float = 0.0, seed: int = 0) -> Demonstration:
    """A made-up demonstration: a swinging hand, a rope hanging below, markers lost late."""
    rng = np.random.default_rng(seed)
    t = t_start + np.arange(k) / RATE
    s = t - t_start
    hand = np.column_stack([0.3 * np.sin(4 * s), 0.1 * s, 1.5 + 0.05 * np.cos(3 * s)])
    rot = Rotation.from_rotvec(np.column_stack([0.5 * s, -0.8 * s, 2.0 * s]))
    quat = rot.as_quat(scalar_first=True)
    drop = np.array([0.0, 0.0, -0.1]) * np.arange(1, 12)[:, None]
    markers = hand[:, None, :] + drop[None] + rng.normal(0, 0.01, (k, 11, 3))
    markers[int(0.8 * k) :] = np.nan
    if k > 25:
        markers[10, 4] = np.nan
        markers[20, [0, 9]] = np.nan
    return Demonstration(
        t=t,
        hand_pos=hand,
        hand_quat=quat,
        markers=markers,
        t_c=float(t[int(0.7 * k)]),
        rope=5,
        metadata={"variant": "fast", "note": "a b, c", "n": [1, 2.5]},
    )


def same_rotation(q1: np.ndarray, q2: np.ndarray, atol: float) -> None:
    """q and -q are the same rotation: compare |q1 . q2| with 1."""
    np.testing.assert_allclose(np.abs(np.sum(q1 * q2, axis=1)), 1.0, rtol=0, atol=atol)


def write_c3d(
    path: Path,
    labels: list[str],
    xyz: np.ndarray,
    *,
    units: str = "mm",
    rate: float = RATE,
    events: tuple = (),
    first_frame: int = 0,
    residuals: np.ndarray | None = None,
) -> None:
    """A C3D written by ezc3d directly, as a lab system would (xyz (k, n, 3) in ``units``)."""
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    c["parameters"]["POINT"]["LABELS"]["value"] = labels
    pts = np.ones((4, len(labels), xyz.shape[0]))
    pts[:3] = xyz.transpose(2, 1, 0)
    c["data"]["points"] = pts
    if residuals is not None:
        c["data"]["meta_points"] = {
            "residuals": residuals.T[None],
            "camera_masks": np.zeros((7, len(labels), xyz.shape[0]), dtype=bool),
        }
    c["header"]["points"]["first_frame"] = first_frame
    for label, minutes, seconds in events:
        c.add_event([minutes, seconds], context="General", label=label)
    c.write(str(path))


def lab_markers(demo: Demonstration) -> np.ndarray:
    """Rope then hand markers, (k, 15, 3) [m]."""
    hand = hand_markers_from_pose(demo.hand_pos, demo.hand_quat, DEFAULT_HAND_CLUSTER)
    return np.concatenate([demo.markers, hand], axis=1)


# --- CSV ----------------------------------------------------------------------------------


def test_csv_round_trip(tmp_path: Path) -> None:
    demo = make_demo()
    save_demo_csv(demo, tmp_path / "d.csv")
    back = load_demo_csv(tmp_path / "d.csv")
    np.testing.assert_array_equal(back.t, demo.t)
    np.testing.assert_allclose(back.hand_pos, demo.hand_pos, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.hand_quat, demo.hand_quat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.markers, demo.markers, rtol=0, atol=1e-12)  # NaN alike
    assert np.isnan(back.markers[10, 4]).all() and np.isnan(back.markers[-1]).all()
    assert (back.t_c, back.rope, back.metadata) == (demo.t_c, demo.rope, demo.metadata)


def test_csv_layout_is_as_documented(tmp_path: Path) -> None:
    save_demo_csv(make_demo(), tmp_path / "d.csv")
    lines = (tmp_path / "d.csv").read_text().splitlines()
    assert lines[0] == "# flyknot-demo-csv: 1"
    assert lines[4] == ",".join(CSV_COLUMNS)
    assert lines[4].startswith("t,hand_x,hand_y,hand_z,hand_qw,hand_qx,hand_qy,hand_qz,m0_x,")
    assert lines[4].endswith(",m10_x,m10_y,m10_z") and len(CSV_COLUMNS) == 41
    row = lines[5 + 10].split(",")
    assert row[8 + 12 : 8 + 15] == ["", "", ""]  # marker 4 lost in sample 10: empty cells


def test_csv_hand_written_file(tmp_path: Path) -> None:
    """Columns in another order, an extra column, 'nan' cells, no comment lines."""
    demo = make_demo(k=6)
    cols = [*reversed(CSV_COLUMNS), "frame"]
    rows = [",".join(cols)]
    data = np.column_stack(
        [demo.t, demo.hand_pos, 2.0 * demo.hand_quat, demo.markers.reshape(6, -1)]
    )
    for i, r in enumerate(data):
        cells = ["nan" if np.isnan(x) else f"{x:.6f}" for x in r[::-1]]
        rows.append(",".join([*cells, str(i + 1)]))
    (tmp_path / "h.csv").write_text("\n".join(rows) + "\n")
    back = load_demo_csv(tmp_path / "h.csv", t_c=0.01, rope=2, metadata={"who": "me"})
    np.testing.assert_allclose(back.hand_pos, demo.hand_pos, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.hand_quat, demo.hand_quat, rtol=0, atol=1e-5)  # normalised
    np.testing.assert_allclose(back.markers, demo.markers, rtol=0, atol=1e-6)
    assert (back.t_c, back.rope, back.metadata) == (0.01, 2, {"who": "me"})


def test_csv_argument_overrides_file(tmp_path: Path) -> None:
    demo = make_demo()
    save_demo_csv(demo, tmp_path / "d.csv")
    back = load_demo_csv(tmp_path / "d.csv", t_c=0.2, rope=7, metadata={"variant": "slow"})
    assert (back.t_c, back.rope, back.metadata["variant"], back.metadata["n"]) == (
        0.2,
        7,
        "slow",
        [1, 2.5],
    )


def _csv_error(tmp_path: Path, text: str, **kw) -> str:
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(RecordError) as e:
        load_demo_csv(p, **kw)
    return str(e.value).replace(repr(str(p)), "FILE")


def test_csv_errors(tmp_path: Path) -> None:
    header = ",".join(CSV_COLUMNS)
    good = ",".join(["0.0", "0", "0", "1", "1", "0", "0", "0"] + ["0"] * 33)
    good2 = ",".join(["0.1", "0", "0", "1", "1", "0", "0", "0"] + [""] * 33)
    cut = ",".join(c for c in CSV_COLUMNS if c not in ("hand_qw", "m3_y", "m10_z"))
    assert _csv_error(tmp_path, cut + "\n") == "FILE lacks columns: hand_qw, m3_y, m10_z"
    assert (
        _csv_error(tmp_path, f"{header}\n{good}\n{good2}\n")
        == "FILE has no '# t_c: <seconds>' line; pass t_c= to the loader"
    )
    assert (
        _csv_error(tmp_path, f"# t_c: 0.05\n{header}\n{good}\n{good2.replace('0.1,', 'x,', 1)}\n")
        == "FILE line 4, column t: 'x' is not a number"
    )
    no_hand = good2.replace(",1,1,", ",,1,", 1)
    assert (
        _csv_error(tmp_path, f"{header}\n{good}\n{no_hand}\n", t_c=0.05)
        == "FILE line 3: column hand_z must hold a number (1 row(s) lack time or hand values)"
    )
    assert (
        _csv_error(tmp_path, f"# flyknot-demo-csv: 2\n{header}\n{good}\n", t_c=0.0)
        == "FILE: flyknot-demo-csv version '2' is not supported (valid choices: 1)"
    )
    assert (
        _csv_error(tmp_path, f"{header}\n{good}\n0.1,1\n", t_c=0.0)
        == "FILE line 3: expected 41 values, got 2"
    )
    assert _csv_error(tmp_path, f"{header}\n{good}\n", t_c=0.0) == (
        "FILE needs at least 2 samples, got 1"
    )
    with pytest.raises(RecordError, match=r"^demonstration file '.*nope.csv' does not exist$"):
        load_demo_csv(tmp_path / "nope.csv")


def test_a_file_that_is_not_a_demonstration_is_named(tmp_path):
    text, single = tmp_path / "notes.npz", tmp_path / "q.npy"
    text.write_text("not a demonstration")
    np.save(single, np.zeros(3))
    for path in (text, single):
        with pytest.raises(RecordError) as e:
            Demonstration.load(path)
        assert str(e.value).startswith(f"{str(path)!r} is not a demonstration file (.npz)")


# --- hand pose from four markers ----------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    rotvec=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    pos=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    hidden=st.sampled_from([None, 0, 1, 2, 3]),
)
def test_fit_rigid_recovers_pose(rotvec: list, pos: list, hidden: int | None) -> None:
    """Exact markers (all 4, or any 3) give back the pose to rounding."""
    R = Rotation.from_rotvec(rotvec).as_matrix()
    m = (DEFAULT_HAND_CLUSTER @ R.T + np.array(pos))[None]
    if hidden is not None:
        m[0, hidden] = np.nan
    R_fit, p_fit, rms = fit_rigid(DEFAULT_HAND_CLUSTER, m)
    np.testing.assert_allclose(R_fit[0], R, rtol=0, atol=1e-9)
    np.testing.assert_allclose(p_fit[0], pos, rtol=0, atol=1e-9)
    assert rms[0] < 1e-9
    assert np.linalg.det(R_fit[0]) == pytest.approx(1.0, abs=1e-12)


def test_fit_rigid_is_least_squares_under_noise() -> None:
    """With noise, the fit beats the true pose and nearby perturbations in squared error."""
    rng = np.random.default_rng(0)
    R = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    p = np.array([0.2, 0.1, 1.4])
    m = DEFAULT_HAND_CLUSTER @ R.T + p + rng.normal(0, 0.001, (4, 3))
    R_fit, p_fit, rms = fit_rigid(DEFAULT_HAND_CLUSTER, m[None])

    def cost(Rx: np.ndarray, px: np.ndarray) -> float:
        return float(np.sum((DEFAULT_HAND_CLUSTER @ Rx.T + px - m) ** 2))

    best = cost(R_fit[0], p_fit[0])
    assert best == pytest.approx(4 * rms[0] ** 2, rel=1e-9)
    assert best <= cost(R, p)
    for _ in range(20):
        dR = Rotation.from_rotvec(rng.normal(0, 1e-3, 3)).as_matrix()
        assert best <= cost(dR @ R_fit[0], p_fit[0] + rng.normal(0, 1e-4, 3))


def test_hand_pose_errors() -> None:
    t = np.array([0.0, 0.005])
    m = np.repeat(DEFAULT_HAND_CLUSTER[None], 2, axis=0)
    m[1, [0, 2]] = np.nan
    with pytest.raises(RecordError) as e:
        hand_pose_from_markers(t, m)
    assert str(e.value) == (
        "hand pose undefined in 1 frame(s), first at t = 0.0050 s: fewer than 3 of hand1, "
        "hand2, hand3, hand4 visible, or they lie on a line"
    )
    swapped = np.repeat(DEFAULT_HAND_CLUSTER[None], 2, axis=0)[:, [1, 0, 2, 3]]
    with pytest.raises(RecordError, match=r"^hand markers do not fit hand_cluster: RMS residual"):
        hand_pose_from_markers(t, swapped)
    # the same file read with the matching layout is fine
    p, q = hand_pose_from_markers(t, swapped, DEFAULT_HAND_CLUSTER[[1, 0, 2, 3]])
    np.testing.assert_allclose(p, 0.0, atol=1e-12)
    same_rotation(q, np.array([[1.0, 0, 0, 0]] * 2), 1e-12)


# --- C3D ----------------------------------------------------------------------------------


def test_c3d_round_trip(tmp_path: Path) -> None:
    demo = make_demo()
    save_demo_c3d(demo, tmp_path / "d.c3d")
    back = load_demo_c3d(tmp_path / "d.c3d")
    np.testing.assert_allclose(back.t, demo.t, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.markers, demo.markers, rtol=0, atol=1e-4)  # NaN alike
    assert np.isnan(back.markers[20, [0, 9]]).all() and np.isfinite(back.markers[20, 1]).all()
    np.testing.assert_allclose(back.hand_pos, demo.hand_pos, rtol=0, atol=1e-4)
    same_rotation(back.hand_quat, demo.hand_quat, 1e-6)
    assert back.t_c == pytest.approx(demo.t_c, abs=1e-6)
    assert (back.rope, back.metadata) == (demo.rope, demo.metadata)
    # quaternion signs are continuous in time
    assert np.all(np.sum(back.hand_quat[1:] * back.hand_quat[:-1], axis=1) > 0)


def test_c3d_stores_millimetres_and_missing_points(tmp_path: Path) -> None:
    demo = make_demo()
    save_demo_c3d(demo, tmp_path / "d.c3d")
    c = ezc3d.c3d(str(tmp_path / "d.c3d"))
    assert c["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    assert c["parameters"]["POINT"]["LABELS"]["value"] == [*ROPE_LABELS, *HAND_LABELS]
    np.testing.assert_allclose(c["data"]["points"][:3, 3, 0], demo.markers[0, 3] * 1e3, atol=1e-3)
    assert c["data"]["meta_points"]["residuals"][0, 4, 10] == -1.0
    assert c["data"]["meta_points"]["residuals"][0, 4, 11] == 0.0
    assert c["parameters"]["EVENT"]["LABELS"]["value"] == ["critical"]


def test_c3d_clock_offset_round_trip(tmp_path: Path) -> None:
    demo = make_demo(t_start=1.25)
    save_demo_c3d(demo, tmp_path / "d.c3d")
    back = load_demo_c3d(tmp_path / "d.c3d")
    assert ezc3d.c3d(str(tmp_path / "d.c3d"))["header"]["points"]["first_frame"] == 250
    np.testing.assert_allclose(back.t, demo.t, rtol=0, atol=1e-6)
    assert back.t_c == pytest.approx(demo.t_c, abs=1e-6)


@pytest.mark.parametrize(("units", "scale"), [("mm", 1e3), ("cm", 1e2), ("m", 1.0)])
def test_c3d_lab_file_units_prefix_and_event(tmp_path: Path, units: str, scale: float) -> None:
    """A lab-written file: subject prefixes, shuffled labels, extra labels, a minute event."""
    demo = make_demo(k=40)
    xyz = lab_markers(demo)
    labels = [f"Demonstrator:{s}" for s in (*ROPE_LABELS, *HAND_LABELS)]
    order = np.random.default_rng(2).permutation(15)
    xyz = np.concatenate([xyz[:, order], np.zeros((40, 1, 3))], axis=1)
    labels = [labels[i] for i in order] + ["Wand:tip"]
    # the file starts at frame 12001 (60 s), the contact is at 1 min 0.1 s
    write_c3d(
        tmp_path / "lab.c3d",
        labels,
        xyz * scale,
        units=units,
        events=[("Foot Strike", 1, 0.05), ("Contact", 1, 0.1)],
        first_frame=12000,
    )
    back = load_demo_c3d(tmp_path / "lab.c3d", rope=3)
    np.testing.assert_allclose(back.t, 60.0 + demo.t, rtol=0, atol=1e-6)
    assert back.t_c == pytest.approx(60.1, abs=1e-5)
    np.testing.assert_allclose(back.markers, demo.markers, rtol=0, atol=1e-4)
    np.testing.assert_allclose(back.hand_pos, demo.hand_pos, rtol=0, atol=1e-4)
    same_rotation(back.hand_quat, demo.hand_quat, 1e-6)
    assert back.rope == 3


def test_c3d_invalid_points_by_residual(tmp_path: Path) -> None:
    """Lab systems often store a lost point as zeros with residual -1: it must read as NaN."""
    demo = make_demo(k=40)
    xyz = lab_markers(demo) * 1e3
    xyz[np.isnan(xyz)] = 0.0
    res = np.zeros(xyz.shape[:2])
    res[np.isnan(demo.markers).any(axis=2).nonzero()] = -1.0
    write_c3d(tmp_path / "r.c3d", [*ROPE_LABELS, *HAND_LABELS], xyz, residuals=res)
    back = load_demo_c3d(tmp_path / "r.c3d", t_c=0.05)
    np.testing.assert_array_equal(np.isnan(back.markers), np.isnan(demo.markers))
    assert np.isnan(back.markers[10, 4]).all()


def test_c3d_missing_labels_named(tmp_path: Path) -> None:
    demo = make_demo(k=10)
    xyz = lab_markers(demo) * 1e3
    labels = [*ROPE_LABELS, *HAND_LABELS]
    keep = [i for i, s in enumerate(labels) if s not in ("rope7", "rope10", "hand3")]
    write_c3d(tmp_path / "m.c3d", [labels[i] for i in keep], xyz[:, keep])
    with pytest.raises(RecordError) as e:
        load_demo_c3d(tmp_path / "m.c3d", t_c=0.0)
    msg = str(e.value).replace(repr(str(tmp_path / "m.c3d")), "FILE")
    assert msg.startswith("FILE lacks marker labels: rope7, rope10, hand3 (found: rope0, rope1,")


def test_c3d_errors(tmp_path: Path) -> None:
    demo = make_demo(k=10)
    labels = [*ROPE_LABELS, *HAND_LABELS]
    write_c3d(tmp_path / "e.c3d", labels, lab_markers(demo) * 1e3, events=[("Foot Off", 0, 0.01)])
    f = repr(str(tmp_path / "e.c3d"))
    with pytest.raises(RecordError) as e:
        load_demo_c3d(tmp_path / "e.c3d")
    assert str(e.value) == (
        f"{f} has no event labelled critical or contact (events: Foot Off); pass t_c= to the loader"
    )
    write_c3d(tmp_path / "u.c3d", labels, lab_markers(demo), units="in")
    with pytest.raises(RecordError) as e:
        load_demo_c3d(tmp_path / "u.c3d", t_c=0.0)
    assert str(e.value) == (
        f"{str(tmp_path / 'u.c3d')!r}: POINT:UNITS 'in' is not supported (valid choices: mm, cm, m)"
    )
    (tmp_path / "junk.c3d").write_bytes(b"not a c3d file at all" * 10)
    with pytest.raises(RecordError, match=r"is not a readable C3D file"):
        load_demo_c3d(tmp_path / "junk.c3d", t_c=0.0)


def test_save_c3d_needs_the_frame_grid(tmp_path: Path) -> None:
    demo = make_demo(k=10, t_start=0.0012)
    with pytest.raises(RecordError) as e:
        save_demo_c3d(demo, tmp_path / "g.c3d")
    assert str(e.value) == (
        "C3D needs uniform samples starting on the frame grid at 200 Hz; the demonstration's "
        "times are off it by up to 0.0012 s (t[0] = 0.0012 s)"
    )
