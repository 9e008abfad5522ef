"""Text on frames, frames side by side, and image and video files (atomic writes)."""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence

import matplotlib
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from jaxsync._errors import ConfigError
from jaxsync.io import results as _results


def _font(size: int):

    for name in ("DejaVuSansMono.ttf", "DejaVuSans.ttf"):
        try:
            return ImageFont.truetype(name, size)
        except OSError:
            pass
    try:  # matplotlib ships DejaVu fonts
        path = os.path.join(matplotlib.get_data_path(), "fonts", "ttf", "DejaVuSansMono.ttf")
        return ImageFont.truetype(path, size)
    except (ImportError, OSError):
        return ImageFont.load_default()


def _draw_text(image: np.ndarray, text: str, xy=(8, 6), size: int | None = None) -> np.ndarray:
    """Draw white text on a dark box onto a copy of ``image``."""

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

    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with _results.atomic_path(path) as tmp:
        Image.fromarray(np.asarray(image, np.uint8)).save(tmp, format="PNG")
    return path


def mp4_available() -> bool:
    """True when ``imageio_ffmpeg`` (which ships an ffmpeg binary) can be imported."""
    try:
        import imageio_ffmpeg  # noqa: F401  (optional: MP4 videos; GIF without it)
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
    with _results.atomic_path(path) as tmp:
        if ext.lower() == ".gif":
            _write_gif(frames, tmp, fps)
        else:
            _write_mp4(frames, tmp, fps)
    return path


def _write_gif(frames: list[np.ndarray], path: str, fps: float) -> None:

    ends = np.rint(np.arange(len(frames) + 1) * 100.0 / fps).astype(int) * 10  # ms, on 10 ms steps
    durations = [int(max(10, d)) for d in np.diff(ends)]
    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=durations, loop=0)


def _write_mp4(frames: list[np.ndarray], path: str, fps: float) -> None:
    import imageio_ffmpeg  # optional (MP4 videos): callers check mp4_available() first

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
