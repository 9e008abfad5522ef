"""Offscreen rendering, trajectories, side-by-side frames and video files.

Tests that draw with OpenGL skip (with the reason) when no backend works on
the machine; file writing and frame arithmetic are tested everywhere.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from jaxsync._errors import ConfigError, JaxsyncError
from jaxsync.io import render
from jaxsync.io import video as _video
from jaxsync.runtime import gl as _gl

W, H = 160, 120


@pytest.fixture(scope="module")
def gl():
    try:
        return render.select_gl_backend()
    except render.RenderUnavailableError as err:
        pytest.skip(str(err))


@pytest.fixture(scope="module")
def traj(model):
    """1 s at 50 Hz (51 states) from the approach keyframe to the grasp keyframe."""
    a, g = model.keyframe_qpos("approach"), model.keyframe_qpos("grasp")
    s = np.linspace(0.0, 1.0, 51)[:, None]
    return (1 - s) * a + s * g, 0.02


def _green_mask(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return (g > r + 40) & (g > b + 40)


# ----------------------------------------------------------------------------- needs OpenGL


def test_render_pose_size_and_content(gl, model):
    img = render.render_pose(model.mj_model, model.keyframe_qpos("grasp"), width=W, height=H)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    colours = np.unique(img.reshape(-1, 3), axis=0)
    assert len(colours) > 100, "image is (nearly) blank"
    green = _green_mask(img)
    centre = green[H // 5 : 4 * H // 5, W // 5 : 4 * W // 5]
    assert centre.sum() > 50, "the green object is not near the image centre"
    assert green.sum() - centre.sum() < 0.1 * green.sum()


def test_render_pose_named_camera_and_bad_qpos(gl, model):
    img = render.render_pose(model.mj_model, model.keyframe_qpos("grasp"), W, H, camera="overview")
    assert img.shape == (H, W, 3) and len(np.unique(img.reshape(-1, 3), axis=0)) > 100
    with pytest.raises(ConfigError):
        render.render_pose(model.mj_model, np.zeros(3), W, H)
    with pytest.raises(ConfigError):
        render.render_pose(model.mj_model, model.keyframe_qpos("grasp"), 5000, 100)


@pytest.mark.parametrize("speed, expected", [(1.0, 11), (2.0, 6), (0.5, 21)])
def test_render_trajectory_frame_count(gl, model, traj, speed, expected):
    qpos, dt = traj
    frames = render.render_trajectory(model.mj_model, qpos, fps_out=10, sim_dt=dt, speed=speed, width=W, height=H)
    assert len(frames) == expected  # 1 s shown at 10 frames per second, sped up or slowed down
    assert all(f.shape == (H, W, 3) and f.dtype == np.uint8 for f in frames)
    assert not np.array_equal(frames[0], frames[-1])  # the arms moved


def test_render_trajectory_force_overlay(gl, model, traj):
    qpos, dt = traj
    T = qpos.shape[0]
    forces = np.zeros((T, 2, 3))
    forces[:, 0, 1], forces[:, 1, 1] = 10.0, -10.0  # each pad pushes the ball towards the other
    points = np.broadcast_to(np.array([[0.65, -0.1, 0.9], [0.65, 0.1, 0.9]]), (T, 2, 3))
    plain = render.render_trajectory(model.mj_model, qpos, 10, dt, 5.0, width=W, height=H)
    drawn = render.render_trajectory(model.mj_model, qpos, 10, dt, 5.0, width=W, height=H, forces=forces, points=points)
    assert len(drawn) == len(plain) == 3  # speed 5: t = 0, 0.5, 1 s
    assert (np.abs(drawn[-1].astype(int) - plain[-1].astype(int)).sum(-1) > 30).sum() > 100
    via_overlay = render.render_trajectory(
        model.mj_model, qpos, 10, dt, 5.0, width=W, height=H, overlay=render.ForceOverlay(forces, points)
    )
    assert np.array_equal(via_overlay[-1], drawn[-1])
    with pytest.raises(ConfigError):
        render.render_trajectory(model.mj_model, qpos, 10, dt, width=W, height=H, forces=forces[:3], points=points[:3])


def test_side_by_side(gl, model, traj):
    qpos, dt = traj
    a = render.render_trajectory(model.mj_model, qpos, 10, dt, width=W, height=H)
    b = render.render_trajectory(model.mj_model, qpos[:26], 10, dt, width=W, height=H)
    out = render.side_by_side(a, b, gap=4)
    assert len(out) == len(a) == 11 and len(b) == 6
    assert out[0].shape == (H, 2 * W + 4, 3)
    assert np.array_equal(out[-1][: H // 2, W + 4 :], b[-1][: H // 2])  # b holds its last frame (label below)
    assert np.array_equal(out[0][: H // 2, :W], a[0][: H // 2])


# ----------------------------------------------------------------------------- no OpenGL needed


def test_frame_indices():
    # 51 states 0.02 s apart = 1 s: 10 fps gives 11 frames at 0, 0.1, ..., 1.0 s.
    np.testing.assert_array_equal(render.frame_indices(51, 10, 0.02), np.arange(0, 51, 5))
    np.testing.assert_array_equal(render.frame_indices(51, 10, 0.02, speed=2.0), np.arange(0, 51, 10))
    assert len(render.frame_indices(1, 30, 0.002)) == 1
    assert len(render.frame_indices(1001, 30, 0.002, speed=0.25)) == 1 + int(2.0 * 30 / 0.25)
    with pytest.raises(ConfigError):
        render.frame_indices(10, 0, 0.01)


def _frames(n: int, w: int = 64, h: int = 48) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(n)]


def test_write_gif_frame_count(tmp_path):
    frames = _frames(7)
    path = render.write_video(frames, tmp_path / "clip.gif", fps=30)
    assert path == str(tmp_path / "clip.gif")
    with Image.open(path) as im:
        assert im.n_frames == 7
        assert im.size == (64, 48)
    assert os.listdir(tmp_path) == ["clip.gif"]  # no temporary file left behind


def test_write_video_falls_back_to_gif(tmp_path, monkeypatch):
    monkeypatch.setattr(_video, "mp4_available", lambda: False)
    path = render.write_video(_frames(5), tmp_path / "clip.mp4", fps=10)
    assert path == str(tmp_path / "clip.gif")
    with Image.open(path) as im:
        assert im.n_frames == 5


def test_write_mp4_frame_count(tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="MP4 needs imageio-ffmpeg")
    path = render.write_video(_frames(9, 65, 47), tmp_path / "clip.mp4", fps=10)  # odd sizes get padded
    assert path == str(tmp_path / "clip.mp4")
    nframes, _ = imageio_ffmpeg.count_frames_and_secs(path)
    assert nframes == 9


def test_write_video_rejects_bad_input(tmp_path):
    with pytest.raises(ConfigError):
        render.write_video([], tmp_path / "x.gif", 10)
    with pytest.raises(ConfigError):
        render.write_video(_frames(2, 10, 10) + _frames(1, 12, 10), tmp_path / "x.gif", 10)


def test_save_png_atomic(tmp_path):
    img = _frames(1)[0]
    path = render.save_png(img, tmp_path / "sub" / "a.png")
    with Image.open(path) as im:
        np.testing.assert_array_equal(np.asarray(im), img)
    assert os.listdir(tmp_path / "sub") == ["a.png"]


def test_no_backend_error_names_what_was_tried(monkeypatch):
    tried = []

    def fake_probe(backend, timeout=0):
        tried.append(backend)
        return False, "no display"

    monkeypatch.setattr(_gl, "_selected_backend", None)
    monkeypatch.setattr(_gl, "_failure", None)
    monkeypatch.setattr(_gl, "_probe_backend", fake_probe)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    with pytest.raises(render.RenderUnavailableError) as err:
        render.select_gl_backend()
    assert isinstance(err.value, JaxsyncError)
    assert tried == ["egl", "osmesa"]
    msg = str(err.value)
    assert "MUJOCO_GL=egl" in msg and "MUJOCO_GL=osmesa" in msg and "apt-get install" in msg
    assert "libegl1" in msg and "libopengl0" in msg and "libosmesa6" in msg
    with pytest.raises(render.RenderUnavailableError):  # the failure is remembered, not probed again
        render.select_gl_backend()
    assert tried == ["egl", "osmesa"]


def test_existing_mujoco_gl_is_respected(monkeypatch):
    tried, activated = [], []
    monkeypatch.setattr(_gl, "_selected_backend", None)
    monkeypatch.setattr(_gl, "_failure", None)
    monkeypatch.setattr(_gl, "_probe_backend", lambda b, timeout=0: (tried.append(b), (True, ""))[1])
    monkeypatch.setattr(_gl, "_activate", activated.append)
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    assert render.select_gl_backend() == "osmesa"
    assert tried == ["osmesa"] and activated == ["osmesa"]


def test_a_mujoco_gl_that_cannot_load_breaks_only_rendering(tmp_path):
    """MUJOCO_GL naming a backend MuJoCo does not know (or one not installed)
    breaks neither ``import mujoco`` nor the commands that do not render: only
    the render commands need OpenGL, and they say what to set and install (one
    line, exit 2, no folder created); --help and info work. One interpreter."""
    code = """
