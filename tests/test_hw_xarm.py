"""XArmCell against a fake controller on loopback, through the real, unmodified xArm SDK.

Never another address: every fake listens on 127.x.y.z (see ``tests/fakes/fake_xarm.py``).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import xarm  # noqa: F401 - the test extra installs it
from fakes import SimFingertip, StandInMocap, fake_factory, lab_doc
from fakes.fake_xarm import HOME, FakeXArm

from flyknot.errors import ConfigError, HardwareError
from flyknot.record import Cell, JointCommand, TrialRecord
from flyknot_hw.config import parse_lab_config
from flyknot_hw.mocap import RawStream
from flyknot_hw.mocap.trial import MAX_TIP_RESIDUAL_M
from flyknot_hw.preflight import PreflightError
from flyknot_hw.xarm_cell import XArmCell
from tests.knot_curves import verdict

ROOT = Path(__file__).resolve().parents[1]
MOTION = {11, 12, 19, 23, 29}  # motion enable, set state, set mode, joint move, servo_j
RATE = 250.0
FK = SimFingertip()


@pytest.fixture
def make_fake(monkeypatch):
    """Start fakes (loopback only); patch the SDK's port constants only when the fake could
    not bind the SDK's own ports."""
    yield from fake_factory(monkeypatch)


@pytest.fixture
def cells():
    made = []

    def make(fake: FakeXArm, judge=lambda r: verdict("knot"), **kw) -> XArmCell:
        sections = kw.pop("sections", {})
        kw.setdefault("mocap", StandInMocap())
        cell = XArmCell(
            parse_lab_config(lab_doc(fake, **sections)), fingertip=FK, judge=judge, **kw
        )
        made.append(cell)
        return cell

    yield make
    for c in made:
        c.close()


def throw(n: int = 250, amp: float | None = None, start=HOME + 0.05) -> np.ndarray:
    """At rest at both ends: q = start + amp (1 - cos(2 pi t / T)) / 2 on every joint
    (default amp 0.3 rad over 1 s, less for shorter commands: peak 24 rad/s^2)."""
    amp = 0.3 * min(1.0, (n / 250) ** 2) if amp is None else amp
    t = np.arange(n) / (n - 1)
    s = 0.5 * (1 - np.cos(2 * np.pi * t))
    return start + amp * np.outer(s, [1.0, 0.6, 1.0, 0.6, 1.0, 0.6, 1.0])


def motion_events(fake: FakeXArm) -> list:
    return [(name, v) for _, name, v in fake.events if name != "move_joint"]


# --- the fake speaks the SDK ---------------------------------------------------------------
def test_sdk_connects_and_changes_mode_and_state(make_fake):
    from xarm.wrapper import XArmAPI

    fk = make_fake(report_hz={30002: 50.0})
    api = XArmAPI(fk.host, is_radian=True, forbid_uds=True)
    try:
        assert api.connected and api.axis == 7 and api.sn == fk.serial
        assert api.version_number == (2, 5, 0)
        assert api.motion_enable(True) == 0
        assert api.set_mode(1) == 0 and api.mode == 0  # takes effect at set_state(0)
        assert api.set_state(0) == 0
        assert fk.wait_for(lambda: fk.mode == 1) and fk.wait_for(lambda: api.mode == 1)
        assert api.set_state(4) == 0 and api.get_state() == (0, 4)
        np.testing.assert_allclose(api.angles, HOME, atol=5e-3)  # rich report, radians, sag
    finally:
        api.disconnect()
    assert not fk.unknown


def test_fake_firmware_faults_on_its_own(make_fake):
    """C24 for a servo target too far from the last, C23 outside the joint range."""
    from xarm.wrapper import XArmAPI

    fk = make_fake(arm="exact")
    api = XArmAPI(fk.host, is_radian=True, forbid_uds=True, check_joint_limit=False)
    try:
        api.motion_enable(True), api.set_mode(1), api.set_state(0)
        assert api.set_servo_angle_j((HOME + 0.05).tolist(), is_radian=True) == 1
        assert api.get_err_warn_code() == (0, [24, 0]) and fk.state == 4
        api.clean_error(), api.motion_enable(True), api.set_mode(1), api.set_state(0)
        q = fk.q
        q[1] = fk.ranges[1, 1] + 0.01
        assert api.set_servo_angle_j(q.tolist(), is_radian=True) == 1
        assert api.get_err_warn_code()[1] == [23, 0]
    finally:
        api.disconnect()


