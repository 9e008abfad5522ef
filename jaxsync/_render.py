"""Pictures and videos of the robot and of rollouts (headless, offscreen).

MuJoCo's ``mujoco.Renderer`` needs an OpenGL context. On a machine without a
GPU or a display, that is EGL (Mesa's software renderer, llvmpipe) or OSMesa.
MuJoCo picks the backend from the ``MUJOCO_GL`` environment variable when
``mujoco`` is first imported; :func:`select_gl_backend` chooses one that works
(probing each in a subprocess, so a failing backend cannot break this
process) and, if ``mujoco`` was already imported, switches its context class
so that the next ``Renderer`` uses the chosen backend. See docs/rendering.md.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import os
import subprocess
import sys
import warnings
from collections.abc import Sequence

import numpy as np

from jaxsync import _io
from jaxsync._errors import ConfigError, JaxsyncError

# Tried in this order when MUJOCO_GL is not set: both work without a display.
GL_BACKENDS = ("egl", "osmesa")

# Debian packages that provide each backend (MuJoCo loads them through PyOpenGL).
SYSTEM_PACKAGES = {
    "egl": ("libegl1", "libegl-mesa0", "libgl1-mesa-dri", "libopengl0"),
    "osmesa": ("libosmesa6",),
}

# The default view: a free camera in front of the robot, a little to its right
# and above the object, aimed between the shoulders and the object. It shows
# the torso, both arms, both pads and the clamped ball (which lands near the
# image centre); the pads clamp along world y, across the image.
DEFAULT_CAMERA = {"lookat": (0.45, 0.0, 1.05), "distance": 1.95, "azimuth": 150.0, "elevation": -15.0}

# Geom groups drawn: 0-2 (MuJoCo's defaults); group 3 holds the hidden pad
# collision spheres.
VISIBLE_GEOM_GROUPS = (0, 1, 2)

# Force arrows: metres of arrow per newton, and colours (RGBA) per pad in the
# order (right, left): the colour of each arm's elbow and wrist, brightened.
FORCE_SCALE = 0.01
FORCE_COLORS = ((0.15, 0.45, 1.0, 1.0), (1.0, 0.35, 0.1, 1.0))
FORCE_ARROW_WIDTH = 0.02
# The object is drawn see-through under a force overlay, so that arrows that
# point into it (the force of each pad on the object) stay visible.
OVERLAY_OBJECT_ALPHA = 0.3


# Shadow-map size cap. MuJoCo's default (4096) costs ~0.25 s a frame in software
# rendering (llvmpipe); 2048 looks the same here at 960x720 and is ~5x faster.
# (1024 shows shadow acne on the torso.) Applied to a copy of the model.
MAX_SHADOW_SIZE = 2048


class RenderUnavailableError(JaxsyncError):
    """No OpenGL backend for offscreen rendering works on this machine."""


_selected_backend: str | None = None
_failure: tuple[str, str] | None = None  # (MUJOCO_GL at the time, message): not probed twice

_PROBE = """
import mujoco
m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size="0.1"/></worldbody></mujoco>')
d = mujoco.MjData(m)
mujoco.mj_forward(m, d)
r = mujoco.Renderer(m, 8, 8)
r.update_scene(d)
img = r.render()
r.close()
assert img.shape == (8, 8, 3), img.shape
print("ok")
"""


def _probe_backend(backend: str, timeout: float = 120.0) -> tuple[bool, str]:
    """Render one tiny frame with MUJOCO_GL=backend in a fresh interpreter."""
    env = dict(os.environ)
    env["MUJOCO_GL"] = backend
    env.pop("PYOPENGL_PLATFORM", None)
    if backend in ("egl", "osmesa"):
        env["PYOPENGL_PLATFORM"] = backend
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
            close_fds=False,  # lets Python use posix_spawn instead of fork (JAX warns on fork)
        )
    except (OSError, subprocess.TimeoutExpired) as err:
        return False, f"{type(err).__name__}: {err}"
    if proc.returncode == 0 and proc.stdout.strip().endswith("ok"):
        return True, ""
    lines = [ln for ln in (proc.stderr or proc.stdout).strip().splitlines() if ln.strip()]
    return False, lines[-1] if lines else f"exit code {proc.returncode}"


def _activate(backend: str) -> None:
    """Make this process's next mujoco.Renderer use ``backend``."""
    os.environ["MUJOCO_GL"] = backend
    if "mujoco" not in sys.modules:
        return  # mujoco reads MUJOCO_GL when it is imported
    gl_context = importlib.import_module("mujoco.rendering.classic.gl_context")
    if getattr(gl_context, "_MUJOCO_GL", None) == backend:
        return  # mujoco was imported with this backend already
    if backend not in GL_BACKENDS:
        raise RenderUnavailableError(
            f"mujoco was imported before MUJOCO_GL={backend} was set; set it before starting Python"
        )
    platform = os.environ.get("PYOPENGL_PLATFORM", "").lower()
    if "OpenGL" in sys.modules and platform != backend:
        raise RenderUnavailableError(
            f"PyOpenGL was already imported for platform {platform or 'default'!r}, so the {backend} "
            f"backend cannot be switched to; run with MUJOCO_GL={backend} set before starting Python"
        )
    try:
        module = importlib.import_module(f"mujoco.{backend}")
    except ImportError as err:
        raise RenderUnavailableError(f"cannot switch mujoco to MUJOCO_GL={backend}: {err}") from None
    gl_context.GLContext = module.GLContext


