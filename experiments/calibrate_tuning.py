"""Does tuning on the calibrated stack do as well as tuning on the true one? (docs/calibrate.md)

A UR5e-like pair whose servo (each joint's stiffness and damping drawn
within +-30 % of the robot file's) and delay (2 periods at 500 Hz) are
known: its robot file is written; the default excitation is played on it on
MuJoCo C (0.5 ms, implicitfast, sensor noise), written as a bag and fitted
by ``jaxsync calibrate``; the fitted lines make the calibrated robot file.
Then ``jaxsync tune --actuation position`` runs on each file, the same run
otherwise, and both tuned gains (and the defaults) are scored on the true
stack's held-out scenarios (the tuner's own held-out seed). With
``--perturbed``, a third run tunes on the true stack with each servo gain
moved at random by up to the calibration's largest error: how far the
tuner's result moves under a model change of that size, whatever its source;
``--perturb-size REL`` moves them by up to REL instead (1e-6: far below any
calibration's error, the tuner's own spread under a model change).

    python experiments/calibrate_tuning.py --out results/calibrate_tuning --perturbed --weight grip_smooth=0.001
    python experiments/calibrate_tuning.py --out results/calibrate_tuning --perturb-size 1e-6 --weight grip_smooth=0.001
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import jax
import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import independent_servo as ind  # noqa: E402  (the tests' independent generator and published figures)

from jaxsync.calibrate import excite, replay
from jaxsync.calibrate.jobs import calibrate_job
from jaxsync.cli import main as cli
from jaxsync.io import bags
from jaxsync.physics.model import load_model
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags

ROBOTS = Path(__file__).resolve().parents[1] / "mjcf" / "robots"


def _robot_file(path: Path, doc: dict, arm_file: str, arm_dir: Path = ROBOTS) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(arm_dir / arm_file, path.parent / arm_file)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _score(robot: Path, gains: dict, controller: str, delay: int, heldout: int = 16) -> dict:
    # the tuner's pieces are imported here: only the scoring needs them
    from jaxsync.control.gains import default_gains
    from jaxsync.io import gains_file
    from jaxsync.optimize.tuning import loss as L
    from jaxsync.optimize.tuning import scenarios as S
    from jaxsync.optimize.tuning.config import TuneConfig
    from jaxsync.sim.actuation import Stack

    model = load_model(str(robot), visual=False)
    stack = Stack("position", None, (delay, delay))
    cfg = TuneConfig(actuation="position", delay=(delay, delay), heldout_batch=heldout)
    cfg = cfg.replace(scenario=S.model_overrides(model))
    held = S.heldout_scenarios(cfg)
    ev = L.make_evaluator(model, 4.0, controller, **stack.rollout_options(model))
    out = {}
    cands = {"defaults": default_gains(model, "position"), **{k: gains_file.load(v) for k, v in gains.items()}}
    for label, g in cands.items():
        s = L.eval_summary(ev(g, held))
        out[label] = {k: s[k] for k in ("settled_peak_resultant_N", "grip_force_error_rel", "dropped", "chattering")}
        print(label, json.dumps(out[label]), flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--iterations", default="60")
    p.add_argument("--controller", default="synchronous")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--score-only", action="store_true", help="score the tuned gains already in --out")
    p.add_argument(
        "--heldout", type=int, default=16, help="held-out scenarios to score on (the tuner's seed; 16 as the tuner)"
    )
    p.add_argument(
        "--tune-seed", type=int, default=0, help="the tuner's training seed (a robot pair in --out is reused)"
    )
    p.add_argument(
        "--robust", action="store_true", help="tune over drawn servos and delays (--servo-spread 0.3 --delay 1:3)"
    )
    p.add_argument(
        "--weight", action="append", default=[], metavar="NAME=VALUE", help="a tuning cost weight (jaxsync tune's)"
    )
    p.add_argument(
        "--resume", action="store_true", help="continue the tuning runs in --out (e.g. with more --iterations)"
    )
    p.add_argument(
        "--figures", choices=sorted(ind.LIMITED), default=None,
        help="instead of the UR5e-like pair: the test arm with this published arm's torque limits, friction loss "
        "and servo (tests/independent_servo.py), recorded by MuJoCo's own actuators with joint efforts",
    )  # fmt: skip
    p.add_argument("--structure", choices=sorted(ind.STRUCTURES), default="feedforward",
                   help="the true servo's structure (feedforward)")  # fmt: skip
    p.add_argument("--method", default="lbfgs", help="the tuner's method (jaxsync tune --method)")
    p.add_argument("--lr", default=None, help="a first-order method's learning rate (jaxsync tune --lr)")
    p.add_argument(
        "--starts", type=int, default=1, help="tuning starts per run (jaxsync tune --starts; seeds from --tune-seed)"
    )
    p.add_argument(
        "--perturbed", action="store_true", help="also tune on the true stack moved by the calibration's largest error"
    )
    p.add_argument(
        "--perturb-size", type=float, default=None, metavar="REL",
        help="instead: the true stack's servo gains moved at random by up to REL (e.g. 1e-6; folder perturbed_REL)",
    )  # fmt: skip
    p.add_argument(
        "--table", type=lambda t: [int(x) for x in t.split(",")], metavar="SEEDS",
        help="print the scored runs of training seeds SEEDS (e.g. 0,1,2,3) as a table, with medians; runs nothing",
    )  # fmt: skip
    args = p.parse_args()
    if args.perturb_size is not None and not 0 < args.perturb_size < 1:
        p.error(f"--perturb-size must be in (0, 1), got {args.perturb_size}")
    args.perturbed = args.perturbed or args.perturb_size is not None
    set_xla_flags()  # before the first JAX computation
    jax.config.update("jax_enable_x64", True)
    enable_compilation_cache()
    out = Path(args.out)
    if args.figures:  # the published figures' test robot, its arm MJCF written beside it
        arm_dir = out / "arm"
        arm_dir.mkdir(parents=True, exist_ok=True)
        base_file = ind.limited_robot(arm_dir, args.figures)
    else:
        arm_dir, base_file = ROBOTS, ROBOTS / "ur5e_twice.yaml"
    doc = yaml.safe_load(base_file.read_text())
    arm_file = doc["arms"]["right"]["model"]
    model = load_model(str(base_file), visual=False)
    nom = replay.Replay(model).nominal()
    rng = np.random.default_rng(args.seed)
    n = len(nom.stiffness)
    truth = nom.replace(
        stiffness=nom.stiffness * rng.uniform(0.7, 1.3, n), damping=nom.damping * rng.uniform(0.7, 1.3, n)
    )
    half = n // 2
    true_doc = dict(doc)
    w, f = ind.STRUCTURES[args.structure]
    true_doc["servo"] = {
        "weight_compensation": bool(w),
        "velocity_feedforward": bool(f),
        **{
            arm: {"stiffness": truth.stiffness[sl].tolist(), "damping": truth.damping[sl].tolist()}
            for arm, sl in (("right", slice(0, half)), ("left", slice(half, n)))
        },
    }
    true_doc["delay"] = {"periods": 2, "control_rate": 500}
    true_file = out / "true" / "robot.yaml"
    cal_file = out / "calibrated" / "robot.yaml"
    pert_file = out / ("perturbed" if args.perturb_size is None else f"perturbed_{args.perturb_size:g}") / "robot.yaml"
    if args.table:
        _table(out, {s: _tag(args, s) for s in args.table})
        return
    tag = _tag(args, args.tune_seed)
    gains = {"tuned on the true stack": str(out / f"tune_true{tag}" / "gains.json"),
             "tuned on the calibrated stack": str(out / f"tune_calibrated{tag}" / "gains.json"),
             "true stack, last iterate": str(out / f"tune_true{tag}" / "gains_last.json"),
             "calibrated stack, last iterate": str(out / f"tune_calibrated{tag}" / "gains_last.json")}  # fmt: skip
    pert = pert_file if args.perturbed else None
    if args.perturbed:
        gains["tuned on the perturbed stack"] = str(out / f"tune_{pert_file.parent.name}{tag}" / "gains.json")
        gains["perturbed stack, last iterate"] = str(out / f"tune_{pert_file.parent.name}{tag}" / "gains_last.json")
    if args.score_only:
        _report(out, true_file, cal_file, gains, args.controller, tag, args.heldout, pert)
        return
    if true_file.exists() and cal_file.exists():  # the pair calibrated before: tune again only
        if args.perturb_size is not None and not pert_file.exists():
            _perturb(true_file, pert_file, args.perturb_size, rng, arm_file, arm_dir)
        _tune([true_file, cal_file] + ([pert_file] if args.perturbed else []), args, tag)
        _report(out, true_file, cal_file, gains, args.controller, tag, args.heldout, pert)
        return
    _robot_file(true_file, true_doc, arm_file, arm_dir)
    ex = excite.excitation(model)
    if args.figures:  # MuJoCo's own actuators (implicitfast, 0.25 ms), nothing of jaxsync's servo or replay
        q0 = np.asarray(model.keyframe_qpos("grasp"))
        t, q, dq, tau = ind.record_actuators(model.robot.spec, q0, truth.stiffness, truth.damping, ex.times,
                                             ex.commands, 2, structure=args.structure, efforts=True)  # fmt: skip
        q, dq = ind.noisy(q, dq, 1e-4, 5e-3, seed=args.seed + 1)
        tau = tau + 0.05 * np.random.default_rng(args.seed + 2).standard_normal(tau.shape)
        rec = bags.Recording(ex.joints, t, q, dq, ex.times, ex.commands, effort=tau)
    else:
        t, q, dq = replay.record(model, truth, ex.times, ex.commands, 2, timestep=0.0005, integrator="implicitfast",
                                 noise_q=1e-5, noise_dq=5e-4, seed=args.seed)  # fmt: skip
        rec = bags.Recording(ex.joints, t, q, dq, ex.times, ex.commands)
    bag = bags.write_recording(out / "recording", rec)
    start = time.perf_counter()
    # a refused calibration is tuned on as written (--force): how much its errors cost is the question
    cal = calibrate_job(out / "calibration", model, bag, report=False, force=True)["calibration"]
    if cal.problems:
        print("calibrate refused (written with --force): " + "; ".join(cal.problems), flush=True)
    print(f"calibrated in {time.perf_counter() - start:.0f} s: delay {cal.delay}, largest stiffness error "
          f"{100 * np.abs(cal.fitted.stiffness / truth.stiffness - 1).max():.2f} %", flush=True)  # fmt: skip
    cal_doc = dict(doc) | yaml.safe_load((out / "calibration" / "calibration.yaml").read_text())
    _robot_file(cal_file, cal_doc, arm_file, arm_dir)
    # the same size of model change as the calibration's, in random directions
    worst = max(
        np.abs(cal.fitted.stiffness / truth.stiffness - 1).max(), np.abs(cal.fitted.damping / truth.damping - 1).max()
    )
    moved = truth.replace(stiffness=truth.stiffness * (1 + rng.uniform(-worst, worst, n)),
                          damping=truth.damping * (1 + rng.uniform(-worst, worst, n)))  # fmt: skip
    pert_doc = dict(true_doc)
    pert_doc["servo"] = {
        **true_doc["servo"],  # the structure's flags
        **{
            arm: {"stiffness": moved.stiffness[sl].tolist(), "damping": moved.damping[sl].tolist()}
            for arm, sl in (("right", slice(0, half)), ("left", slice(half, n)))
        },
    }
    if args.perturb_size is None:
        _robot_file(pert_file, pert_doc, arm_file, arm_dir)
        print(f"perturbed stack: every servo gain moved by up to {100 * worst:.2f} %", flush=True)
    else:
        _perturb(true_file, pert_file, args.perturb_size, rng, arm_file, arm_dir)
    _tune([true_file, cal_file] + ([pert_file] if args.perturbed else []), args, tag)
    _report(out, true_file, cal_file, gains, args.controller, tag, args.heldout, pert)


def _tag(args, seed: int) -> str:
    """The run's name in the folder: its training seed and whatever differs from the default run."""
    tag = ("" if seed == 0 else f"_seed{seed}") + ("_robust" if args.robust else "")
    tag += ("" if args.method == "lbfgs" else f"_{args.method}") + ("" if args.lr is None else f"_lr{args.lr}")
    return tag + "".join("_" + w.replace("=", "") for w in args.weight) + (f"_starts{args.starts}" * (args.starts > 1))


