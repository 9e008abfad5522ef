"""How well ``jaxsync calibrate`` finds a known servo and delay, and how long it takes (docs/calibrate.md).

A recording made on MuJoCo C: the excitation (``jaxsync excite``'s
defaults, 20 s at 500 Hz) played through a servo whose every joint's
stiffness and damping are off the robot file's by up to 30 % (drawn), a
known delay, sensor noise, at a physics step and integrator of the
``--record-step`` / ``--record-integrator`` given; written as a bag and
fitted by ``calibrate_job`` (the command's job) with the replay at
``--fit-step`` (default: the model's). Prints the delay found, each
stiffness' and damping's error and the wall time.

    python experiments/calibrate_accuracy.py --robot mjcf/robots/ur5e_twice.yaml
    python experiments/calibrate_accuracy.py --record-step 0.0005 --record-integrator implicitfast
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from jaxsync.calibrate import excite, replay
from jaxsync.calibrate.jobs import calibrate_job
from jaxsync.calibrate.replay import replay_step
from jaxsync.io import bags
from jaxsync.physics.model import load_model
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="mjcf/robots/ur5e_twice.yaml")
    p.add_argument("--delay", type=int, default=2)
    p.add_argument("--spread", type=float, default=0.3)
    p.add_argument("--record-step", type=float, default=0.002)
    p.add_argument("--record-integrator", default="euler")
    p.add_argument("--fit-step", type=float, default=None)
    p.add_argument("--noise-q", type=float, default=1e-5, help="rad")
    p.add_argument("--noise-dq", type=float, default=5e-4, help="rad/s")
    p.add_argument("--delays", default="0:4")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", default=None, help="keep the bag and the results here")
    args = p.parse_args()
    set_xla_flags()  # before the first JAX computation
    jax.config.update("jax_enable_x64", True)
    enable_compilation_cache()
    model = load_model(args.robot, visual=False)
    ex = excite.excitation(model)
    nom = replay.Replay(model).nominal()
    rng = np.random.default_rng(args.seed)
    n = len(nom.stiffness)
    lo, hi = 1 - args.spread, 1 + args.spread
    truth = nom.replace(stiffness=nom.stiffness * rng.uniform(lo, hi, n), damping=nom.damping * rng.uniform(lo, hi, n))
    t, q, dq = replay.record(model, truth, ex.times, ex.commands, args.delay, timestep=args.record_step,
                             integrator=args.record_integrator, noise_q=args.noise_q, noise_dq=args.noise_dq,
                             seed=args.seed)  # fmt: skip
    root = Path(args.out or tempfile.mkdtemp(prefix="jaxsync_cal_"))
    bag = bags.write_recording(root / "recording", bags.Recording(ex.joints, t, q, dq, ex.times, ex.commands))
    a, _, b = args.delays.partition(":")
    start = time.perf_counter()
    out = calibrate_job(root / "calibration", model, bag, delays=range(int(a), int(b or a) + 1),
                        timestep=args.fit_step, report=False, progress=print)  # fmt: skip
    wall = time.perf_counter() - start
    cal = out["calibration"]
    k_err = 100 * (cal.fitted.stiffness / truth.stiffness - 1)
    b_err = 100 * (cal.fitted.damping / truth.damping - 1)
    result = {
        "robot": args.robot,
        "recording": {
            "seconds": float(t[-1]),
            "rate_Hz": ex.rate,
            "step_s": args.record_step,
            "integrator": args.record_integrator,
            "noise": [args.noise_q, args.noise_dq],
        },  # fmt: skip
        "fit_step_s": args.fit_step or replay_step(model),
        "delay_true": args.delay,
        "delay_found": cal.delay,
        "stiffness_error_pct": np.round(k_err, 2).tolist(),
        "damping_error_pct": np.round(b_err, 2).tolist(),
        "largest_stiffness_error_pct": float(np.abs(k_err).max()),
        "rms_before_urad": np.round(cal.rms_before * 1e6, 1).tolist(),
        "rms_after_urad": np.round(cal.rms_after * 1e6, 1).tolist(),
        "wall_s": wall,
        "fit_s": cal.seconds,
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