def select_gl_backend() -> str:
    """Choose a working OpenGL backend for offscreen rendering and activate it.

    Respects an existing ``MUJOCO_GL`` (checked, not replaced); otherwise tries
    ``egl`` then ``osmesa``, each by rendering a tiny frame in a subprocess.
    The choice is cached for the process. Call it before rendering; the
    rendering functions here call it themselves.

    Returns:
      The backend name, as put in ``os.environ["MUJOCO_GL"]``.

    Raises:
      RenderUnavailableError: no backend works; the message names what was
        tried, why each failed, and the Debian packages to install.
    """
    global _selected_backend, _failure
    if _selected_backend is not None:
        return _selected_backend
    requested = os.environ.get("MUJOCO_GL", "").strip().lower()
    if _failure is not None and _failure[0] == requested:
        raise RenderUnavailableError(_failure[1])
    candidates = (requested,) if requested else GL_BACKENDS
    failures = []
    for backend in candidates:
        ok, why = _probe_backend(backend)
        if ok:
            _activate(backend)
            _selected_backend = backend
            return backend
        failures.append(f"MUJOCO_GL={backend}: {why}")
    packages = " ".join(p for b in GL_BACKENDS for p in SYSTEM_PACKAGES[b])
    hint = f"unset MUJOCO_GL to let jaxsync try {' and '.join(GL_BACKENDS)}, or " if requested else ""
    message = (
        "no OpenGL backend for offscreen rendering works here (tried "
        + "; ".join(failures)
        + f"). {hint}install the system libraries, e.g. on Debian/Ubuntu: "
        f"apt-get install -y {packages}"
    )
    _failure = (requested, message)
    raise RenderUnavailableError(message)


# --------------------------------------------------------------------------- cameras and scenes


def default_camera():
    """The default free camera (see ``DEFAULT_CAMERA``) as a ``mujoco.MjvCamera``."""
    import mujoco

    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = DEFAULT_CAMERA["lookat"]
    cam.distance = DEFAULT_CAMERA["distance"]
    cam.azimuth = DEFAULT_CAMERA["azimuth"]
    cam.elevation = DEFAULT_CAMERA["elevation"]
    return cam


def _scene_option():
    import mujoco

    opt = mujoco.MjvOption()
    for g in range(len(opt.geomgroup)):
        opt.geomgroup[g] = 1 if g in VISIBLE_GEOM_GROUPS else 0
    return opt


def _check_size(mj_model, width: int, height: int) -> None:
    if int(width) < 1 or int(height) < 1:
        raise ConfigError(f"image size must be positive, got {width}x{height}")
    offw, offh = mj_model.vis.global_.offwidth, mj_model.vis.global_.offheight
    if width > offw or height > offh:
        raise ConfigError(
            f"image size {width}x{height} exceeds the model's offscreen buffer {offw}x{offh} "
            "(<visual><global offwidth offheight>)"
        )


