"""Live motion capture, labelling, resampling and clock alignment of flyknot_hw.mocap.

The live adapter runs against the ``mock`` backend of the real ``motioncapture`` package
(no network), and against a stand-in with the package's API for what 1.1 does not bind
(``pointCloud``). Everything else is loopback-free pure math on synthetic data; the
simulated-lab end-to-end checks are in ``test_hw_mocap_files.py``.
"""

from __future__ import annotations

import sys
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.constants import DEMOS_DIR
from flyknot.errors import ConfigError, HardwareError
from flyknot_hw.mocap import (
    LIVE_KINDS,
    BodyTrack,
    LabelParams,
    MocapSource,
    MotioncaptureSource,
    RawStream,
    align_clocks,
    hanging_markers,
    label_rope_markers,
    marker_arclengths,
    resample_uniform,
    start_event_time,
)

# --- stream and rope geometry ---------------------------------------------------------


def test_marker_arclengths_match_the_rope_layout():
    s = marker_arclengths()
    np.testing.assert_allclose(s[:10], 0.1 * np.arange(1, 11))
    assert s[-1] == pytest.approx(1.1)
    with pytest.raises(ConfigError, match="length"):
        marker_arclengths(0.95)


def test_hanging_markers_hang_down_from_the_fingertip():
    tip = np.array([0.4, 0.0, 1.3])
    h = hanging_markers(tip)
    np.testing.assert_allclose(h[:, :2], np.tile(tip[:2], (11, 1)))
    np.testing.assert_allclose(h[:, 2], tip[2] - marker_arclengths())
    with pytest.raises(ConfigError, match="gravity_dir"):
        hanging_markers(tip, gravity_dir=(0, 0, 0))


def test_raw_stream_validates_and_names_fields():
    t = np.arange(4) * 0.005
    s = RawStream(t, np.zeros((4, 2, 3)), {"hand": BodyTrack.positions_only(np.zeros((4, 3)))})
    assert s.n_frames == 4 and s.frame_rate() == pytest.approx(200.0)
    with pytest.raises(ConfigError, match="valid choices: hand"):
        s.body("tip")
    with pytest.raises(ConfigError, match="increase strictly"):
        RawStream(t[::-1], np.zeros((4, 2, 3)))
    with pytest.raises(ConfigError, match=r"RawStream.points"):
        RawStream(t, np.zeros((3, 2, 3)))
    with pytest.raises(ConfigError, match="frames"):
        RawStream(t, np.zeros((4, 0, 3)), {"hand": BodyTrack.positions_only(np.zeros((3, 3)))})


# --- live source: the real package's mock backend ---------------------------------------


def test_mock_backend_through_the_real_package():
    import motioncapture as mc

    src = MotioncaptureSource(
        "mock",
        {
            "rigid_bodies": "hand(0.4,0.0,1.3,1,0,0,0);base(0,0,1,0.7071068,0,0,0.7071068)",
            "frequency": "200",
        },
        require_points=False,
    )
    assert isinstance(src, MocapSource)
    src.start()
    time.sleep(0.15)
    stream = src.stop()
    assert stream.n_frames >= 5  # 200 Hz requested; the mock sleeps int(1000 / 200) ms
    assert np.all(np.diff(stream.times) > 0.003)
    assert sorted(stream.bodies) == ["base", "hand"]
    np.testing.assert_allclose(
        stream.body("hand").position, [[0.4, 0.0, 1.3]] * stream.n_frames, atol=1e-6
    )
    np.testing.assert_allclose(stream.body("base").quat[0], [0.7071068, 0, 0, 0.7071068], atol=1e-6)
    assert stream.points.shape == (stream.n_frames, 0, 3)
    assert stream.source == "mock@localhost"
    # The source can record again.
    src.start()
    time.sleep(0.03)
    assert src.stop().n_frames >= 1
    # Version 1.1 binds no point cloud: a source that needs the rope's points refuses to start.
    if not hasattr(mc.MotionCapture, "pointCloud"):
        with pytest.raises(HardwareError, match="pointCloud"):
            MotioncaptureSource("mock", {"frequency": "200"}).start()


def test_unknown_kind_lists_the_choices():
    with pytest.raises(ConfigError) as e:
        MotioncaptureSource("phasespace")
    assert e.value.choices == list(LIVE_KINDS)


def test_missing_package_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "motioncapture", None)  # import fails
    with pytest.raises(HardwareError, match=r"flyknot\[mocap\]"):
        MotioncaptureSource("vicon", {"hostname": "10.0.0.1"}).start()