def _table(out: Path, tags: dict[int, str]) -> None:
    """The scored runs of each seed as a table (markdown): every tuned gain set's held-out
    settled peak on the true stack, over the true-stack tune of the same seed; then the
    median and the geometric mean over the seeds of each column."""
    cols: dict[str, dict[int, float | None]] = {}
    for seed, tag in tags.items():
        files = sorted(out.glob(f"scores{tag}.json")) + sorted(out.glob(f"scores{tag}_perturbed*.json"))
        if not files:
            raise SystemExit(f"--table: no scores{tag}.json in {out} (score seed {seed} first: --score-only)")
        for f in files:
            on_true = json.loads(f.read_text())["on the true stack"]
            # the pair's own file gives the true and calibrated tunes, a perturbed stack's file its own
            pert = f.stem[len(f"scores{tag}_") :] if f.stem != f"scores{tag}" else None
            picked = {pert: "perturbed"} if pert else {"true": "true", "calibrated": "calibrated"}
            for col, stack in picked.items():
                cols.setdefault(col, {})[seed] = on_true[f"tuned on the {stack} stack"]["settled_peak_resultant_N"]
    names = list(cols)
    print("| training | " + " | ".join(names) + " |")
    print("|---" * (len(names) + 1) + "|")
    for seed in tags:
        base = cols["true"].get(seed)
        cells = [_cell(cols[c].get(seed), None if c == "true" else base) for c in names]
        print(f"| seed {seed} | " + " | ".join(cells) + " |")
    for stat, fn in (("median", np.median), ("geometric mean", lambda v: float(np.exp(np.mean(np.log(v)))))):
        vals = {c: [v for v in cols[c].values() if v is not None] for c in names}
        row = {c: float(fn(v)) if len(v) == len(tags) else None for c, v in vals.items()}
        print(f"| {stat} | " + " | ".join(_cell(row[c], None if c == "true" else row["true"]) for c in names) + " |")