class _Session:
    """One renderer, camera and scene options shared by many frames."""

    def __init__(self, mj_model, width: int, height: int, camera=None):
        import mujoco

        select_gl_backend()
        _check_size(mj_model, width, height)
        if mj_model.vis.quality.shadowsize > MAX_SHADOW_SIZE:
            mj_model = copy.copy(mj_model)  # a deep copy: the caller's model is left alone
            mj_model.vis.quality.shadowsize = MAX_SHADOW_SIZE
        self.model = mj_model
        self.data = mujoco.MjData(mj_model)
        self.camera = default_camera() if camera is None else camera
        self.option = _scene_option()
        try:
            self.renderer = mujoco.Renderer(mj_model, int(height), int(width))
        except Exception as err:  # the GL context or MuJoCo's render context could not be made
            raise RenderUnavailableError(
                f"cannot create an offscreen renderer with MUJOCO_GL={os.environ.get('MUJOCO_GL')}: {err}"
            ) from err
        obj = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, "object")
        self.object_body = int(obj)

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def frame(self, qpos, forces=None, points=None, force_scale=FORCE_SCALE) -> np.ndarray:
        import mujoco

        self.data.qpos[:] = qpos
        self.data.qvel[:] = 0
        mujoco.mj_forward(self.model, self.data)
        self.renderer.update_scene(self.data, camera=self.camera, scene_option=self.option)
        if forces is not None:
            self._add_force_arrows(np.asarray(forces, float), np.asarray(points, float), force_scale)
        return self.renderer.render().copy()

    def _add_force_arrows(self, forces: np.ndarray, points: np.ndarray, scale: float) -> None:
        import mujoco

        scene = self.renderer.scene
        if self.object_body >= 0:
            for i in range(scene.ngeom):
                g = scene.geoms[i]
                if g.objtype == mujoco.mjtObj.mjOBJ_GEOM and self.model.geom_bodyid[g.objid] == self.object_body:
                    g.rgba[3] = OVERLAY_OBJECT_ALPHA
        for k in range(forces.shape[0]):
            f = forces[k]
            if not np.all(np.isfinite(f)) or np.linalg.norm(f) * scale < 1e-4:
                continue
            if scene.ngeom >= scene.maxgeom:
                return
            g = scene.geoms[scene.ngeom]
            rgba = np.array(FORCE_COLORS[k % len(FORCE_COLORS)], np.float32)
            mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_ARROW, np.zeros(3), np.zeros(3), np.zeros(9), rgba)
            start = points[k]
            mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_ARROW, FORCE_ARROW_WIDTH, start, start + scale * f)
            # MuJoCo's classic renderer draws an arrow geom size[2] / 2 long (shaft
            # size[2] / 3, head size[2] / 6; measured: a 1 m connector is drawn 0.5 m
            # long). Double it so the arrow ends at start + scale * force.
            g.size[2] *= 2.0
            g.category = mujoco.mjtCatBit.mjCAT_DECOR
            g.emission = 0.6
            scene.ngeom += 1


# --------------------------------------------------------------------------- public rendering API


def render_pose(mj_model, qpos, width: int = 960, height: int = 720, camera=None) -> np.ndarray:
    """Render the model in configuration ``qpos``.

    Args:
      mj_model: a ``mujoco.MjModel`` (e.g. ``jaxsync.load_model().mj_model``).
      qpos: the generalised positions, shape ``(nq,)``.
      width, height: image size in pixels (at most the model's offscreen buffer,
        1280x960 for the packaged model).
      camera: ``None`` for the default free camera (:func:`default_camera`), a
        camera name or id from the model, or a ``mujoco.MjvCamera``.

    Returns:
      An ``(height, width, 3)`` uint8 RGB image.

    Raises:
      RenderUnavailableError: no OpenGL backend works here.
    """
    qpos = _check_qpos(mj_model, np.asarray(qpos, float)[None])[0]
    with _Session(mj_model, width, height, camera) as s:
        return s.frame(qpos)


def frame_indices(num_states: int, fps_out: float, sim_dt: float, speed: float = 1.0) -> np.ndarray:
    """Indices of the states shown by each output frame.

    State ``i`` is at time ``i * sim_dt``; frame ``k`` shows the state at time
    ``k * speed / fps_out`` (the nearest one), for every such time within the
    trajectory's duration ``(num_states - 1) * sim_dt``.
    """
    if num_states < 1:
        raise ConfigError("a trajectory needs at least one state")
    if not (fps_out > 0 and sim_dt > 0 and speed > 0):
        raise ConfigError(f"fps_out, sim_dt and speed must be positive, got {fps_out}, {sim_dt}, {speed}")
    duration = (num_states - 1) * sim_dt
    step = speed / fps_out
    n = int(np.floor(duration / step + 1e-9)) + 1
    idx = np.rint(np.arange(n) * step / sim_dt).astype(int)
    return np.minimum(idx, num_states - 1)


def _check_qpos(mj_model, qpos_traj: np.ndarray) -> np.ndarray:
    if qpos_traj.ndim != 2 or qpos_traj.shape[1] != mj_model.nq:
        raise ConfigError(f"qpos must have shape (T, {mj_model.nq}), got {qpos_traj.shape}")
    return qpos_traj


