"""``jaxsync info``: versions, devices and a summary of the model."""

from __future__ import annotations

import argparse
import os
import platform

from jaxsync.cli._common import add_model_argument, model_options, model_source


def run(args: argparse.Namespace) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from importlib.metadata import version

    import jax
    import mujoco

    from jaxsync.physics.model import load_model, summary

    model = load_model(model_source(args), solver=args.solver, **model_options(args))
    print(f"jaxsync      {version('jaxsync')}")
    print(f"python       {platform.python_version()} on {platform.machine()}")
    print(f"jax          {jax.__version__} (x64: {jax.config.jax_enable_x64})")
    print(f"mujoco       {mujoco.__version__}")
    print(f"mujoco-mjx   {version('mujoco-mjx')}")
    print(f"devices      {', '.join(str(d) for d in jax.devices())}")
    print(f"XLA_FLAGS    {os.environ.get('XLA_FLAGS') or '(none)'}")
    print(f"cpu cores    {os.cpu_count()}")
    print()
    for key, value in summary(model).items():
        if isinstance(value, dict):
            value = ", ".join(f"{k}: {v}" for k, v in value.items())
        elif isinstance(value, list):
            value = ", ".join(map(str, value))
        print(f"{key:<30} {value}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("info", help="versions, devices and a summary of the model")
    add_model_argument(p)
    p.add_argument("--solver", default="accurate", choices=["accurate", "unrolled"])
    p.set_defaults(func=run)
