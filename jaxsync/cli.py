"""The ``jaxsync`` command line."""

from __future__ import annotations

import argparse
import os
import platform
import sys

from jaxsync._errors import JaxsyncError


def _setup_jax(args: argparse.Namespace) -> None:
    import jax

    from jaxsync._cache import enable_compilation_cache

    jax.config.update("jax_enable_x64", not getattr(args, "float32", False))
    enable_compilation_cache(getattr(args, "cache_dir", None))


def model_summary(model) -> dict:
    """A plain-dict description of a loaded model (for ``jaxsync info``)."""
    import mujoco

    m = model.mj_model
    name = lambda obj, i: mujoco.mj_id2name(m, obj, i)  # noqa: E731
    arms = {}
    for arm in model.index.arms:
        arms[arm.prefix] = [name(mujoco.mjtObj.mjOBJ_JOINT, int(m.dof_jntid[a])) for a in arm.dof_adr]
    return {
        "model": model.path,
        "bodies": m.nbody,
        "nq": m.nq,
        "nv": m.nv,
        "joints_per_arm": {k: len(v) for k, v in arms.items()},
        "arm_joints": arms,
        "actuators": m.nu,
        "sensors": [name(mujoco.mjtObj.mjOBJ_SENSOR, i) for i in range(m.nsensor)],
        "contact_pairs": [
            f"{name(mujoco.mjtObj.mjOBJ_GEOM, int(m.pair_geom1[i]))}-"
            f"{name(mujoco.mjtObj.mjOBJ_GEOM, int(m.pair_geom2[i]))}"
            for i in range(m.npair)
        ],
        "colliding_geoms_outside_pairs": int(((m.geom_contype != 0) | (m.geom_conaffinity != 0)).sum()),
        "object_mass_kg": float(m.body_subtreemass[model.index.object_body]),
        "object_radius_m": float(m.geom_size[model.index.object_geom][0]),
        "timestep_s": float(m.opt.timestep),
        "integrator": mujoco.mjtIntegrator(m.opt.integrator).name,
        "solver": f"{mujoco.mjtSolver(m.opt.solver).name} ({model.solver}: iterations={m.opt.iterations}, "
        f"ls_iterations={m.opt.ls_iterations})",
        "cone": mujoco.mjtCone(m.opt.cone).name,
    }


def cmd_info(args: argparse.Namespace) -> int:
    import jax
    import mujoco

    from jaxsync._model import load_model

    model = load_model(args.model, solver=args.solver)
    from importlib.metadata import version

    print(f"jaxsync      {version('jaxsync')}")
    print(f"python       {platform.python_version()} on {platform.machine()}")
    print(f"jax          {jax.__version__} (x64: {jax.config.jax_enable_x64})")
    print(f"mujoco       {mujoco.__version__}")
    print(f"mujoco-mjx   {version('mujoco-mjx')}")
    print(f"devices      {', '.join(str(d) for d in jax.devices())}")
    print(f"cpu cores    {os.cpu_count()}")
    print()
    for key, value in model_summary(model).items():
        if isinstance(value, dict):
            value = ", ".join(f"{k}: {v}" for k, v in value.items())
        elif isinstance(value, list):
            value = ", ".join(map(str, value))
        print(f"{key:<30} {value}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxsync",
        description="Differentiable dual-arm contact-force synchronous control with JAX and MuJoCo MJX.",
    )
    parser.add_argument(
        "--cache-dir",
        default=None,
        help="JAX persistent compilation cache (default $JAXSYNC_CACHE_DIR or ~/.cache/jaxsync/xla; 'off').",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    info = sub.add_parser("info", help="versions, devices and a summary of the model")
    info.add_argument("--model", default=None, help="MJCF file (default: the packaged paper model)")
    info.add_argument("--solver", default="accurate", choices=["accurate", "differentiable"])
    info.set_defaults(func=cmd_info)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        _setup_jax(args)
        return args.func(args)
    except JaxsyncError as err:
        print(f"jaxsync {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"jaxsync {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # an unexpected failure: say what, keep the traceback opt-in
        if os.environ.get("JAXSYNC_DEBUG"):
            raise
        print(
            f"jaxsync {args.command}: internal error: {type(err).__name__}: {err}\n"
            "(set JAXSYNC_DEBUG=1 for the traceback, and please report it)",
            file=sys.stderr,
        )
        return 3


if __name__ == "__main__":
    sys.exit(main())