@dataclasses.dataclass(frozen=True)
class ForceOverlay:
    """Contact forces to draw as arrows over a trajectory.

    Attributes:
      forces: ``(T, 2, 3)`` world-frame force of each pad (right, left) on the
        object, in newtons.
      points: ``(T, 2, 3)`` where each arrow starts: the contact points on the
        object, or the pad positions.
      scale: arrow length per newton (metres).
      caption: text drawn at the top left of every frame (after time and forces).
    """

    forces: np.ndarray
    points: np.ndarray
    scale: float = FORCE_SCALE
    caption: str | None = None


def render_trajectory(
    mj_model,
    qpos_traj,
    fps_out: float,
    sim_dt: float,
    speed: float = 1.0,
    width: int = 960,
    height: int = 720,
    overlay: ForceOverlay | None = None,
    *,
    forces=None,
    points=None,
    camera=None,
) -> list[np.ndarray]:
    """Render a trajectory as video frames, subsampled to the output frame rate.

    Args:
      mj_model: a ``mujoco.MjModel``.
      qpos_traj: ``(T, nq)`` states; state ``i`` is at time ``i * sim_dt``.
      fps_out: frames per second of the video.
      sim_dt: time between successive states (seconds).
      speed: playback speed (2.0 = twice as fast); frame ``k`` shows the state
        at time ``k * speed / fps_out`` (see :func:`frame_indices`).
      width, height: frame size in pixels.
      overlay: contact forces to draw (a :class:`ForceOverlay`); or pass
        ``forces`` and ``points`` directly (shortcut for the same thing).
      camera: as for :func:`render_pose`; the same camera for every frame.

    Returns:
      A list of ``(height, width, 3)`` uint8 frames. With a force overlay each
      frame also carries a caption: the time and the force magnitude of each pad.
    """
    qpos_traj = _check_qpos(mj_model, np.asarray(qpos_traj, float))
    if overlay is None and forces is not None:
        if points is None:
            raise ConfigError("forces given without points: pass where the arrows start (T, 2, 3)")
        overlay = ForceOverlay(np.asarray(forces, float), np.asarray(points, float))
    if overlay is not None:
        T = qpos_traj.shape[0]
        f, p = np.asarray(overlay.forces, float), np.asarray(overlay.points, float)
        if f.ndim != 3 or f.shape[0] != T or f.shape[2] != 3 or p.shape != f.shape:
            raise ConfigError(
                f"overlay forces and points must both have shape ({T}, 2, 3), got {f.shape} and {p.shape}"
            )
        overlay = dataclasses.replace(overlay, forces=f, points=p)
    idx = frame_indices(qpos_traj.shape[0], fps_out, sim_dt, speed)
    frames = []
    with _Session(mj_model, width, height, camera) as s:
        for i in idx:
            if overlay is None:
                frames.append(s.frame(qpos_traj[i]))
                continue
            img = s.frame(qpos_traj[i], overlay.forces[i], overlay.points[i], overlay.scale)
            mags = np.linalg.norm(overlay.forces[i], axis=-1)
            text = f"t = {i * sim_dt:6.3f} s   " + "   ".join(
                f"|F_{name}| = {m:6.2f} N ({colour})"
                for name, colour, m in zip(("right", "left"), ("blue", "orange"), mags, strict=False)
            )
            if overlay.caption:
                text = f"{overlay.caption}\n{text}"
            frames.append(_draw_text(img, text, (8, 6)))
    return frames


def _font(size: int):
    from PIL import ImageFont

    for name in ("DejaVuSansMono.ttf", "DejaVuSans.ttf"):
        try:
            return ImageFont.truetype(name, size)
        except OSError:
            pass
    try:  # matplotlib ships DejaVu fonts
        import matplotlib

        path = os.path.join(matplotlib.get_data_path(), "fonts", "ttf", "DejaVuSansMono.ttf")
        return ImageFont.truetype(path, size)
    except (ImportError, OSError):
        return ImageFont.load_default()