def test_connection_failure_is_a_hardware_error():
    def refuse(kind, cfg):
        raise RuntimeError("Error connecting QTM on address: 127.0.0.1:22222")

    src = MotioncaptureSource("qualisys", {"hostname": "127.0.0.1"}, connect=refuse)
    with pytest.raises(HardwareError, match=r"qualisys@127\.0\.0\.1.*QTM"):
        src.start()


class StandIn:
    """An object with the motioncapture API, plus the ``pointCloud`` later builds bind."""

    def __init__(self, clouds, bodies, stall_after=None):
        self.clouds, self.bodies_seq = clouds, bodies
        self.k = -1
        self.n = 0  # frames delivered
        self.stall_after = stall_after
        self.release = threading.Event()

    def waitForNextFrame(self):
        if self.stall_after is not None and self.n >= self.stall_after:
            self.release.wait()
            raise RuntimeError("connection closed")
        time.sleep(0.001)
        self.n += 1
        self.k = min(self.k + 1, len(self.clouds) - 1)

    @property
    def rigidBodies(self):
        return self.bodies_seq[self.k]

    @property
    def pointCloud(self):
        return self.clouds[self.k]


def _rb(name, pos):
    rot = SimpleNamespace(w=1.0, x=0.0, y=0.0, z=0.0)
    return SimpleNamespace(name=name, position=np.asarray(pos, dtype=np.float32), rotation=rot)


def test_stand_in_points_are_padded_and_bodies_may_vanish():
    clouds = [np.zeros((3, 3)), np.ones((5, 3)), np.zeros((0, 3))] * 4
    bodies = [{"hand": _rb("hand", [1, 2, 3])}, {}, {"hand": _rb("hand", [np.nan, 0, 0])}] * 4
    ticks = iter(np.arange(1000) * 0.005)
    src = MotioncaptureSource(
        "vicon",
        {"hostname": "h"},
        connect=lambda k, c: StandIn(clouds, bodies),
        clock=lambda: float(next(ticks)),
    )
    src.start()
    time.sleep(0.05)
    s = src.stop()
    assert s.points.shape[1] == 5 and s.n_frames >= 3
    counts = np.all(np.isfinite(s.points), axis=2).sum(axis=1)
    assert list(counts[:3]) == [3, 5, 0]
    hand = s.body("hand").position
    np.testing.assert_allclose(hand[0], [1, 2, 3])
    assert np.all(np.isnan(hand[1])) and np.all(np.isnan(hand[2]))  # absent, non-finite


def test_a_stalled_stream_fails_on_stop():
    stand_in = StandIn([np.zeros((1, 3))], [{}], stall_after=2)
    src = MotioncaptureSource("vrpn", connect=lambda k, c: stand_in, frame_timeout_s=0.2)
    src.start()
    time.sleep(0.05)
    with pytest.raises(HardwareError, match="stalled"):
        src.stop()
    stand_in.release.set()  # let the reader thread end


def test_a_silent_system_times_out_on_connect():
    hold = threading.Event()

    def hang(kind, cfg):  # optitrack waits for a NatNet reply that never comes
        hold.wait()
        raise RuntimeError("Could not query NatNet version!")

    src = MotioncaptureSource(
        "optitrack", {"hostname": "127.0.0.1"}, connect=hang, connect_timeout_s=0.1
    )
    with pytest.raises(HardwareError, match=r"no answer within 0\.1 s"):
        src.start()
    hold.set()


def test_stop_before_start_and_double_start():
    src = MotioncaptureSource("vrpn", connect=lambda k, c: StandIn([np.zeros((1, 3))], [{}]))
    with pytest.raises(HardwareError, match="before start"):
        src.stop()
    src.start()
    with pytest.raises(HardwareError, match="already recording"):
        src.start()
    src.stop()


# --- resampling -------------------------------------------------------------------------


def test_resample_bridges_short_gaps_only():
    t = np.arange(20) * 0.005
    v = np.column_stack([t, 2 * t, -t])[:, None, :].repeat(2, axis=1)  # (20, 2, 3), linear
    v[5:8, 0] = np.nan  # 3 missing frames: gap 0.02 s between valid samples 4 and 8
    v[10:16, 1] = np.nan  # 6 missing frames: gap 0.035 s > 0.025 s
    grid, out = resample_uniform(t + 0.001, v, 200.0, max_gap_s=0.025)
    assert out.shape == (20, 2, 3)
    np.testing.assert_allclose(grid, 0.001 + np.arange(20) * 0.005)
    np.testing.assert_allclose(out[:, 0], np.column_stack([t, 2 * t, -t]), atol=1e-12)
    assert np.all(np.isnan(out[10:16, 1])) and np.all(np.isfinite(out[:10, 1]))


