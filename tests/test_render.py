"""Offscreen renders of a trial (``flyknot render``): MuJoCo on EGL, no display."""

from __future__ import annotations

import dataclasses

import imageio.v2 as imageio
import numpy as np
import pytest

from flyknot.errors import ConfigError
from flyknot_app.cli import main
from flyknot_app.viewer.render import (
    SUFFIXES,
    RenderParams,
    TrialRenderer,
    frame_times,
    render_trial,
    trial_end,
)
from flyknot_sim.commands import swing_command
from flyknot_sim.lab import LabParams, SimLab

SMALL = RenderParams(width=160, height=120, fps=20.0)


@pytest.fixture(scope="module")
def record():
    return SimLab(LabParams(rope=1, settle_s=0.1)).run(
        swing_command(duration=0.3, amplitude=np.full(7, 0.1))
    )


@pytest.fixture(scope="module")
def stem(record, tmp_path_factory):
    path = tmp_path_factory.mktemp("render") / "trial"
    record.save(path)
    return path


def _orange(image: np.ndarray) -> int:
    """Pixels of the rope's hue (orange: red high, green middling, blue low)."""
    r, g, b = (image[..., i].astype(int) for i in range(3))
    return int(((r > 120) & (g > 0.45 * r) & (g < 0.85 * r) & (b < 0.45 * r)).sum())


def test_a_png_of_a_record_shows_the_arm_and_the_rope(egl, stem, tmp_path, capsys):
    out = tmp_path / "figs" / "trial.png"
    assert main(["render", str(stem), "--out", str(out), "--width", "320", "--height", "240"]) == 0
    assert str(out) in capsys.readouterr().out
    image = imageio.imread(out)
    assert image.shape == (240, 320, 3)
    assert image.std() > 20.0
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 200
    assert _orange(image) > 50  # the rope's capsules


def test_the_arm_is_posed_from_the_measured_joints(egl, record):
    moved = dataclasses.replace(record, q_meas=record.q_meas + np.array([0.6, 0, 0, 0, 0, 0, 0]))
    t = trial_end(record)
    with TrialRenderer(record, SMALL) as a:
        img_a = a.render(t)
        again = a.render(t)
    with TrialRenderer(moved, SMALL) as b:
        b.camera = a.camera  # the same view (the framing follows the arm)
        img_b = b.render(t)
    np.testing.assert_array_equal(img_a, again)  # deterministic
    differ = np.any(img_a != img_b, axis=-1)
    assert differ.mean() > 0.01  # the arm turned by 0.6 rad about joint 1
    assert not np.all(differ)  # the floor, pedestal and rope did not move


def test_without_truth_the_rope_follows_the_markers(egl, record):
    bare = dataclasses.replace(record, truth={})
    with TrialRenderer(bare, SMALL) as r:
        assert not r.has_truth
        rope = r.rope_at(0.2)
        np.testing.assert_array_equal(rope, r.markers_at(0.2))
        assert rope.shape == (11, 3)
        assert _orange(r.render(0.2)) > 5


def test_an_mp4_has_a_frame_per_step_through_the_trial(egl, stem, tmp_path, record):
    out = render_trial(stem, tmp_path / "trial.mp4", params=SMALL)
    reader = imageio.get_reader(out)
    try:
        frames = [f for f in reader]
        fps = reader.get_meta_data()["fps"]
    finally:
        reader.close()
    expected = frame_times(record, SMALL.fps).size
    assert expected == int(np.floor(trial_end(record) * SMALL.fps + 1e-9)) + 1
    assert len(frames) == expected
    assert fps == pytest.approx(SMALL.fps)
    assert frames[0].shape == (SMALL.height, SMALL.width, 3)
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).mean() > 0.1  # it moves