# --- the robot's own limits ------------------------------------------------------------------
@pytest.mark.parametrize(
    ("serial", "q4_min"), [("XI1305FAKE0001", -0.10472), ("XI1303FAKE0001", -0.19)]
)
def test_cell_reads_the_robot_limits(make_fake, cells, serial, q4_min):
    fk = make_fake(serial=serial, reduced=(2.0, np.tile([-3.0, 3.0], (7, 1))))
    cell = cells(fk)
    cell.connect()
    assert cell.robot_info["serial"] == serial and cell.robot_info["reduced_mode"]
    assert cell.limits.q_min[3] == pytest.approx(q4_min, abs=1e-6)  # stricter of paper, robot
    assert cell.limits.q_min[0] == pytest.approx(-3.0, abs=1e-6)  # reduced-mode range
    np.testing.assert_allclose(cell.limits.qd_max, 2.0, rtol=1e-6)  # reduced-mode speed


# --- a whole trial -----------------------------------------------------------------------------
def test_stream_plays_the_command_and_records_it(make_fake, cells):
    fk = make_fake()
    mocap = StandInMocap(fk)
    ticks = []
    cell = cells(fk, mocap=mocap, on_tick=lambda i, t: ticks.append(i))
    q = throw()
    assert isinstance(cell, Cell)
    rec = cell.run(JointCommand(q))
    assert rec.fault is None and rec.knot == "trefoil" and cell.trial_index == 1
    # the controller received exactly the command, in servo mode, once each
    np.testing.assert_allclose(fk.servo_targets(), q, atol=1e-6)
    assert all(e.mode == 1 and e.applied for e in fk.servo)
    assert motion_events(fk) == [
        ("motion_enable", True), ("set_mode", 0), ("set_state", 0),
        ("set_mode", 1), ("set_state", 0), ("set_mode", 0), ("set_state", 0),
    ]  # fmt: skip
    moves = [v for _, name, v in fk.events if name == "move_joint"]
    assert len(moves) == 1
    np.testing.assert_allclose(moves[0], q[0], atol=1e-6)
    # what was measured
    n_after = round(0.1 * RATE)
    assert rec.q_meas.shape == (250 + n_after, 7) and ticks == list(range(250 + n_after))
    np.testing.assert_allclose(rec.t_joint, np.arange(250 + n_after) / RATE)
    np.testing.assert_array_equal(rec.q_cmd[:250], q)
    np.testing.assert_array_equal(rec.q_cmd[250:], np.tile(q[-1], (n_after, 1)))
    assert np.all(np.isfinite(rec.q_meas))
    # The measured joints follow the command: the same excursion on every joint, a lag
    # behind it (the fake's servos and the report's age, which grows with the machine's
    # load: 0.03 rad seen, 30 ms at the throw's speed) well under the throw's 0.3 rad.
    np.testing.assert_allclose(np.ptp(rec.q_meas, axis=0), np.ptp(rec.q_cmd, axis=0), rtol=0.05)
    assert np.max(np.abs(rec.q_meas - rec.q_cmd)) < 0.1
    assert rec.metadata["joint_source"] == "report30000"
    timing = rec.metadata["timing"]
    assert timing["ticks"] == 250
    late_ms = np.array(timing["lateness_us"]) / 1e3  # the summary is of the ticks' own times
    assert timing["lateness"]["max_ms"] == pytest.approx(late_ms.max(), abs=1e-3)
    assert len(timing["lateness_us"]) == len(timing["round_trip_us"]) == 250
    assert rec.metadata["robot"]["serial"] == fk.serial
    # fingertip in the mocap frame: the base pose's translation added to the base-frame FK
    p, quat = FK(rec.q_meas[:1])
    np.testing.assert_allclose(rec.fingertip_pos[0], p[0] + [0.1, -0.2, 0.8], atol=1e-9)
    assert abs(np.dot(rec.fingertip_quat[0], quat[0])) == pytest.approx(1.0)
    # markers: started before the stream, on the robot clock (0 at the first command sample)
    assert mocap.started == mocap.stopped == 1
    assert rec.t_marker[0] < 0 < rec.t_marker[-1] and rec.markers.shape[1:] == (11, 3)
    meta = rec.metadata["mocap"]
    assert "error" not in meta and meta["aligned_on"] == "fingertip body"
    # The stand-in sees the fake arm's own fingertip on the host clock (t_robot = t_perf -
    # t0), stamped in a thread that shares the GIL with the controller's: a stamp can lag its
    # reading by a thread switch (2.5 mm rms seen on a loaded machine, 1 ms at the throw's
    # speed). Another instant of the throw would be centimetres and tens of ms off.
    assert meta["residual_rms_m"] < MAX_TIP_RESIDUAL_M  # what the cell accepts
    t0 = rec.metadata["timing"]["t0_perf_counter_s"]
    assert abs(meta["offset_s"] + t0) < 5e-3
    k = rec.t_marker * 200.0
    np.testing.assert_allclose(k, np.round(k), atol=1e-6)
    i = np.searchsorted(rec.t_marker, 0.5)
    j = round(0.5 * RATE)
    hang = rec.fingertip_pos[j] + np.outer(0.1 * np.arange(1, 12), [0, 0, -1.0])
    np.testing.assert_allclose(rec.markers[i], hang, atol=0.01)  # markers follow the arm
    assert rec.metadata["settle"]["before"]["mode"] == "seconds"


