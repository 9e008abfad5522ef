"""``jaxsync render``: a PNG of the model in a keyframe pose (``jaxsync.io.render``)."""

from __future__ import annotations

import os

from jaxsync.cli._common import add_model_argument, model_options, model_source


def run(args) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.io import render as _render
    from jaxsync.physics.model import load_model

    backend = _render.select_gl_backend()
    model = load_model(model_source(args), **model_options(args))
    png, record = _render.render_keyframe(model, args.keyframe, args.out, args.width, args.height)
    print(f"wrote {png} and {os.path.basename(record)} ({args.width}x{args.height}, OpenGL backend: {backend})")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("render", help="a PNG of the model in a keyframe pose (headless)")
    p.add_argument("--out", default="results/render", help="output folder (results/render)")
    p.add_argument("--keyframe", default="grasp", choices=["grasp", "approach"])
    p.add_argument("--width", type=int, default=960)
    p.add_argument("--height", type=int, default=720)
    add_model_argument(p)
    p.set_defaults(func=run)
