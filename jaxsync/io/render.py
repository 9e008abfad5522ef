"""Pictures and videos of the robot and of rollouts (headless, offscreen).

Scenes and frames here; the OpenGL backend in ``jaxsync.runtime.gl``; text,
side-by-side frames and image and video files in ``jaxsync.io.video``.
"""

from __future__ import annotations

import copy
import dataclasses
import os

import mujoco
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.io import results as _results
from jaxsync.io.video import _draw_text, save_png, side_by_side, write_video
from jaxsync.physics.model import identity
from jaxsync.runtime.gl import RenderUnavailableError, select_gl_backend

__all__ = [
    "ForceOverlay",
    "RenderUnavailableError",
    "default_camera",
    "frame_indices",
    "render_pose",
    "render_trajectory",
    "save_png",
    "select_gl_backend",
    "side_by_side",
    "write_video",
]

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


# --------------------------------------------------------------------------- cameras and scenes


def default_camera():
    """The default free camera (see ``DEFAULT_CAMERA``) as a ``mujoco.MjvCamera``."""

    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = DEFAULT_CAMERA["lookat"]
    cam.distance = DEFAULT_CAMERA["distance"]
    cam.azimuth = DEFAULT_CAMERA["azimuth"]
    cam.elevation = DEFAULT_CAMERA["elevation"]
    return cam


def _scene_option():

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

        self.data.qpos[:] = qpos
        self.data.qvel[:] = 0
        mujoco.mj_forward(self.model, self.data)
        self.renderer.update_scene(self.data, camera=self.camera, scene_option=self.option)
        if forces is not None:
            self._add_force_arrows(np.asarray(forces, float), np.asarray(points, float), force_scale)
        return self.renderer.render().copy()

    def _add_force_arrows(self, forces: np.ndarray, points: np.ndarray, scale: float) -> None:

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
    progress=None,
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
      progress: ``progress(done, total)``, called after each frame.

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
            if progress is not None and frames:
                progress(len(frames), len(idx))
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
    if progress is not None:
        progress(len(frames), len(idx))
    return frames


def render_keyframe(model, keyframe: str, out: str, width: int = 960, height: int = 720) -> list[str]:
    """``jaxsync render``'s job: ``model`` (a :class:`~jaxsync.physics.model.DualArmModel`)
    in ``keyframe``'s pose as ``out/<keyframe>.png``, and ``out/render.json``
    recording which model it drew and its object; returns both paths."""
    image = render_pose(model.mj_model, model.keyframe_qpos(keyframe), width, height)
    _results.ensure_writable_dir(out)  # the input is checked: only now the folder
    png = save_png(image, os.path.join(out, f"{keyframe}.png"))
    m, index = model.mj_model, model.index
    doc = {
        "model": identity(model),
        "keyframe": keyframe,
        "size_px": [int(width), int(height)],
        "object": {
            "mass_kg": float(m.body_subtreemass[index.object_body]),
            "radius_m": float(m.geom_size[index.object_geom][0]),
        },
    }
    record = os.path.join(out, "render.json")
    _results.write_json(record, doc)
    return [png, record]