def test_record_round_trips_through_files(make_fake, cells, tmp_path):
    fk = make_fake(arm="exact")
    rec = cells(fk, sections={"robot": {"joint_source": "poll"}}).run(JointCommand(throw(60)))
    assert rec.metadata["joint_source"] == "poll:get_servo_angle"
    assert np.all(np.isfinite(rec.q_meas))
    assert fk.registers().count(42) >= 60  # one joint read per tick
    back = TrialRecord.load(rec.save(tmp_path / "trial"))
    np.testing.assert_array_equal(back.q_meas, rec.q_meas)
    assert back.metadata == rec.metadata


def test_report_port_refused(make_fake, cells):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        dead = s.getsockname()[1]
    fk = make_fake(arm="exact")
    rec = cells(fk, sections={"robot": {"report_port": dead}}).run(JointCommand(throw(30)))
    assert rec.metadata["joint_source"] == "poll:get_servo_angle (report port refused)"
    before = len(fk.events)
    strict = cells(fk, sections={"robot": {"report_port": dead, "joint_source": "report"}})
    with pytest.raises(HardwareError, match=r"robot\.report_port: cannot connect"):
        strict.run(JointCommand(throw(30)))
    assert len(fk.events) == before  # refused before any motion


def test_settle_checks_are_called_and_recorded(make_fake, cells, monkeypatch):
    fk = make_fake(arm="exact")
    calls = []
    cell = cells(
        fk,
        settle=lambda phase: calls.append(phase) or {"rest_s": 1.0},
        sections={"settle": {"mode": "markers"}},
    )
    rec = cell.run(JointCommand(throw(30)))
    assert calls == ["before", "after"]
    after = rec.metadata["settle"]["after"]
    assert after["mode"] == "markers" and after["rest_s"] == 1.0
    with pytest.raises(ConfigError, match=r"settle\.mode"):
        cells(fk, sections={"settle": {"mode": "markers"}})
    prompts = []
    monkeypatch.setattr("builtins.input", lambda text: prompts.append(text) or "")
    cells(fk, sections={"settle": {"mode": "operator"}}).run(JointCommand(throw(30)))
    assert len(prompts) == 2 and "before the throw" in prompts[0]


def test_no_controller_or_wrong_port(make_fake, cells):
    fk = make_fake(arm="exact")
    doc = lab_doc(fk)
    doc["robot"]["address"] = fk.host.rsplit(".", 1)[0] + ".255"  # fakes use .1 to .254
    cell = XArmCell(parse_lab_config(doc), fingertip=FK)
    with pytest.raises(HardwareError, match=r"robot\.address: cannot connect"):
        cell.run(JointCommand(throw(30)))
    with pytest.raises(ConfigError, match=r"robot\.port: the xArm SDK connects to port"):
        cells(fk, sections={"robot": {"port": 503}}).connect()