import sys
from jaxsync.cli import main
try:
    main(["--help"])
except SystemExit as exit_:
    print("help:", exit_.code)
print("info:", main(["info"]))
print("render:", main(["render", "--out", sys.argv[1]]))
print("video:", main(["compare", "--video", "--out", sys.argv[2]]))
"""
    out = tmp_path / "r"
    env = dict(os.environ, MUJOCO_GL="bogus", JAXSYNC_CACHE_DIR="off")
    env.pop("PYOPENGL_PLATFORM", None)
    proc = subprocess.run(
        [sys.executable, "-c", code, str(out), str(tmp_path / "c")],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=300,
    )
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert "help: 0" in proc.stdout and "usage: jaxsync" in proc.stdout
    assert "info: 0" in proc.stdout and "joints_per_arm" in proc.stdout
    assert "render: 2" in proc.stdout and "video: 2" in proc.stdout  # the video: before any rollout
    errors = proc.stderr.strip().splitlines()
    assert len(errors) == 2, errors
    for line in errors:
        assert "MUJOCO_GL=bogus" in line and "apt-get install -y libegl1" in line, line
    assert not out.exists() and not (tmp_path / "c").exists()


def test_mujoco_gl_names_a_backend_module():
    """The backend the first Renderer loads (import_mujoco defers it), as MuJoCo picks it."""
    assert _gl._backend_module("egl") == "mujoco.egl" and _gl._backend_module("") == "mujoco.glfw"
    with pytest.raises(render.RenderUnavailableError, match="apt-get install -y libegl1"):
        _gl._backend_module("bogus")
