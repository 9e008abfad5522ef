"""``jaxsync info``: versions, devices and a summary of the model."""

from __future__ import annotations

import argparse
import os
import platform

from jaxsync.cli._common import add_model_argument


def model_summary(model) -> dict:
    """A plain-dict description of a loaded model."""
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


def run(args: argparse.Namespace) -> int:
    from importlib.metadata import version

    import jax
    import mujoco

    from jaxsync.physics.model import load_model

    model = load_model(args.model, solver=args.solver)
    print(f"jaxsync      {version('jaxsync')}")
    print(f"python       {platform.python_version()} on {platform.machine()}")
    print(f"jax          {jax.__version__} (x64: {jax.config.jax_enable_x64})")
    print(f"mujoco       {mujoco.__version__}")
    print(f"mujoco-mjx   {version('mujoco-mjx')}")
    print(f"devices      {', '.join(str(d) for d in jax.devices())}")
    print(f"XLA_FLAGS    {os.environ.get('XLA_FLAGS') or '(none)'}")
    print(f"cpu cores    {os.cpu_count()}")
    print()
    for key, value in model_summary(model).items():
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