# --- refused before anything moves -------------------------------------------------------------
@pytest.mark.parametrize("what", ["joint", "workspace", "torque", "rate", "pose", "error"])
def test_refused_before_any_motion(make_fake, cells, what):
    fk = make_fake(
        arm="exact",
        q0=np.r_[HOME[0], -1.9, HOME[2:]] if what == "pose" else HOME,
        initial_error=31 if what == "error" else 0,
    )
    q = throw()
    kw, rate = {}, RATE
    if what == "joint":
        q[150:, 1] = q[149, 1] + np.linspace(0, 2.0, 100)  # past the paper's joint 2 limit
    if what == "workspace":
        kw["sections"] = {"safety": {"workspace": {"min": [-1, -1, 0.5], "max": [1, 1, 1.5]}}}
    if what == "torque":
        kw["torques"] = lambda c: np.full((c.n, 7), 25.0)  # joint 6/7 limit 20 N m
    if what == "rate":
        rate = 200.0
    cell = cells(fk, **kw)
    expected = {"rate": ConfigError, "error": HardwareError}.get(what, PreflightError)
    with pytest.raises(expected) as e:
        cell.run(JointCommand(q, rate_hz=rate))
    msg = str(e.value)
    assert {
        "joint": "joint 2 ",
        "workspace": "leaves the workspace box",
        "torque": "joint 6 torque 25 N m",
        "rate": "robot.servo_rate_hz",
        "pose": "the robot's current pose: joint 2 position -1.9 rad",
        "error": "C31 Collision Caused Abnormal Current",
    }[what] in msg
    assert not MOTION & set(fk.registers()), fk.registers()
    assert not fk.servo and cell.trial_index == 0


def test_recover_after_an_error(make_fake, cells):
    fk = make_fake(arm="exact", initial_error=31)
    cell = cells(fk)
    assert cell.recover() == 2 and fk.error_code == 0
    assert cell.run(JointCommand(throw(30))).fault is None


# --- faults mid-motion --------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("code", "warn", "label"),
    [
        (31, False, "controller error C31 Collision Caused Abnormal Current"),
        (23, False, "controller error C23 Joints Angle Exceed Limit"),
        (24, False, "controller error C24 Speed Exceeds Limit"),
        (11, True, "controller warning W11 Current controller cache is full"),
    ],
)
def test_fault_mid_motion_stops_the_arm(make_fake, cells, code, warn, label):
    fk = make_fake(arm="exact")
    judged = []
    mocap = StandInMocap()
    cell = cells(fk, judge=lambda r: judged.append(r) or verdict("knot"), mocap=mocap)
    fk.inject(code, after_servo=60, warn=warn)
    rec = cell.run(JointCommand(throw(200)))
    assert rec.fault == f"{label} at t={59 / RATE:.3f} s (tick 59)"
    assert rec.fault_time == pytest.approx(59 / RATE)
    assert len(fk.servo) == 60  # nothing streamed after the faulted tick
    stops = [t for t, name, v in fk.events if name == "set_state" and v == 4]
    assert stops and stops[0] >= fk.servo[-1].t and fk.state == 4
    ctrl = rec.metadata["controller"]
    assert ctrl["code"] == code and ctrl["stop"] == {"stop_sent": True, "state": 4, "stop_code": 0}
    assert rec.knot is None and not judged and cell.trial_index == 1
    n = 60 + round(cell.brake_s * RATE)
    assert rec.q_meas.shape == (n, 7)
    np.testing.assert_allclose(rec.q_cmd[59:], np.tile(rec.q_meas[59], (n - 59, 1)))
    assert mocap.stopped == 1


@pytest.mark.parametrize("how", ["close", "silent"])
def test_dropped_connection_raises_after_trying_to_stop(make_fake, cells, how):
    fk = make_fake(arm="exact")
    mocap = StandInMocap()
    cell = cells(fk, mocap=mocap)
    fk.drop(after_servo=40, how=how)
    t = time.perf_counter()
    with pytest.raises(HardwareError, match="connection to the controller lost at tick 39"):
        cell.run(JointCommand(throw(200)))
    assert time.perf_counter() - t < 5.0
    assert len(fk.servo) == 40 and mocap.stopped == 1 and cell.trial_index == 0