def _cell(v, base) -> str:
    if v is None:
        return "n/a"
    return f"{v:.5f} N" + ("" if base is None else f" ({v / base:.2f}x)")


def _perturb(true_file: Path, pert_file: Path, size: float, rng, arm_file: str, arm_dir: Path = ROBOTS) -> None:
    """The true robot file with each servo gain moved at random by up to ``size`` (relative)."""
    doc = yaml.safe_load(true_file.read_text())
    doc["servo"] = {
        arm: {key: (np.asarray(v) * (1 + rng.uniform(-size, size, len(v)))).tolist() for key, v in gains.items()}
        if isinstance(gains, dict)
        else gains  # the structure's flags
        for arm, gains in doc["servo"].items()
    }
    _robot_file(pert_file, doc, arm_file, arm_dir)
    print(f"perturbed stack: every servo gain moved by up to {100 * size:.2g} %", flush=True)


def _tune(robots: list[Path], args, tag: str) -> None:
    """The same tuning run on each robot file."""
    for robot in robots:
        label = f"tuned on the {robot.parent.name} stack"
        dest = robot.parent.parent / f"tune_{robot.parent.name}{tag}"
        if (dest / "summary.json").exists() and not args.resume:
            print(f"{label}: finished in {dest}, kept", flush=True)
            continue
        start = time.perf_counter()
        robust = ["--servo-spread", "0.3", "--delay", "1:3"] if args.robust else []
        rc = cli(["tune", "--robot", str(robot), "--no-visual", "--actuation", "position", "--controller",
                  args.controller, "--method", args.method, "--iterations", args.iterations,
                  "--seed", str(args.tune_seed), "--out", str(dest), "--starts", str(args.starts), *robust,
                  *(["--resume"] if args.resume else []), *(["--lr", args.lr] if args.lr is not None else []),
                  *(a for w in args.weight for a in ("--weight", w))])  # fmt: skip
        print(f"{label}: exit {rc}, {time.perf_counter() - start:.0f} s", flush=True)


