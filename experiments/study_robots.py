"""The fair study on the paper model and on each test robot, one folder each.

Runs ``jaxsync study`` (its defaults unless told) for the paper model and
for every robot file given (default: the test robots in ``mjcf/robots``),
each into ``OUT/<name>``, resumable: a stopped run continues where it
stopped when started again. Prints each study's table.

    python experiments/study_robots.py --out results/study_robots
    python experiments/study_robots.py mjcf/robots/ur5e_twice.yaml --iterations 4 --seeds 0,1,2
"""

from __future__ import annotations

import argparse
import glob
import os
import subprocess
import sys


def main() -> int:
    here = os.path.dirname(os.path.abspath(__file__))
    robots = sorted(glob.glob(os.path.join(here, "..", "mjcf", "robots", "*.yaml")))
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("robots", nargs="*", default=None, help="robot files (default: the test robots and the paper model)")
    p.add_argument("--out", default="results/study_robots", help="output folder (results/study_robots)")
    args, study_args = p.parse_known_args()  # the rest goes to jaxsync study as given
    models = [(name, path) for path in (args.robots or robots) for name in [os.path.basename(path).split(".")[0]]]
    if not args.robots:
        models.insert(0, ("paper", None))
    exe = os.path.join(os.path.dirname(sys.executable), "jaxsync")
    status = 0
    for name, path in models:
        out = os.path.join(args.out, name)
        cmd = [exe, "study", "--out", out, *study_args]
        if path is not None:
            cmd += ["--robot", path]
        if os.path.exists(os.path.join(out, "study.json")):
            cmd.append("--resume")
        print(f"== {name}: {' '.join(cmd)}", flush=True)
        rc = subprocess.call(cmd)
        if rc != 0:
            print(f"== {name}: jaxsync study exited {rc}", file=sys.stderr, flush=True)
            status = status or rc
    return status


if __name__ == "__main__":
    sys.exit(main())