# --- Ctrl-C -------------------------------------------------------------------------------------
def test_keyboard_interrupt_from_the_tick_callback_stops_the_arm(make_fake, cells):
    fk = make_fake(arm="exact")
    mocap = StandInMocap()

    def tick(i, t):
        if i == 40:
            raise KeyboardInterrupt

    cell = cells(fk, mocap=mocap, on_tick=tick)
    with pytest.raises(KeyboardInterrupt):
        cell.run(JointCommand(throw(200)))
    assert len(fk.servo) == 41 and fk.state == 4
    assert fk.events[-1][1:] == ("set_state", 4) and fk.events[-1][0] > fk.servo[-1].t
    assert mocap.stopped == 1 and cell.trial_index == 0


def test_a_tick_sent_late_stops_the_arm(make_fake, cells):
    fk = make_fake(arm="exact")
    mocap = StandInMocap()

    def tick(i, t):
        if i == 40:
            time.sleep(0.6)  # tick 41 goes out ~0.6 s after its deadline

    # A bound well above a loaded machine's hiccups (the fake's 20-30 ms) but below 0.6 s.
    cell = cells(fk, mocap=mocap, on_tick=tick, sections={"robot": {"max_late_s": 0.25}})
    with pytest.raises(HardwareError, match=r"^tick 41 was sent \d+\.\d ms late "):
        cell.run(JointCommand(throw(200)))
    assert len(fk.servo) == 41 and fk.state == 4
    assert mocap.stopped == 1 and cell.trial_index == 0


CHILD = textwrap.dedent(
    """
    import json, sys
    sys.path[:0] = [{root!r}, {tests!r}]
    from xarm.core.config.x_config import XCONF
    for name, port in json.loads({ports!r}).items():
        setattr(XCONF.SocketConf, name, port)
    import numpy as np
    from fakes import SimFingertip, StandInMocap
    from flyknot.record import JointCommand
    from flyknot_hw.config import parse_lab_config
    from flyknot_hw.xarm_cell import XArmCell
    from flyknot.verdict import operator_verdict
    cell = XArmCell(parse_lab_config(json.loads({doc!r})), fingertip=SimFingertip(),
                    judge=lambda r: operator_verdict("none"), mocap=StandInMocap())
    q = np.load({command!r})
    rec = cell.run(JointCommand(q))
    print("RESULT " + json.dumps({{"fault": rec.fault, "timing": rec.metadata["timing"]}}))
    cell.close()
    """
)


def _child(fk: FakeXArm, q: np.ndarray, tmp_path: Path) -> subprocess.Popen:
    np.save(tmp_path / "q.npy", q)
    ports = {} if fk.uses_sdk_ports else fk.sdk_port_overrides()
    code = CHILD.format(
        root=str(ROOT), tests=str(ROOT / "tests"), ports=json.dumps(ports),
        doc=json.dumps(lab_doc(fk)), command=str(tmp_path / "q.npy"),
    )  # fmt: skip
    return subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip


def test_sigint_to_a_streaming_process_stops_the_arm(make_fake, tmp_path):
    """Ctrl-C (SIGINT) to the process streaming a 4 s command: the arm is stopped, then the
    KeyboardInterrupt ends the process."""
    fk = make_fake(arm="exact")
    proc = _child(fk, throw(1000), tmp_path)
    try:
        assert fk.wait_for(lambda: len(fk.servo) >= 50, timeout=30.0), proc.stderr
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    finally:
        proc.kill()
    assert "KeyboardInterrupt" in err and "RESULT" not in out
    assert proc.returncode != 0
    assert 50 <= len(fk.servo) < 1000
    stops = [t for t, name, v in fk.events if name == "set_state" and v == 4]
    assert stops and stops[-1] > fk.servo[-1].t and fk.state == 4