@settings(max_examples=60)
@given(
    seed=st.integers(0, 2**32 - 1),
    rate=st.sampled_from([100.0, 200.0, 250.0]),
    max_gap=st.floats(0.004, 0.05),
)
def test_resample_properties(seed, rate, max_gap):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(2, 60))
    t = np.cumsum(rng.uniform(0.002, 0.008, m))  # jittered capture frames
    a, b = rng.normal(size=3), rng.normal(size=3)
    v = a + np.outer(t, b)  # linear in time
    v[rng.random(m) < 0.3] = np.nan
    grid, out = resample_uniform(t, v, rate, max_gap_s=max_gap)
    valid = np.all(np.isfinite(v), axis=1)
    tv = t[valid]
    ok = np.all(np.isfinite(out), axis=1)
    assert np.all(np.isfinite(out) == ok[:, None])  # coordinates valid together
    # Exact for linear data wherever defined.
    np.testing.assert_allclose(out[ok], a + np.outer(grid[ok], b), atol=1e-9)
    for g, defined in zip(grid, ok, strict=True):
        if tv.size == 0 or g < tv[0] - 1e-9 or g > tv[-1] + 1e-9:
            assert not defined  # never extrapolated
            continue
        j = np.searchsorted(tv, g + 1e-9, side="right") - 1
        on_sample = abs(tv[j] - g) <= 1e-9
        bridge = j + 1 < tv.size and tv[j + 1] - tv[j] <= max_gap + 1e-9
        assert defined == (on_sample or bridge)  # never across a longer gap


# --- labelling on synthetic ropes --------------------------------------------------------

TIP = np.array([0.4, 0.0, 1.3])


