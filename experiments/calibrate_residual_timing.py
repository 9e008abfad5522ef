"""The calibrate fit's residual against ``mujoco.sysid``'s, timed interleaved in one run.

One recording of the FR3-figures test robot (``calibrate_independent.recording``:
MuJoCo's own actuators, gains moved within +-25 %, sensor noise), cut into
the fit's windows; then, round after round, the toolbox's
``build_residual_fn`` (the same rollout and residual hooks: a model and a
scratch MjData per window and column) and the fit's own residual
(``Problem.residual_fn``: each column's model once, every window of every
column in one threaded rollout) on the same finite-difference columns, the
order alternating between rounds. Checks the two give the same numbers and
prints each call's seconds and their ratio.

    python experiments/calibrate_residual_timing.py --rounds 6
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests"))
import independent_servo as ind  # noqa: E402  (the tests' independent generator)
from calibrate_independent import recording  # noqa: E402  (its cases' recording)

from jaxsync.calibrate import fit  # noqa: E402
from jaxsync.physics.model import load_model  # noqa: E402
from jaxsync.physics.servo import STRUCTURES  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--figures", default="fr3", help=f"the test robot's figures: {list(ind.LIMITED)}")
    p.add_argument("--structure", default="weight_compensated", choices=list(STRUCTURES))
    p.add_argument("--delay", type=int, default=0)
    p.add_argument("--duration", type=float, default=20.0, help="the excitation, s (calibrate's default 20)")
    p.add_argument("--rounds", type=int, default=6)
    args = p.parse_args()

    model = load_model(str(ind.limited_robot(pathlib.Path(tempfile.mkdtemp()), args.figures)), visual=False)
    rec = recording(model, args.structure, args.delay, args.duration, 0, 1e-4, 5e-3, figures=args.figures)[0]

    prob = fit.Problem(model, rec, 0.5, structure=STRUCTURES[args.structure])
    pd = prob.parameters(prob.replay.nominal(), fit.FACTORS)
    prob.delay = args.delay
    m = prob.replay.m
    toolbox = prob.sysid.build_residual_fn(models_sequences=[prob.sequences], build_model=lambda p, s, m=m: m,
                                           custom_rollout=prob._rollout, modify_residual=prob._residual,
                                           resample_true=False, n_threads=1)  # fmt: skip
    x = pd.as_vector()
    cols = np.column_stack([x, *(x + 1e-3 * np.eye(pd.size)[:, i] for i in range(pd.size))])  # one Jacobian's
    windows = len(prob.sequences.measured_rollout)
    print(f"{args.figures} figures, {args.structure}, delay {args.delay}: {windows} windows, {cols.shape[1]} columns")
    for label, point in (("a Jacobian's columns", cols), ("one point", x)):
        a, b = timed(point, {"toolbox": toolbox, "fit": prob.residual_fn}, pd, args.rounds)
        print(f"{label}, median of {args.rounds}: toolbox {a:.3f} s, fit {b:.3f} s: {a / b:.2f}x", flush=True)


def timed(point, fns, pd, rounds):
    """The median seconds of each residual on ``point``, the order alternating between rounds."""
    seconds = {name: [] for name in fns}
    for r in range(rounds):
        out = {}
        for name in list(fns)[:: 1 if r % 2 == 0 else -1]:
            start = time.perf_counter()
            out[name] = fns[name](point, pd.copy())[0]
            seconds[name].append(time.perf_counter() - start)
        same = all(np.array_equal(a, b) for a, b in zip(out["toolbox"], out["fit"], strict=True))
        print(f"  round {r}: " + ", ".join(f"{k} {v[-1]:.3f} s" for k, v in seconds.items())
              + f", same numbers: {same}", flush=True)  # fmt: skip
        if not same:
            raise SystemExit("the two residuals differ")
    return statistics.median(seconds["toolbox"]), statistics.median(seconds["fit"])


if __name__ == "__main__":
    main()