def test_streaming_jitter_in_a_separate_process(make_fake, tmp_path):
    """The cell in its own process, the fake in this one (as a real controller would be):
    the stream plays every tick and records its timing (printed; the lab file's
    ``robot.max_late_s`` bounds it, since a later tick aborts the stream)."""
    fk = make_fake()
    proc = _child(fk, throw(500), tmp_path)
    out, err = proc.communicate(timeout=60)
    line = [x for x in out.splitlines() if x.startswith("RESULT ")]
    assert line, err
    result = json.loads(line[0][7:])
    assert result["fault"] is None
    timing = result["timing"]
    stats = {k: v for k, v in timing.items() if not k.endswith("_us")}
    print("\nstreaming timing against the fake (separate process):", json.dumps(stats))
    assert timing["ticks"] == 500
    assert 0.0 <= timing["lateness"]["max_ms"] < 1e3 * lab_doc(fk)["robot"]["max_late_s"]
    np.testing.assert_allclose(fk.servo_targets(), throw(500), atol=1e-6)


# --- the cell's motion capture ------------------------------------------------------------------
def test_the_cell_builds_its_motion_capture_from_the_lab_file(make_fake, tmp_path):
    from flyknot_hw.mocap import MotioncaptureSource, RecordedFileSource

    fk = make_fake(arm="exact")
    lab = tmp_path / "lab"
    lab.mkdir()
    doc = lab_doc(fk)
    path = lab / "lab.toml"
    cell = XArmCell(parse_lab_config(doc, source=str(path)), fingertip=FK)
    src = cell._mocap
    assert isinstance(src, RecordedFileSource)  # relative to the lab file, its name a pattern
    assert src.directory == lab / "captures" and src.pattern == "trial_*.c3d"
    assert src.reader_kwargs == {"clusters": ("fingertip",)}
    # the recordings directory is missing: refused before anything moves
    with pytest.raises(HardwareError, match=r"mocap\.file: the recordings directory"):
        cell.run(JointCommand(throw(30)))
    assert not MOTION & set(fk.registers())
    live = {"kind": "live", "system": "qualisys", "address": "10.0.0.5:22223", "file": None}
    src = XArmCell(parse_lab_config(lab_doc(fk, mocap=live)), fingertip=FK)._mocap
    assert isinstance(src, MotioncaptureSource) and src.host_clock
    assert src.config == {"hostname": "10.0.0.5", "port": "22223"}
    bad = {**live, "system": "c3d"}
    with pytest.raises(ConfigError, match=r"mocap\.system: unknown value 'c3d'"):
        XArmCell(parse_lab_config(lab_doc(fk, mocap=bad)), fingertip=FK)
    with pytest.raises(ConfigError, match=r"settle\.mode: \"markers\" needs a live"):
        XArmCell(parse_lab_config(lab_doc(fk, settle={"mode": "markers"})), fingertip=FK)


def test_recorded_files_are_matched_by_pattern_and_novelty(tmp_path):
    from flyknot_hw.mocap import RecordedFileSource, cluster_labels, write_c3d

    labels = ["p0", "fingertip1", "Hand:fingertip_2", "fingertip3", "tip1", "fingertips"]
    assert cluster_labels(labels, "fingertip") == ["fingertip1", "Hand:fingertip_2", "fingertip3"]
    t = np.arange(5) / 200.0
    pts = np.tile([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]], (5, 1, 1))  # a point, a cluster

    def name(prefix: str, ago_s: float) -> str:  # stamped with the capture's start
        return time.strftime(f"{prefix}_%Y%m%d-%H%M%S.c3d", time.localtime(time.time() - ago_s))

    old = write_c3d(tmp_path / name("trial", 5), RawStream(t, pts), rate_hz=200.0)
    (tmp_path / name("other", 0)).write_bytes(old.read_bytes())
    src = RecordedFileSource(tmp_path, pattern="trial_*.c3d", wait_s=0.3, poll_s=0.05,
                             reader_kwargs={"clusters": ("fingertip",)})  # fmt: skip
    src.start()  # the earlier trial's file is there and stays unchanged: never taken
    with pytest.raises(HardwareError, match="new since the trial began"):
        src.stop()
    src.start()
    new = name("trial", 0)
    write_c3d(tmp_path / new, RawStream(t, pts), rate_hz=200.0,
              labels=["p0", "fingertip1", "fingertip2"])  # fmt: skip
    stream = src.stop()
    assert src.last_path.name == new and stream.points.shape[1] == 1
    np.testing.assert_allclose(stream.body("fingertip").position[0], [0.5, 0.5, 0.0], atol=1e-6)