def _static_rope(m: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(m) * 0.005
    return t, np.repeat(hanging_markers(TIP)[None], m, axis=0)


def test_neighbours_passing_close_keep_their_labels():
    """Markers 4 and 5 trade places, passing 8 mm apart (inside each other's gate)."""
    t, truth = _static_rope(120)
    s = np.clip((t - 0.1) / 0.3, 0, 1)
    u = s**3 * (10 - 15 * s + 6 * s**2)  # smooth 0 -> 1: 0.63 m/s peak, 7 m/s^2
    bump = np.sin(np.pi * u)
    truth[:, 4, 2] -= 0.1 * u
    truth[:, 5, 2] += 0.1 * u
    truth[:, 4, 0] += 0.004 * bump
    truth[:, 5, 0] -= 0.004 * bump
    gap = np.linalg.norm(truth[:, 4] - truth[:, 5], axis=1)
    assert gap.min() < 0.0081  # well inside the 0.03 m gate of each other
    rng = np.random.default_rng(0)
    pts = np.stack([f[rng.permutation(11)] for f in truth])
    res = label_rope_markers(t, pts, TIP)
    np.testing.assert_allclose(res.markers, truth, atol=1e-12)  # every frame, every label
    assert res.n_ambiguous == 0


def test_coincident_markers_are_dropped_not_swapped():
    t, truth = _static_rope(40)
    truth[20, 5] = truth[20, 4] + [0.001, 0, 0]  # marker 5 jumps onto marker 4 for a frame
    res = label_rope_markers(t, truth, TIP)
    assert res.n_ambiguous >= 1
    ok = np.all(np.isfinite(res.markers), axis=2)
    assert not ok[20, 4] or np.allclose(res.markers[20, 4], truth[20, 4])
    assert not ok[20, 5] or np.allclose(res.markers[20, 5], truth[20, 5])
    np.testing.assert_allclose(res.markers[25:], truth[25:])  # all back afterwards


@settings(max_examples=10)
@given(seed=st.integers(0, 2**32 - 1))
def test_labels_do_not_depend_on_point_order(seed):
    rng = np.random.default_rng(seed)
    t, truth = _static_rope(30)
    truth = truth + 0.02 * np.sin(t)[:, None, None] * rng.normal(size=(1, 11, 3))
    truth[rng.random(truth.shape[:2]) < 0.1] = np.nan
    junk = rng.uniform(-1, 2, (30, 2, 3))
    pts = np.concatenate([truth, junk], axis=1)
    a = label_rope_markers(t, pts, TIP).markers
    shuffled = np.stack([f[rng.permutation(f.shape[0])] for f in pts])
    b = label_rope_markers(t, shuffled, TIP).markers
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("demo", ["robot", "swipe"])
def test_labels_through_a_knot_tying_motion(demo):
    """The simulated knot throws of assets/demos (whip accelerations to 800 m/s^2)."""
    z = np.load(DEMOS_DIR / f"{demo}.npz")
    t, truth = z["t"], z["markers"]  # NaN from 20 ms after the first self-contact
    rng = np.random.default_rng(0)
    m = len(t)
    pts = truth + rng.normal(0.0, 0.001, truth.shape)
    visible = rng.random((m, 11)) >= 0.03
    for _ in range(5):
        k, f0, n = rng.integers(0, 10), rng.integers(20, m - 40), rng.integers(5, 30)
        visible[f0 : f0 + n, k : k + 2] = False
    pts[~visible] = np.nan
    visible &= np.all(np.isfinite(truth), axis=2)
    raw = np.concatenate([pts, rng.uniform(-1, 2, (m, 2, 3))], axis=1)
    raw = np.stack([f[rng.permutation(len(f))] for f in raw])
    tip = truth[0, 0] + [0.0, 0.0, 0.1]  # the rope hangs from 0.10 m above marker 0
    res = label_rope_markers(t, raw, tip)
    tracked = np.all(np.isfinite(res.markers), axis=2)
    correct = tracked & (np.linalg.norm(res.markers - truth, axis=2) < 0.008)
    assert correct.sum() >= 0.99 * tracked.sum()
    assert (tracked & visible).sum() >= 0.97 * visible.sum()


def test_hand_cluster_points_are_excluded_with_a_fingertip_track():
    t, truth = _static_rope(10)
    cluster = TIP + np.array([[0.015, 0, 0], [-0.015, 0, 0], [0, 0.015, 0.0]])
    pts = np.concatenate([truth, np.repeat(cluster[None], 10, axis=0)], axis=1)
    tip_track = np.repeat(TIP[None], 10, axis=0)
    res = label_rope_markers(t, pts, tip_track)
    np.testing.assert_allclose(res.markers, truth)


def test_no_hanging_rope_is_a_hardware_error():
    t, truth = _static_rope(5)
    with pytest.raises(HardwareError, match="hanging"):
        label_rope_markers(t, truth + np.array([0.2, 0, 0]), TIP)


def test_label_params_are_validated():
    with pytest.raises(ConfigError, match="gate_m"):
        LabelParams(gate_m=0)
    with pytest.raises(ConfigError, match="init_min_markers"):
        LabelParams(init_min_markers=12)
    with pytest.raises(ConfigError, match="fingertip"):
        label_rope_markers(np.arange(3.0), np.zeros((3, 11, 3)), np.zeros(2))


# --- clock alignment on a synthetic arm ---------------------------------------------------

M = np.random.default_rng(7).normal(0, 0.15, (3, 7))


def toy_fk(q: np.ndarray) -> np.ndarray:
    """A smooth nonlinear map q (n, 7) -> (n, 3) [m] standing in for an arm."""
    return np.sin(q) @ M.T + np.array([0.4, 0.0, 0.3])


def _motion(t: np.ndarray) -> np.ndarray:
    s = np.clip((t - 0.3) / 0.8, 0, 1)
    bump = 64 * s**3 * (1 - s) ** 3
    return 0.2 + np.outer(bump, np.linspace(0.5, 1.2, 7))


def test_alignment_recovers_a_sub_frame_offset():
    t_joint = np.arange(0, 1.6, 0.004)
    q = _motion(t_joint)
    offset = -0.5371234  # t_robot = t_mocap + offset
    t_mocap = np.arange(0.45, 2.2, 0.005)
    base = np.array([1.0, -0.5, 0.8, 0.9, 0.0, 0.1, 0.4])
    base[3:] /= np.linalg.norm(base[3:])
    from flyknot_hw.mocap.calibration import apply_pose

    tip = apply_pose(base, toy_fk(_motion(t_mocap + offset)))
    al = align_clocks(t_mocap, tip, t_joint, q, toy_fk)
    assert abs(al.offset_s - offset) < 1e-5
    assert al.residual_rms_m < 1e-5 and al.correlation > 0.99
    assert abs(al.coarse_offset_s - offset) < 0.01
    np.testing.assert_allclose(al.base_pose[:3], base[:3], atol=1e-4)
    given = align_clocks(t_mocap, tip, t_joint, q, toy_fk, base_pose=base, coarse_offset_s=-0.55)
    assert abs(given.offset_s - offset) < 1e-5 and given.coarse_offset_s == -0.55


def test_start_event_and_its_failures():
    t = np.arange(0, 1, 0.01)
    p = np.zeros((100, 3))
    p[:, 0] = np.clip(t - 0.5, 0, None)  # moves at 1 m/s from t = 0.5 s
    assert start_event_time(t, p, threshold_m=0.005) == pytest.approx(0.505)
    with pytest.raises(HardwareError, match="never moves"):
        start_event_time(t, np.zeros((100, 3)))
    with pytest.raises(ConfigError, match="fk"):
        align_clocks(t, p, t, np.zeros((100, 7)), lambda q: np.zeros((len(q), 2)))
