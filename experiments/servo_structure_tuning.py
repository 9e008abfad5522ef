"""What tuning on the wrong servo law costs (docs/servo.md).

A robot with joint torque limits, friction loss and a servo as a published
arm has them (``tests/independent_servo.py``: the iiwa-like arm with the
Franka FR3's figures), its servo as written (MuJoCo's ``<position>``: no
weight compensation, no velocity feed-forward). ``jaxsync tune
--actuation position`` runs twice with everything else equal: on the true
stack, and on the same robot whose robot file states the law the position
stack used to assume for every robot (weight-compensated, the command's
velocity fed forward). Both tuned gain sets and the true stack's defaults
are then scored on the true stack's 16 held-out scenarios at each delay
(``experiments/position_defaults.py``).

    python experiments/servo_structure_tuning.py --iterations 30 --out results/servo_structure
"""

from __future__ import annotations

import argparse
import pathlib
import subprocess
import sys

import yaml

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests"))
import independent_servo as ind  # noqa: E402  (the tests' robot with published limits)

HERE = pathlib.Path(__file__).resolve().parent


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="results/servo_structure")
    p.add_argument("--iterations", type=int, default=30)
    p.add_argument("--controller", default="synchronous")
    p.add_argument("--delays", default="0,1,2,3")
    args = p.parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    truth = ind.limited_robot(out)
    doc = yaml.safe_load(truth.read_text())
    doc["servo"] = {**doc["servo"], "weight_compensation": True, "velocity_feedforward": True}
    assumed = out / "assumed_pair.yaml"
    assumed.write_text(yaml.safe_dump(doc))
    tuned = {}
    for label, robot in (("as_written", truth), ("assumed", assumed)):
        folder = out / f"tune_{label}"
        if not (folder / "gains.json").exists():
            cmd = ["jaxsync", "tune", "--robot", str(robot), "--no-visual", "--actuation", "position",
                   "--delay", "0:3", "--servo-spread", "0.3", "--controller", args.controller,
                   "--iterations", str(args.iterations), "--out", str(folder)]  # fmt: skip
            print("$", " ".join(cmd), flush=True)
            subprocess.run(cmd, check=True)
        tuned[label] = folder / "gains.json"
    score = [sys.executable, str(HERE / "position_defaults.py"), "--robot", str(truth), "--controllers",
             args.controller, "--filters", "1", "--delays", args.delays, "--any-model"]  # fmt: skip
    for label, path in tuned.items():
        score += ["--gains", f"tuned_on_{label}={path}"]
    print("$", " ".join(score), flush=True)
    subprocess.run(score, check=True)


if __name__ == "__main__":
    main()
