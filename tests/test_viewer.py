"""The trial viewer: frames, a run directory's trials and targets, and the page in Chromium.

The browser test drives Debian's Chromium (``/usr/bin/chromium``) through its chromedriver
(``/usr/bin/chromedriver``) with Selenium; nothing is downloaded (Selenium Manager is never
asked: both paths are given). Without them it is skipped, naming what is missing; under
``CI=true`` it fails (``tests/system_needs.py``).
"""

from __future__ import annotations

import json
import socket
import tempfile
import time

import numpy as np
import pytest

from flyknot.errors import ConfigError
from flyknot.record import TrialRecord
from flyknot_app.viewer.server import COLOURS, NODES, RunViewer, start, trial_frames
from flyknot_app.viewer.trials import (
    TargetCache,
    base_offset,
    demo_to_lab,
    find_view_trials,
    markers_at,
)
from flyknot_sim.commands import swing_command
from flyknot_sim.lab import LabParams, SimLab
from learner.critical_state import critical_state_from_record
from tests.system_needs import CHROMEDRIVER, CHROMIUM

CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    # WebGL on SwiftShader (software), opted in: Chromium 150 no longer falls back silently.
    "--enable-unsafe-swiftshader",
    "--window-size=1000,760",
)


@pytest.fixture(scope="module")
def record():
    return SimLab(LabParams(rope=1, settle_s=0.1)).run(
        swing_command(duration=0.3, amplitude=np.full(7, 0.1))
    )


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A real ``flyknot run`` directory at the smallest size: the quick scenario's run, one
    learning trial from a still arm at home (no trajectory optimisation), one repeat."""
    from flyknot_app.runner import execute_run
    from flyknot_app.scenario import load_scenario, parse_overrides
    from learner.initial_guess_params import HOME_Q

    scen = load_scenario("quick", parse_overrides(["max_trials=1", "settle_s=0.1", "repeats=1"]))
    knots0 = np.zeros((10, 8))
    knots0[:7] = np.asarray(HOME_Q)[:, None]
    knots0[7:] = np.array([0.2, 0.5, 0.3])[:, None]
    out = tmp_path_factory.mktemp("view_run")
    execute_run(scen.runs[0], out, knots0, resume=False, progress=False)
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_frames_follow_the_record(record):
    f = trial_frames(record, rate_hz=50)
    k = f["t"].size
    assert f["robot"].shape == (k, 9, 3) and f["markers"].shape == (k, 11, 3)
    assert f["rope"].shape[0] == k and f["rope"].shape[1] > 11
    # the drawn fingertip is the recorded one (same clock, joint-rate sample)
    i = np.searchsorted(record.t_joint, f["t"][5])
    np.testing.assert_allclose(f["robot"][5, -1], record.fingertip_pos[i], atol=1e-9)
    # the robot base sits on the pedestal
    np.testing.assert_allclose(f["robot"][0, 0], record.base_pose[:3], atol=1e-12)


def test_a_run_directory_lists_its_trials_with_the_runs_t_c(run_dir, record, tmp_path):
    result = json.loads((run_dir / "runs" / "rope1" / "result.json").read_text())
    trials = find_view_trials(run_dir)
    assert [t.name for t in trials] == [
        "runs/rope1/learning/trial_0000_a0",
        "runs/rope1/repeats/repeat_000",
    ]
    assert all(t.t_c == pytest.approx(result["t_c"]) for t in trials)
    # one record of the run, given by its stem: the same trial and t_c
    (one,) = find_view_trials(run_dir / "runs" / "rope1" / "learning" / "trial_0000_a0")
    assert one.path == trials[0].path and one.t_c == pytest.approx(result["t_c"])
    # a record outside a run has no t_c
    record.save(tmp_path / "alone" / "trial")
    (alone,) = find_view_trials(tmp_path / "alone" / "trial.npz")
    assert alone.t_c is None and base_offset(alone.path) is None
    with pytest.raises(ConfigError, match="PATH"):
        find_view_trials(tmp_path / "nothing_here")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="no trial records"):
        find_view_trials(tmp_path / "empty")


def test_the_target_is_the_learners_demonstration_state_at_t_c(run_dir):
    """Drawn target, taken back to the demonstration frame, equals what the learner compared
    the trial with: x_meas(t_c) - err of the run's update file."""
    trial = find_view_trials(run_dir)[0]
    rec = TrialRecord.load(trial.path, with_truth=True)
    update = json.loads((trial.path.parent / "update_0000.json").read_text())
    assert update["t_eff"] == pytest.approx(trial.t_c)  # the update used t_c itself
    b = base_offset(trial.path)
    np.testing.assert_allclose(b, np.load(trial.path.parent / "knots_0000.npy")[7:, 0])
    x_meas = critical_state_from_record(rec, trial.t_c, b)
    x_demo = x_meas - np.asarray(update["err"])
    target = TargetCache().target_in_lab(trial, rec)
    np.testing.assert_allclose(
        target, demo_to_lab(x_demo[:33].reshape(11, 3), rec.base_pose, b), atol=1e-9
    )
    # the measured markers at t_c are near the learner's fitted ones (noise, 5 ms sampling)
    crit = markers_at(rec, trial.t_c)
    assert crit.shape == (11, 3)
    fitted = demo_to_lab(x_meas[:33].reshape(11, 3), rec.base_pose, b)
    np.testing.assert_allclose(crit, fitted, atol=0.05)


