"""jaxsync calibrate on recordings jaxsync's model did not make (docs/calibrate.md).

Each case: a robot with joint torque limits and friction loss as a published
arm has them (``tests/independent_servo.py``: the iiwa-like arm with the
Franka FR3's limits, friction loss, armature and servo gains), its servo
gains moved at random by up to +-25 %, plays ``jaxsync excite``'s trajectory
through a servo written independently of jaxsync (MuJoCo C, RK4 at 0.25 ms,
one of three structures: as written, weight-compensated, with velocity
feed-forward) with a delay of whole command periods and sensor noise; then
``calibrate`` fits it. Prints per case the delay found, the worst stiffness
and damping errors, the claimed 95 % half-width beside the actual error,
the fit's warnings and the seconds, and the servo structure it chose
with its margin on held-out windows.

    python experiments/calibrate_independent.py --structures feedforward --delays 0,2 --duration 20
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests"))
import independent_servo as ind  # noqa: E402  (the tests' independent generator)

from jaxsync.calibrate import excite  # noqa: E402
from jaxsync.calibrate.fit import calibrate  # noqa: E402
from jaxsync.calibrate.replay import Replay  # noqa: E402
from jaxsync.io.bags import Recording  # noqa: E402
from jaxsync.physics.model import load_model  # noqa: E402


def case(
    model,
    structure: str,
    delay: int,
    duration: float,
    seed: int,
    noise_q: float,
    noise_dq: float,
    verbose: bool = False,
    timestep: float | None = None,
    generator: str = "actuators",
    noise_tau: float | None = None,
    amplitude: float | None = None,
    speed: float | None = None,
):
    nominal = Replay(model).nominal()
    rng = np.random.default_rng(seed)
    n = len(nominal.stiffness)
    kp = nominal.stiffness * rng.uniform(0.75, 1.25, n)
    kv = nominal.damping * rng.uniform(0.75, 1.25, n)
    shape = {k: v for k, v in (("amplitude", amplitude), ("speed", speed)) if v is not None}
    ex = excite.excitation(model, duration=duration, **shape)
    q0 = np.asarray(model.keyframe_qpos("grasp"))
    lim = np.tile(ind.LIMITED["fr3"].limits, 2)
    eff = noise_tau is not None
    if generator == "actuators":
        out = ind.record_actuators(model.robot.spec, q0, kp, kv, ex.times, ex.commands, delay,
                                   structure=structure, efforts=eff)  # fmt: skip
    else:
        out = ind.record(model.mj_model, q0, kp, kv, lim, ex.times, ex.commands, delay, structure=structure,
                         efforts=eff)  # fmt: skip
    t, q, dq = out[:3]
    q, dq = ind.noisy(q, dq, noise_q, noise_dq, seed + 1)
    tau = out[3] + noise_tau * np.random.default_rng(seed + 2).standard_normal(out[3].shape) if eff else None
    rec = Recording(tuple(ex.joints), t, q, dq, ex.times, ex.commands, source=f"{structure}, delay {delay}",
                    effort=tau)  # fmt: skip
    start = time.perf_counter()
    cal = calibrate(model, rec, timestep=timestep)[0]
    seconds = time.perf_counter() - start
    err_k = np.abs(cal.fitted.stiffness / kp - 1)
    err_b = np.abs(cal.fitted.damping / kv - 1)
    claimed_k = np.nanmax(cal.intervals.get("stiffness", np.full(n, np.nan)) / kp)
    if verbose:
        for name, a, b, c, d in zip(
            cal.joints,
            cal.fitted.stiffness / kp - 1,
            cal.fitted.damping / kv - 1,
            cal.intervals.get("stiffness", np.full(n, np.nan)) / kp,
            cal.rms_after,
            strict=False,
        ):
            print(f"  {name}: stiffness {a:+.3f} (claimed +-{c:.3f}), damping {b:+.3f}, rms {1e3 * d:.3f} mrad")
    return {
        "structure": structure,
        "delay": delay,
        "found": cal.delay,
        "found_structure": cal.structure,
        "structure_margin": float(cal.structure_margin) if cal.structure_margin is not None else float("nan"),
        "stiffness_err_max": float(err_k.max()),
        "damping_err_max": float(err_b.max()),
        "claimed_k_halfwidth_max": float(claimed_k),
        "poor": len(cal.poor),
        "refused": "; ".join(cal.problems) or "no",
        "rms_after_max_mrad": float(1e3 * cal.rms_after.max()),
        "gains_from_efforts": len(cal.from_efforts),
        "seconds": seconds,
        **(
            {
                "efforts": f"{cal.efforts.structure} at delay {cal.efforts.delay}",
                "efforts_stiffness_err_max": float(np.abs(cal.efforts.stiffness / kp - 1).max()),
                "efforts_damping_err_max": float(np.abs(cal.efforts.damping / kv - 1).max()),
                "saturated_max": float(cal.efforts.saturated.max()),
            }
            if cal.efforts is not None
            else {}
        ),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--structures", default=",".join(ind.STRUCTURES))
    p.add_argument("--delays", default="0,1,2,3")
    p.add_argument("--duration", type=float, default=20.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--noise-q", type=float, default=1e-4)
    p.add_argument("--noise-dq", type=float, default=5e-3)
    p.add_argument("--noise-tau", type=float, default=None,
                   help="record the joints' efforts with this noise, N m (default: no efforts)")  # fmt: skip
    p.add_argument("--amplitude", type=float, default=None, help="the excitation's amplitude, rad (excite's)")
    p.add_argument("--speed", type=float, default=None, help="the excitation's speed cap, rad/s (excite's)")
    p.add_argument("--verbose", action="store_true", help="every joint's errors")
    p.add_argument("--timestep", type=float, default=None, help="the fit's replay step, s (default: calibrate's)")
    p.add_argument(
        "--generator",
        choices=["actuators", "applied"],
        default="actuators",
        help="the robot: MuJoCo's actuators under implicitfast, or the servo law as a force under RK4",
    )
    args = p.parse_args()
    model = load_model(str(ind.limited_robot(pathlib.Path(tempfile.mkdtemp()))), visual=False)
    for structure in args.structures.split(","):
        for delay in (int(d) for d in args.delays.split(",")):
            r = case(
                model,
                structure,
                delay,
                args.duration,
                args.seed,
                args.noise_q,
                args.noise_dq,
                args.verbose,
                args.timestep,
                args.generator,
                args.noise_tau,
                args.amplitude,
                args.speed,
            )
            print(" | ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()), flush=True)


if __name__ == "__main__":
    main()
