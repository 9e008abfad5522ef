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

``--efforts-only --seeds 0,1,2`` reads each recording's joint efforts alone
(``jaxsync.calibrate.efforts.fit_efforts``, seconds a case) and counts the
gains they call fixed, those of them off the truth by more than 10 % / 20 %,
and how often their 95 % half-widths hold the truth.
"""

from __future__ import annotations

import argparse
import json
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


def recording(model, structure: str, delay: int, duration: float, seed: int, noise_q: float, noise_dq: float,
              generator: str = "actuators", noise_tau: float | None = None, amplitude: float | None = None,
              speed: float | None = None, figures: str = "fr3"):  # fmt: skip
    """One case's recording by the independent generator and its true stiffness and damping: the
    gains drawn within +-25 % of the robot file's (``seed``), ``jaxsync excite``'s trajectory played
    with ``delay`` periods through a servo of ``structure``, sensor noise (efforts where ``noise_tau``
    is given)."""
    nominal = Replay(model).nominal()
    rng = np.random.default_rng(seed)
    n = len(nominal.stiffness)
    kp = nominal.stiffness * rng.uniform(0.75, 1.25, n)
    kv = nominal.damping * rng.uniform(0.75, 1.25, n)
    shape = {k: v for k, v in (("amplitude", amplitude), ("speed", speed)) if v is not None}
    ex = excite.excitation(model, duration=duration, **shape)
    q0 = np.asarray(model.keyframe_qpos("grasp"))
    lim = np.tile(ind.LIMITED[figures].limits, 2)
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
    return rec, kp, kv


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
    figures: str = "fr3",
):
    rec, kp, kv = recording(model, structure, delay, duration, seed, noise_q, noise_dq, generator, noise_tau,
                            amplitude, speed, figures)  # fmt: skip
    n = len(kp)
    start = time.perf_counter()
    say = (lambda text: print(f"  {text}", file=sys.stderr, flush=True)) if verbose else None
    cal = calibrate(model, rec, timestep=timestep, progress=say)[0]
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

    def per_joint(values, truth):
        return [float(v) for v in np.asarray(values) / truth]

    parts = {f"{part}_{field}": per_joint(cal.interval_parts[part][field], truth)
             for part in cal.interval_parts for field, truth in (("stiffness", kp), ("damping", kv))}  # fmt: skip
    detail = {
        "joints": list(cal.joints),
        "stiffness_err": [float(v) for v in cal.fitted.stiffness / kp - 1],
        "damping_err": [float(v) for v in cal.fitted.damping / kv - 1],
        "stiffness_half": per_joint(cal.intervals["stiffness"], kp),
        "damping_half": per_joint(cal.intervals["damping"], kv),
        **parts,
        "from_efforts": list(cal.from_efforts),
        "delay_costs": {str(d): float(c) for d, c in cal.delay_costs.items()},
        "structure_costs": {k: float(c) for k, c in cal.structure_costs.items()},
        **(
            {
                "efforts_stiffness_err": [float(v) for v in cal.efforts.stiffness / kp - 1],
                "efforts_damping_err": [float(v) for v in cal.efforts.damping / kv - 1],
                "efforts_stiffness_half": per_joint(cal.efforts.intervals["stiffness"], kp),
                "efforts_damping_half": per_joint(cal.efforts.intervals["damping"], kv),
            }
            if cal.efforts is not None
            else {}
        ),
        "problems": list(cal.problems),
    }
    return {
        "figures": figures,
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
    }, detail


# the half-widths calibrate states (the largest of the motion's parts, or the efforts' where their gains
# were taken) and each part alone (Calibration.interval_parts)
PARTS = ("jacobian", "windows", "halves", "open_step", "step")
RULES = {"stated": "{field}_half", "largest of the parts": "largest_{field}", **{p: p + "_{field}" for p in PARTS}}


def efforts_only(model, figures: str, structures, delays, seeds, duration: float, noise) -> dict:
    """The joint efforts' reading alone on each case (``--efforts-only``): per case and in total, the
    gains it calls fixed (``efforts.determined``), those wrongly, and its half-widths holding the truth."""
    from jaxsync.calibrate import efforts  # noqa: PLC0415 -- this mode only

    nominal = Replay(model).nominal()
    n = len(nominal.stiffness)
    ex = excite.excitation(model, duration=duration)
    q0 = np.asarray(model.keyframe_qpos("grasp"))
    total = {"gains": 0, "held": 0, "fixed": 0, "fixed_wrongly": 0, "decided_wrongly": 0}
    for seed in seeds:
        rng = np.random.default_rng(seed)
        kp = nominal.stiffness * rng.uniform(0.75, 1.25, n)
        kv = nominal.damping * rng.uniform(0.75, 1.25, n)
        for structure in structures:
            for delay in delays:
                t, q, dq, tau = ind.record_actuators(model.robot.spec, q0, kp, kv, ex.times, ex.commands, delay,
                                                     structure=structure, efforts=True)  # fmt: skip
                q, dq = ind.noisy(q, dq, noise[0], noise[1], seed + 1)
                tau = tau + noise[2] * np.random.default_rng(seed + 2).standard_normal(tau.shape)
                rec = Recording(tuple(ex.joints), t, q, dq, ex.times, ex.commands, effort=tau)
                ef = efforts.fit_efforts(model, rec)
                fixed = efforts.determined(ef, {"stiffness": 0.10, "damping": 0.20})
                ek, eb = np.abs(ef.stiffness - kp), np.abs(ef.damping - kv)
                wrong = fixed & ((ek > 0.10 * kp) | (eb > 0.20 * kv))
                held = int((ek <= ef.intervals["stiffness"]).sum() + (eb <= ef.intervals["damping"]).sum())
                decided_wrongly = ef.decisive() and (ef.structure, ef.delay) != (structure, delay)
                counts = {"gains": 2 * n, "held": held, "fixed": int(fixed.sum()), "fixed_wrongly": int(wrong.sum()),
                          "decided_wrongly": int(decided_wrongly)}  # fmt: skip
                for key, v in counts.items():
                    total[key] += v
                print(f"{figures} {structure} delay {delay} seed {seed}: efforts' {ef.structure} at delay {ef.delay}"
                      f"{' (decisive)' if ef.decisive() else ''}, {int(fixed.sum())} joints fixed, "
                      f"{int(wrong.sum())} wrongly, half-widths hold {held}/{2 * n}", flush=True)  # fmt: skip
    print(f"{figures}: {total}")
    return total


def coverage(path: str) -> None:
    """How often each 95 % half-width held the truth, over every stiffness and damping of every case in
    ``path`` (the motion's fit; gains taken from the efforts are the efforts' own), and over those within
    what calibrate stands behind (10 % stiffness, 20 % damping)."""
    rows = [json.loads(line) for line in open(path)]
    for r in rows:
        for field in ("stiffness", "damping"):
            present = [r[f"{part}_{field}"] for part in PARTS if r.get(f"{part}_{field}") is not None]
            r[f"largest_{field}"] = np.fmax.reduce(np.asarray(present, float)).tolist()
    share = {"stiffness": 0.10, "damping": 0.20}
    print(f"{len(rows)} cases, {sum(len(r['joints']) for r in rows)} joints")
    print("| half-width | covers (all) | covers (within 10 % / 20 %) | median half / error |")
    print("|---|---|---|---|")
    for rule, key in RULES.items():
        hit, n, hit_in, n_in, ratio = 0, 0, 0, 0, []
        for r in rows:
            for field in share:
                if r.get(key.format(field=field)) is None:
                    continue
                err = np.abs(np.asarray(r[f"{field}_err"]))
                half = np.asarray(r[key.format(field=field)], float)
                taken = np.isin(r["joints"], r["from_efforts"])
                if rule != "stated":  # the motion's own intervals: not where the efforts' gains were taken
                    err, half = err[~taken], half[~taken]
                ok = err <= half
                hit, n = hit + ok.sum(), n + ok.size
                inside = half <= share[field]
                hit_in, n_in = hit_in + ok[inside].sum(), n_in + inside.sum()
                ratio += list(half / np.maximum(err, 1e-12))
        if n:
            print(f"| {rule} | {hit / n:.0%} ({hit}/{n}) | {hit_in / max(n_in, 1):.0%} ({hit_in}/{n_in}) | "
                  f"{np.median(ratio):.2g} |")  # fmt: skip


SHORT = (  # a refusal's phrases (fit.problems, efforts.problems), shortened for the table
    (r"efforts do not fix the gains of (\d+)", "efforts leave {} joints open"),
    (r"does not determine the stiffness of (\d+) joint\(s\) to 10% \(worst [^:]+: ([^)]+)\)", "{} stiffnesses {}"),
    (r"does not determine the damping of (\d+) joint\(s\) to 20% \(worst [^:]+: ([^)]+)\)", "{} dampings {}"),
    (r"delays \[([^]]+)\] explain the recording", "delay {} as good"),
    (r"is the last one scanned", "delay at the scan's end"),
    (r"leaves (\d+) joint\(s\) over", "{} residuals over the noise"),
    (r"(\d+) gain\(s\) sit on their bounds", "{} gains on a bound"),
    (r"servo explains the held-out windows within", "structures alike"),
    (r"the joint efforts say", "efforts disagree"),
    (r"efforts and the motion disagree on the (\w+) of (\d+)", "efforts deny the {} of {} joints"),
    (r"the delay found \((\d+) periods\) was fitted", "delay {} with them"),
)


def table(paths: list[str]) -> None:
    """Every case in ``paths`` (jsonl) as a markdown row."""
    import re  # noqa: PLC0415 -- the table only

    print("| robot | structure | delay | found | structure found (margin) | worst stiffness / damping error | "
          "intervals holding the truth | result | seconds |")  # fmt: skip
    print("|---" * 9 + "|")
    for path in paths:
        for line in open(path):
            r = json.loads(line)
            held = sum(int(abs(e) <= h) for f in ("stiffness", "damping")
                       for e, h in zip(r[f"{f}_err"], r[f"{f}_half"], strict=True))  # fmt: skip
            why = []
            for problem in r["problems"]:
                for pattern, text in SHORT:
                    m = re.search(pattern, problem)
                    if m:
                        why.append(text.format(*m.groups()))
                        break
                else:
                    why.append(problem[:40])
            result = "answered" if not r["problems"] else "refused: " + "; ".join(why)
            margin = r["structure_margin"]
            margin = "the efforts'" if margin != margin else f"{1 + margin:.3g}×"  # NaN: the efforts chose alone
            print(f"| {r['figures']} | {r['structure'].replace('_', ' ')} | {r['delay']} | {r['found']} | "
                  f"{r['found_structure'].replace('_', ' ')} ({margin}) | "
                  f"{100 * r['stiffness_err_max']:.1f} / {100 * r['damping_err_max']:.1f} % | "
                  f"{held}/{2 * len(r['joints'])} | {result} | {r['seconds']:.0f} |")  # fmt: skip


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
    p.add_argument("--figures", default="fr3", help=f"the test robots' figures, comma-separated: {list(ind.LIMITED)}")
    p.add_argument("--jsonl", default=None, help="append each case's row and per-joint errors and half-widths here")
    p.add_argument("--timestep", type=float, default=None, help="the fit's replay step, s (default: calibrate's)")
    p.add_argument(
        "--generator",
        choices=["actuators", "applied"],
        default="actuators",
        help="the robot: MuJoCo's actuators under implicitfast, or the servo law as a force under RK4",
    )
    p.add_argument("--efforts-only", action="store_true", help="the joint efforts' reading alone on every case")
    p.add_argument("--seeds", default=None, help="--efforts-only: the gain draws, comma-separated (default --seed)")
    p.add_argument("--coverage", action="store_true", help="read --jsonl and print each interval's coverage")
    p.add_argument("--table", action="store_true", help="read --jsonl (comma-separated) and print every case")
    args = p.parse_args()
    if args.coverage:
        coverage(args.jsonl)
        return
    if args.table:
        table(args.jsonl.split(","))
        return
    if args.efforts_only:
        seeds = [int(x) for x in (args.seeds or str(args.seed)).split(",")]
        for figures in args.figures.split(","):
            model = load_model(str(ind.limited_robot(pathlib.Path(tempfile.mkdtemp()), figures)), visual=False)
            efforts_only(model, figures, args.structures.split(","), [int(d) for d in args.delays.split(",")], seeds,
                         args.duration, (args.noise_q, args.noise_dq, args.noise_tau or 0.05))  # fmt: skip
        return
    for figures in args.figures.split(","):
        run_figures(args, figures)


def run_figures(args, figures: str) -> None:
    model = load_model(str(ind.limited_robot(pathlib.Path(tempfile.mkdtemp()), figures)), visual=False)
    for structure in args.structures.split(","):
        for delay in (int(d) for d in args.delays.split(",")):
            r, detail = case(
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
                figures,
            )
            if args.jsonl:
                with open(args.jsonl, "a") as fh:
                    fh.write(json.dumps({**r, **detail}) + "\n")
            print(" | ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()), flush=True)


if __name__ == "__main__":
    main()
