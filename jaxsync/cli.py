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


def _scenario_from_args(args: argparse.Namespace):
    import jax
    import numpy as np

    from jaxsync._scenario import default_scenario

    overrides = {}
    if args.object_mass is not None:
        overrides["object_mass"] = args.object_mass
    if args.grip_force is not None:
        overrides["grip_force"] = args.grip_force
    if args.object_offset is not None:
        overrides["object_offset"] = [0.0, args.object_offset, 0.0]
    if args.force_noise is not None:
        overrides["force_noise"] = args.force_noise
    overrides["noise_key"] = np.asarray(jax.random.key_data(jax.random.key(args.seed)))
    if "object_mass" in overrides:
        overrides["mass_estimate"] = overrides["object_mass"]
    return default_scenario(**overrides)


def cmd_compare(args: argparse.Namespace) -> int:
    import time

    from jaxsync import _compare, _gains
    from jaxsync._io import ensure_writable_dir
    from jaxsync._model import load_model

    ensure_writable_dir(args.out)
    gains = _gains.load(args.gains) if args.gains else _gains.default_gains()
    scenario = _scenario_from_args(args)
    model = load_model(args.model, solver="accurate")
    t0 = time.perf_counter()
    results = _compare.run(model, gains, scenario, duration=args.duration, backend=args.backend)
    options = {k: v for k, v in vars(args).items() if k not in ("func",)}
    summary = _compare.write_results(args.out, results, scenario, gains, options, time.perf_counter() - t0)
    if args.video:
        from jaxsync import _render_cli

        _render_cli.compare_video(model, results, scenario, args.out, speed=args.video_speed)
    keys = _compare.SUMMARY_KEYS
    print(f"{'':28}{'classical':>14}{'synchronous':>14}")
    for k in keys:
        a, b = summary["classical"][k], summary["synchronous"][k]
        fmt = (lambda v: f"{str(v):>14}") if isinstance(a, bool) else (lambda v: f"{v:>14.5g}")
        print(f"{k:<28}{fmt(a)}{fmt(b)}")
    ratio = summary["resultant_ratio"]
    print(f"resultant_ratio (classical / synchronous): {ratio:.3f}" if ratio else "resultant_ratio: n/a")
    print(f"results in {args.out}: summary.json, series.csv, forces_classical.png, forces_synchronous.png")
    return 0


def _positive(kind):
    def parse(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not v > 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {text}")
        return v

    return parse


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

    cmp_ = sub.add_parser(
        "compare",
        help="the paper's comparison: classical vs synchronous controller on one scenario",
        description="Roll out the classical impedance and the synchronous controller with the same "
        "impedance parameters on the same scenario; write summary.json, series.csv and force plots.",
    )
    cmp_.add_argument("--duration", type=_positive(float), default=4.0, help="seconds simulated (default 4)")
    cmp_.add_argument("--grip-force", type=_positive(float), default=None, help="desired grip force f_d, N (10)")
    cmp_.add_argument("--object-mass", type=_positive(float), default=None, help="object mass, kg (0.5)")
    cmp_.add_argument(
        "--object-offset",
        type=float,
        default=None,
        help="where the object starts off the nominal grasp centre along the clamping axis, m (0.003)",
    )
    cmp_.add_argument("--force-noise", type=float, default=None, help="wrist force noise std, N (0.1)")
    cmp_.add_argument("--seed", type=int, default=0, help="sensor-noise seed (0)")
    cmp_.add_argument("--gains", default=None, help="JSON file of gains (default: built-in)")
    cmp_.add_argument("--out", default="results/compare", help="output folder (results/compare)")
    cmp_.add_argument("--backend", default="mjx", choices=["mjx", "mujoco"], help="physics engine (mjx)")
    cmp_.add_argument("--model", default=None, help="MJCF file (default: the packaged paper model)")
    cmp_.add_argument("--video", action="store_true", help="also render both rollouts side by side to a video")
    cmp_.add_argument("--video-speed", type=_positive(float), default=0.5, help="playback speed of the video (0.5)")
    cmp_.set_defaults(func=cmd_compare)

    from jaxsync._bench import add_bench_parser
    from jaxsync._render_cli import add_render_parser
    from jaxsync.optimize.sweep import add_sweep_parser
    from jaxsync.optimize.tune import add_tune_parser

    add_tune_parser(sub)
    add_sweep_parser(sub)
    add_bench_parser(sub)
    add_render_parser(sub)
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
        hint = getattr(args, "interrupted_hint", None)
        print(f"jaxsync {args.command}: interrupted" + (f" ({hint})" if hint else ""), file=sys.stderr)
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
