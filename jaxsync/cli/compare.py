"""``jaxsync compare``: the paper's comparison, classical vs synchronous on one scenario."""

from __future__ import annotations

import argparse

from jaxsync.cli._common import add_model_argument, positive


def scenario_from_args(args: argparse.Namespace):
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


def run(args: argparse.Namespace) -> int:
    import time

    from jaxsync import _compare, _gains
    from jaxsync._io import ensure_writable_dir
    from jaxsync._model import load_model

    ensure_writable_dir(args.out)
    gains = _gains.load(args.gains) if args.gains else _gains.default_gains()
    scenario = scenario_from_args(args)
    model = load_model(args.model, solver="accurate")
    t0 = time.perf_counter()
    results = _compare.run(model, gains, scenario, duration=args.duration, backend=args.backend)
    options = {k: v for k, v in vars(args).items() if k not in ("func",)}
    summary = _compare.write_results(args.out, results, scenario, gains, options, time.perf_counter() - t0)
    if args.video:
        from jaxsync.cli.render import compare_video

        compare_video(model, results, scenario, args.out, speed=args.video_speed)
    print(f"{'':28}{'classical':>14}{'synchronous':>14}")
    for k in _compare.SUMMARY_KEYS:
        a, b = summary["classical"][k], summary["synchronous"][k]
        fmt = (lambda v: f"{str(v):>14}") if isinstance(a, bool) else (lambda v: f"{v:>14.5g}")
        print(f"{k:<28}{fmt(a)}{fmt(b)}")
    ratio = summary["resultant_ratio"]
    print(f"resultant_ratio (classical / synchronous): {ratio:.3f}" if ratio else "resultant_ratio: n/a")
    print(f"results in {args.out}: summary.json, series.csv, forces_classical.png, forces_synchronous.png")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "compare",
        help="the paper's comparison: classical vs synchronous controller on one scenario",
        description="Roll out the classical impedance and the synchronous controller with the same "
        "impedance parameters on the same scenario; write summary.json, series.csv and force plots.",
    )
    p.add_argument("--duration", type=positive(float), default=4.0, help="seconds simulated (default 4)")
    p.add_argument("--grip-force", type=positive(float), default=None, help="desired grip force f_d, N (10)")
    p.add_argument("--object-mass", type=positive(float), default=None, help="object mass, kg (0.5)")
    p.add_argument(
        "--object-offset",
        type=float,
        default=None,
        help="where the object starts off the nominal grasp centre along the clamping axis, m (0.003)",
    )
    p.add_argument("--force-noise", type=float, default=None, help="wrist force noise std, N (0.1)")
    p.add_argument("--seed", type=int, default=0, help="sensor-noise seed (0)")
    p.add_argument("--gains", default=None, help="JSON file of gains (default: built-in)")
    p.add_argument("--out", default="results/compare", help="output folder (results/compare)")
    p.add_argument("--backend", default="mjx", choices=["mjx", "mujoco"], help="physics engine (mjx)")
    add_model_argument(p)
    p.add_argument("--video", action="store_true", help="also render both rollouts side by side to a video")
    p.add_argument("--video-speed", type=positive(float), default=0.5, help="playback speed of the video (0.5)")
    p.set_defaults(func=run)