class _SwingingRope:
    """A stand-in for ``motioncapture``'s connection: 200 Hz point clouds of a rope hanging from
    (0, 0, 2) whose free end swings with amplitude ``amp(t)`` [m] at 3.6 rad/s."""

    def __init__(self, amp):
        self.amp, self.t0 = amp, time.perf_counter()
        self.pointCloud, self.rigidBodies = np.zeros((0, 3)), {}

    def waitForNextFrame(self):
        time.sleep(0.005)
        t = time.perf_counter() - self.t0
        from flyknot_hw.mocap import hanging_markers

        pts = hanging_markers(np.array([0.0, 0.0, 2.0]))
        pts[:, 0] += self.amp(t) * np.sin(3.6 * t) * np.arange(1, 12) / 11
        self.pointCloud = pts + np.random.default_rng().normal(0, 5e-4, pts.shape)


@pytest.mark.parametrize("settles", [True, False])
def test_the_markers_settle_check_waits_for_the_free_end(settles):
    from flyknot_hw.mocap import MarkerSettle, MotioncaptureSource

    amp = (lambda t: 0.05 * np.exp(-t / 0.4)) if settles else (lambda t: 0.05)
    src = MotioncaptureSource("mock", connect=lambda kind, cfg: _SwingingRope(amp))
    check = MarkerSettle(src, lambda: np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, -1.0]),
                         timeout_s=4.0)  # fmt: skip
    t = time.perf_counter()
    if settles:
        out = check("before")
        waited = time.perf_counter() - t
        assert 1.3 < waited < 4.0 and out["rest"]["free_end_speed_m_s"] < 0.03
        assert not src.recording  # started for the check, stopped after it
    else:
        with pytest.raises(HardwareError, match=r"settle\.timeout_s: the rope did not come"):
            check("after")


def test_a_trial_without_its_recording_keeps_its_joints(make_fake, cells, tmp_path):
    from flyknot_hw.mocap import RecordedFileSource

    fk = make_fake(arm="exact")
    src = RecordedFileSource(tmp_path, pattern="trial_*.c3d", wait_s=0.3, poll_s=0.05)
    rec = cells(fk, mocap=src).run(JointCommand(throw(60)))
    assert rec.fault is None and np.all(np.isfinite(rec.q_meas)) and rec.knot == "trefoil"
    assert rec.t_marker.shape == (0,) and rec.markers.shape == (0, 11, 3)
    assert rec.metadata["mocap"]["error"].startswith("no recording: no finished recording")


def test_parallel_first_imports_of_the_sdk_do_not_race(tmp_path):
    """On a machine without the SDK's log directory, eight processes importing it at once all
    succeed (the SDK alone creates it without exist_ok: a FileExistsError in the losers)."""
    code = "from flyknot_hw.xarm_sdk import sdk_version; print(sdk_version())"
    env = {**os.environ, "HOME": str(tmp_path)}
    procs = [
        subprocess.Popen([sys.executable, "-c", code], env=env, stderr=subprocess.PIPE, text=True)
        for _ in range(8)
    ]
    errors = [p.communicate()[1] for p in procs if p.wait() != 0]
    assert errors == []
    assert (tmp_path / ".UFACTORY" / "log" / "xarm" / "sdk").is_dir()


@pytest.mark.parametrize(
    ("typed", "answer"),
    [
        ("k", "knot"),
        ("W", "wrapped"),
        ("f", "floor"),
        ("floor", "floor"),
        ("n", "none"),
        ("?", None),
    ],
)
def test_the_operator_answers_at_the_console(monkeypatch, typed, answer):
    from flyknot.verdict import operator_verdict
    from flyknot_hw.xarm_cell import console_ask

    monkeypatch.setattr("builtins.input", lambda prompt: typed)
    assert console_ask(None, None) == answer
    if answer is not None:  # every answer the console gives is one the judge takes
        assert operator_verdict(answer).success is (answer == "knot")