def _report(
    out: Path,
    true_file: Path,
    cal_file: Path,
    gains: dict,
    controller: str,
    tag: str = "",
    heldout: int = 16,
    pert_file: Path | None = None,
) -> None:
    """Both tuned gains on the true stack (the target) and on the calibrated one (does the model
    predict what the gains do on the robot?)."""
    scores = {"on the true stack": _score(true_file, gains, controller, 2, heldout),
              "on the calibrated stack": _score(cal_file, gains, controller, 2, heldout)}  # fmt: skip
    # a gain set that dropped the object in every scenario has no settled peak: no ratio, "n/a"
    peak = [scores["on the true stack"][k]["settled_peak_resultant_N"] for k in gains]
    scores["calibrated_over_true"] = {"selected": _ratio(peak[1], peak[0]), "last iterate": _ratio(peak[3], peak[2])}
    if len(peak) > 4:
        scores["perturbed_over_true"] = {"selected": _ratio(peak[4], peak[0]), "last iterate": _ratio(peak[5], peak[2])}
        print(f"perturbed-tuned / true-tuned: selected {_line(peak[4], peak[0])}; "
              f"last iterates {_line(peak[5], peak[2])}", flush=True)  # fmt: skip
    print(f"held-out settled peak on the true stack, calibrated-tuned / true-tuned: selected gains "
          f"{_line(peak[1], peak[0])}; last iterates {_line(peak[3], peak[2])}", flush=True)  # fmt: skip
    suffix = ("" if heldout == 16 else f"_heldout{heldout}") + (
        "" if pert_file is None else "_" + pert_file.parent.name
    )
    (out / f"scores{tag}{suffix}.json").write_text(json.dumps(scores, indent=1, default=float))


def _ratio(a, b):
    return None if a is None or b is None else a / b


def _line(a, b) -> str:
    def f(v, digits=5):
        return "n/a" if v is None else f"{v:.{digits}f}"

    return f"{f(a)} / {f(b)} N = {f(_ratio(a, b), 3)}"


if __name__ == "__main__":
    main()
