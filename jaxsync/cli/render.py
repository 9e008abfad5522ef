"""``jaxsync render`` and ``jaxsync compare --video``: thin glue over ``jaxsync._render``."""

from __future__ import annotations

import os

import numpy as np

from jaxsync.cli._common import add_model_argument

VIDEO_FPS = 25


def run(args) -> int:
    from jaxsync import _io, _render
    from jaxsync._model import load_model

    _io.ensure_writable_dir(args.out)
    backend = _render.select_gl_backend()
    model = load_model(args.model)
    image = _render.render_pose(model.mj_model, model.keyframe_qpos(args.keyframe), args.width, args.height)
    path = _render.save_png(image, os.path.join(args.out, f"{args.keyframe}.png"))
    print(f"wrote {path} ({args.width}x{args.height}, OpenGL backend: {backend})")
    return 0


def compare_video(
    model, results: dict, scenario, out: str, speed: float = 0.5, width: int = 480, height: int = 360
) -> str:
    """Both controllers' rollouts side by side, from the states that were
    computed (MJX states drawn by MuJoCo's renderer), with each pad's contact
    force on the object as an arrow; ``speed`` < 1 is slow motion."""
    from jaxsync import _render
    from jaxsync._metrics import summarize

    _render.select_gl_backend()
    dt = float(np.asarray(results["classical"][0].time[1] - results["classical"][0].time[0]))
    frames = {}
    for name, (traj, _) in results.items():
        peak = float(summarize(traj, scenario).settled_peak_resultant_N)
        overlay = _render.ForceOverlay(
            forces=np.asarray(traj.pad_forces),
            points=np.asarray(traj.pad_pos),
            caption=f"{name}: settled peak resultant {peak * 1000:.1f} mN (x{speed:g} speed)",
        )
        frames[name] = _render.render_trajectory(
            model.mj_model, np.asarray(traj.qpos), VIDEO_FPS, dt, speed, width, height, overlay
        )
    combined = _render.side_by_side(frames["classical"], frames["synchronous"])
    path = _render.write_video(combined, os.path.join(out, "compare.mp4"), VIDEO_FPS)
    print(f"video: {path} ({len(combined)} frames at {VIDEO_FPS} fps, {speed:g}x speed)")
    return path


def add_parser(sub) -> None:
    p = sub.add_parser("render", help="a PNG of the model in a keyframe pose (headless)")
    p.add_argument("--out", default="results/render", help="output folder (results/render)")
    p.add_argument("--keyframe", default="grasp", choices=["grasp", "approach"])
    p.add_argument("--width", type=int, default=960)
    p.add_argument("--height", type=int, default=720)
    add_model_argument(p)
    p.set_defaults(func=run)