def test_bad_requests_name_the_flag(stem, tmp_path, capsys):
    with pytest.raises(ConfigError) as e:
        render_trial(stem, tmp_path / "trial.gif")
    assert e.value.field == "--out" and e.value.choices == list(SUFFIXES) == [".png", ".mp4"]
    assert not (tmp_path / "trial.gif").exists()
    with pytest.raises(ConfigError, match="--time"):
        render_trial(stem, tmp_path / "late.png", time=99.0, params=SMALL)
    with pytest.raises(ConfigError, match="--time"):
        render_trial(stem, tmp_path / "clip.mp4", time=0.1, params=SMALL)
    with pytest.raises(ConfigError, match="--width"):
        render_trial(stem, tmp_path / "odd.mp4", params=RenderParams(width=161, height=120))
    with pytest.raises(ConfigError, match="--fps"):
        RenderParams(fps=0.0)
    # through the command line: one line naming the flag and the choices, exit 2
    assert main(["render", str(stem), "--out", str(tmp_path / "x.jpg")]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and ".png, .mp4" in err


def test_a_renderer_bound_again_draws_what_a_new_one_draws(egl, record):
    from flyknot_app.viewer.render import RendererCache

    moved = dataclasses.replace(record, q_meas=record.q_meas + np.array([0.6, 0, 0, 0, 0, 0, 0]))
    bare = dataclasses.replace(moved, truth={})
    views = [
        (record, SMALL),
        (moved, dataclasses.replace(SMALL, show_arm=False)),
        (bare, dataclasses.replace(SMALL, close_up=True)),
        (record, dataclasses.replace(SMALL, focus=(3, 9))),
    ]
    t = trial_end(record)
    with RendererCache() as cache:
        again = [cache.get(rec, params).render(t, "caption") for rec, params in views]
        assert len(cache._open) == 1  # one scene and image size: one renderer
    for (rec, params), img in zip(views, again, strict=True):
        with TrialRenderer(rec, params) as fresh:
            np.testing.assert_array_equal(img, fresh.render(t, "caption"))


@pytest.mark.parametrize("close_up", [False, True])
def test_the_skipped_shadow_and_reflection_passes_would_draw_nothing(egl, record, close_up):
    import mujoco

    params = dataclasses.replace(SMALL, width=320, height=240, close_up=close_up)
    t = trial_end(record)
    passes = (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION)
    with TrialRenderer(record, params) as r:
        assert not any(r.scene.flags[flag] for flag in passes)  # skipped: they cost, not show
        plain = r.render(t)
        for flag in passes:
            r.scene.flags[flag] = True
        np.testing.assert_array_equal(r.render(t), plain)


def test_a_renderer_names_what_it_cannot_draw(egl, record):
    raised = dataclasses.replace(record, base_pose=np.r_[0.0, 0.0, 1.4, 1.0, 0.0, 0.0, 0.0])
    with TrialRenderer(record, SMALL) as r:
        assert not r.fits(raised, SMALL)
        assert not r.fits(record, dataclasses.replace(SMALL, width=200))
        with pytest.raises(ConfigError) as err:
            r.view(raised, SMALL)
    assert str(err.value) == (
        "record: needs a renderer for pedestal 1.4 m and 160x120 px; this one draws 1 m and "
        "160x120 px"
    )


FORK_AFTER_RENDER = """
import multiprocessing, sys
from flyknot.record import TrialRecord
from flyknot_app.viewer.render import RenderParams, TrialRenderer

def draw():
    record = TrialRecord.load(sys.argv[1])
    with TrialRenderer(record, RenderParams(width=160, height=120)) as r:
        return float(r.render(0.1).mean())

def child():
    sys.exit(0 if draw() > 0 else 3)

if __name__ == "__main__":
    assert draw() > 0
    p = multiprocessing.get_context("fork").Process(target=child)
    p.start()
    p.join(60)
    if p.is_alive():
        p.kill()
        sys.exit("the forked child hung in its first render")
    sys.exit(p.exitcode)
"""


def test_a_process_forked_after_a_render_draws(egl, stem, tmp_path):
    # A run pool's worker is forked from a process that may have drawn already (the report of
    # an earlier scenario): with Mesa's rasteriser on threads it would hang in its first
    # render; the renderer's context keeps it on the calling thread unless the user says.
    import os
    import subprocess
    import sys

    script = tmp_path / "fork_after_render.py"
    script.write_text(FORK_AFTER_RENDER)
    env = {k: v for k, v in os.environ.items() if k != "LP_NUM_THREADS"}
    done = subprocess.run(
        [sys.executable, str(script), str(stem)],
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert done.returncode == 0, done.stderr[-2000:]