def test_the_viewer_switches_trials_and_jumps_to_t_c(run_dir):
    import viser

    trials = find_view_trials(run_dir)
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        viewer = RunViewer(server, trials)
        for name in NODES:
            assert server.scene.get_handle_by_name(name) is not None, name
        assert viewer.slider.max == pytest.approx(viewer.frames["t"][-1])
        assert viewer.target is not None and viewer.target.shape == (11, 3)
        first_target = viewer.target
        viewer.selector.value = trials[1].name  # the repeat: final_knots' base offset
        assert viewer.index == 1 and viewer.record.metadata["trial_index"] == 1
        assert viewer.target is not None
        assert not np.allclose(viewer.target, first_target)  # the command moved its base
        viewer.to_t_c.value = True  # a click
        assert viewer.slider.value == pytest.approx(trials[1].t_c, abs=1 / viewer.rate_hz)
        viewer.play.value = True
        before = viewer.slider.value
        viewer.step()
        assert viewer.slider.value == pytest.approx(before + 1 / viewer.rate_hz)
    finally:
        server.stop()


def test_a_record_outside_a_run_has_no_target_nodes(record, tmp_path):
    record.save(tmp_path / "trial")
    server, viewer = start(tmp_path / "trial", port=_free_port())
    try:
        assert viewer.target is None and viewer.to_t_c.disabled
        assert server.scene.get_handle_by_name("/target_rope") is None
        assert server.scene.get_handle_by_name("/critical") is None
        assert server.scene.get_handle_by_name("/robot") is not None
    finally:
        server.stop()


def _chromium():
    """Headless Chromium, the system's, driven by the system's chromedriver."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    profile = tempfile.TemporaryDirectory(prefix="flyknot-chromium-")
    options.add_argument(f"--user-data-dir={profile.name}")
    driver = webdriver.Chrome(service=Service(executable_path=str(CHROMEDRIVER)), options=options)
    return driver, profile


def _wait(condition, timeout: float, what):
    """Poll ``condition`` until truthy; ``what`` (text, or a function giving it) on timeout."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    what = what() if callable(what) else what
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _near(image: np.ndarray, rgb: tuple[int, int, int], tol: int = 40) -> int:
    """Pixels of ``image`` within ``tol`` of colour ``rgb`` in every channel."""
    return int(np.all(np.abs(image[..., :3].astype(int) - rgb) <= tol, axis=-1).sum())


def test_the_page_renders_the_run_in_headless_chromium(chromium, run_dir, tmp_path):
    import imageio.v3 as iio
    from selenium.webdriver.common.by import By

    port = _free_port()
    server, viewer = start(run_dir, port=port)
    driver = profile = None
    try:
        driver, profile = _chromium()
        driver.get(f"http://127.0.0.1:{port}/")
        clients = _wait(server.get_clients, 30, "the page's websocket client")
        client = next(iter(clients.values()))
        for name in NODES:  # the server's scene, which every client receives
            assert server.scene.get_handle_by_name(name) is not None, name
        # the browser drew every node with WebGL: the client's own canvas (no GUI on it)
        # shows each node's colour once the page's camera has moved to the server's framing
        drawn = ("/robot", "/rope", "/markers", "/target_rope", "/critical")

        seen: dict[str, int] = {}

        def canvas_shows_every_node():
            image = client.get_render(540, 720, transport_format="png", timeout=30)
            seen.update({n: _near(image, COLOURS[n.lstrip("/")]) for n in drawn})
            return min(seen.values()) > 30

        _wait(canvas_shows_every_node, 60, lambda: f"the canvas to show each node (pixels: {seen})")
        # a click on the page's button moves the server's slider to t_c
        driver.find_element(By.XPATH, "//button[contains(., 'go to t_c')]").click()
        t_c = viewer.trials[viewer.index].t_c
        _wait(lambda: abs(viewer.slider.value - t_c) < 1.5 / viewer.rate_hz, 10, "t_c")
        shot = tmp_path / "page.png"
        assert driver.save_screenshot(str(shot))
        image = iio.imread(shot)[..., :3]
        assert image.std() > 10.0
        assert len(np.unique(image.reshape(-1, 3), axis=0)) > 50
        assert _near(image, COLOURS["target_rope"]) > 20
    finally:
        if driver is not None:
            driver.quit()
        if profile is not None:
            profile.cleanup()
        server.stop()
