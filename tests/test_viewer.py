"""The trial viewer: frames are right, and the server builds the scene on loopback."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from flyknot_app.viewer import build_scene, trial_frames
from flyknot_sim.commands import swing_command
from flyknot_sim.lab import LabParams, SimLab


@pytest.fixture(scope="module")
def record():
    return SimLab(LabParams(rope=1, settle_s=0.1)).run(
        swing_command(duration=0.3, amplitude=np.full(7, 0.1))
    )


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


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_server_builds_the_scene_on_loopback(record):
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        draw, slider, play = build_scene(server, record, trial_frames(record))
        draw(3)
        assert slider.max == pytest.approx(trial_frames(record)["t"][-1])
        assert play.value is False
    finally:
        server.stop()