def _draw_text(image: np.ndarray, text: str, xy=(8, 6), size: int | None = None) -> np.ndarray:
    """Draw white text on a dark box onto a copy of ``image``."""
    from PIL import Image, ImageDraw

    h = image.shape[0]
    size = size or max(10, h // 36)
    im = Image.fromarray(image)
    draw = ImageDraw.Draw(im)
    font = _font(size)
    box = draw.multiline_textbbox(xy, text, font=font)
    pad = max(2, size // 4)
    draw.rectangle((box[0] - pad, box[1] - pad, box[2] + pad, box[3] + pad), fill=(0, 0, 0))
    draw.multiline_text(xy, text, fill=(255, 255, 255), font=font)
    return np.asarray(im)


def side_by_side(
    frames_a: Sequence[np.ndarray],
    frames_b: Sequence[np.ndarray],
    labels: tuple[str, str] | None = ("classical", "synchronous"),
    gap: int = 4,
) -> list[np.ndarray]:
    """Put two frame lists next to each other, each labelled at its bottom left.

    The shorter list holds its last frame; frames of different heights are
    padded (black) at the bottom. ``gap`` pixels of white separate the two.
    """
    if len(frames_a) == 0 or len(frames_b) == 0:
        raise ConfigError("side_by_side needs at least one frame in each list")
    n = max(len(frames_a), len(frames_b))
    out = []
    for k in range(n):
        a = np.asarray(frames_a[min(k, len(frames_a) - 1)], np.uint8)
        b = np.asarray(frames_b[min(k, len(frames_b) - 1)], np.uint8)
        h = max(a.shape[0], b.shape[0])
        parts = []
        for img, label in zip((a, b), labels or (None, None), strict=False):
            if img.shape[0] < h:
                img = np.concatenate([img, np.zeros((h - img.shape[0], *img.shape[1:]), np.uint8)])
            if label:
                size = max(10, h // 30)
                img = _draw_text(img, label, (10, h - size - 14), size=size)
            parts.append(img)
        sep = np.full((h, gap, 3), 255, np.uint8)
        out.append(np.concatenate([parts[0], sep, parts[1]], axis=1))
    return out


# --------------------------------------------------------------------------- files


def save_png(image: np.ndarray, path: str | os.PathLike) -> str:
    """Write an RGB(A) uint8 image to ``path`` as PNG, atomically; returns the path."""
    from PIL import Image

    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with _io.atomic_path(path) as tmp:
        Image.fromarray(np.asarray(image, np.uint8)).save(tmp, format="PNG")
    return path


def mp4_available() -> bool:
    """True when ``imageio_ffmpeg`` (which ships an ffmpeg binary) can be imported."""
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return False
    return True


def write_video(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: float) -> str:
    """Write frames as a video, atomically; returns the path actually written.

    A ``.gif`` path is written as an animated GIF (Pillow). Any other path is
    written as H.264 MP4 when ``imageio_ffmpeg`` is importable (odd frame sizes
    are padded by one black pixel), else as a GIF with the extension changed to
    ``.gif``. GIF frame delays are in 10 ms steps; they alternate so that the
    average rate is ``fps``. Pillow merges identical consecutive GIF frames
    into one longer frame (timing is kept).
    """
    if len(frames) == 0:
        raise ConfigError("write_video needs at least one frame")
    if not fps > 0:
        raise ConfigError(f"fps must be positive, got {fps}")
    frames = [np.ascontiguousarray(np.asarray(f, np.uint8)[..., :3]) for f in frames]
    shape = frames[0].shape
    if any(f.shape != shape for f in frames):
        raise ConfigError("all video frames must have the same size")
    path = os.fspath(path)
    root, ext = os.path.splitext(path)
    if ext.lower() != ".gif" and not mp4_available():
        path = root + ".gif"
        ext = ".gif"
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with _io.atomic_path(path) as tmp:
        if ext.lower() == ".gif":
            _write_gif(frames, tmp, fps)
        else:
            _write_mp4(frames, tmp, fps)
    return path


def _write_gif(frames: list[np.ndarray], path: str, fps: float) -> None:
    from PIL import Image

    ends = np.rint(np.arange(len(frames) + 1) * 100.0 / fps).astype(int) * 10  # ms, on 10 ms steps
    durations = [int(max(10, d)) for d in np.diff(ends)]
    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=durations, loop=0)


def _write_mp4(frames: list[np.ndarray], path: str, fps: float) -> None:
    import imageio_ffmpeg

    h, w = frames[0].shape[:2]
    H, W = h + h % 2, w + w % 2  # H.264 with yuv420p needs even sizes
    writer = imageio_ffmpeg.write_frames(
        path,
        (W, H),
        fps=fps,
        codec="libx264",
        pix_fmt_in="rgb24",
        pix_fmt_out="yuv420p",
        macro_block_size=1,
        quality=7,
        ffmpeg_log_level="error",
        output_params=["-f", "mp4"],
    )
    with warnings.catch_warnings():
        # imageio-ffmpeg starts ffmpeg with fork + exec, which is safe; JAX warns on any fork.
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        writer.send(None)
    try:
        for f in frames:
            if (H, W) != (h, w):
                f = np.pad(f, ((0, H - h), (0, W - w), (0, 0)))
            writer.send(np.ascontiguousarray(f))
    finally:
        writer.close()
