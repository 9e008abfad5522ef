"""The paper's comparison as a video: both controllers side by side, the pad
forces drawn as arrows (``jaxsync compare --video``)."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

import numpy as np

from jaxsync.io import render as _render
from jaxsync.sim.metrics import drop_time, summarize

VIDEO_FPS = 25


def compare_video(
    model,
    results: dict,
    scenario,
    out: str,
    speed: float = 0.5,
    width: int = 480,
    height: int = 360,
    log: Callable[[str], None] = print,
) -> str:
    """The controllers' rollouts side by side, from the states that were
    computed (MJX states drawn by MuJoCo's renderer), with each pad's contact
    force on the object as an arrow; ``speed`` < 1 is slow motion."""
    _render.select_gl_backend()
    first = next(iter(results.values()))[0]
    dt = float(np.asarray(first.time[1] - first.time[0]))
    frames = {}
    for k, (name, (traj, _)) in enumerate(results.items()):
        m = summarize(traj, scenario)
        t_drop = drop_time(m)
        what = (
            f"dropped the object at t={t_drop:.2f} s"
            if t_drop is not None
            else f"settled peak resultant {float(m.settled_peak_resultant_N) * 1000:.1f} mN"
        )
        overlay = _render.ForceOverlay(
            forces=np.asarray(traj.pad_forces),
            points=np.asarray(traj.pad_pos),
            caption=f"{name}: {what} (x{speed:g} speed)",
        )
        frames[name] = _render.render_trajectory(
            model.mj_model,
            np.asarray(traj.qpos),
            VIDEO_FPS,
            dt,
            speed,
            width,
            height,
            overlay,
            progress=FrameCounter(f"[video {k + 1}/{len(results)}] rendering {name}"),
        )
    names = list(frames)
    combined = _render.side_by_side(frames[names[0]], frames[names[1]], labels=(names[0], names[1]))
    for name in names[2:]:  # each further controller to the right (its caption names it)
        combined = _render.side_by_side(combined, frames[name], labels=None)
    path = _render.write_video(combined, os.path.join(out, "compare.mp4"), VIDEO_FPS)
    log(f"video: {path} ({len(combined)} frames at {VIDEO_FPS} fps, {speed:g}x speed)")
    return path


class FrameCounter:
    """A frame counter on stderr: one line rewritten in place on a terminal,
    else a line at every tenth of the frames (a log stays short)."""

    def __init__(self, label: str, stream=None):
        self.label, self.stream = label, stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.shown = -1

    def __call__(self, done: int, total: int) -> None:
        line = f"{self.label}: frame {done}/{total}"
        if self.tty:
            self.stream.write("\r" + line + ("\n" if done == total else ""))
        elif done == total or done * 10 // total > self.shown:
            self.shown = done * 10 // total
            self.stream.write(line + "\n")
        self.stream.flush()
