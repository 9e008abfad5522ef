"""The two jobs behind ``jaxsync excite`` and ``jaxsync calibrate``: files in, files out.

Each writes into a new folder beside ``out`` and moves it there complete, so
an interrupted or failed run leaves nothing half-written.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import yaml

from jaxsync._errors import ConfigError, UntrustedResultError
from jaxsync.calibrate import excite as _excite
from jaxsync.calibrate import sensor as _sensor
from jaxsync.calibrate.fit import calibrate
from jaxsync.calibrate.replay import UNITS
from jaxsync.io import bags
from jaxsync.physics.servo import STRUCTURES


@contextlib.contextmanager
def _new_folder(out):
    """A temporary folder that becomes ``out`` when the block ends without an error."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"{out} exists and is not an empty folder", inputs=("out",))
    parent = out.parent if str(out.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=parent))
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # a folder like any other, not mkdtemp's private one
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def excite_job(out, model, *, command_topic: str = bags.COMMAND_TOPIC, storage: str = "mcap", **kw) -> dict:
    """``out``/excitation (a rosbag2 of the commands), excitation.csv and excitation.yaml (what it is)."""
    ex = _excite.excitation(model, **kw)
    with _new_folder(out) as tmp:
        store = bags._typestore()
        msgs = [(command_topic, bags.MULTI_ARRAY, 1.0e9 + t, bags.multi_array(c, store))
                for t, c in zip(ex.times, ex.commands, strict=True)]  # fmt: skip
        bags.write_bag(tmp / "excitation", msgs, storage)
        _excite.write_csv(tmp / "excitation.csv", ex)
        about = ex.describe() | {"command_topic": command_topic, "message_type": bags.MULTI_ARRAY,
                                 "controller_joints": list(ex.joints)}  # fmt: skip
        (tmp / "excitation.yaml").write_text(yaml.safe_dump(about, sort_keys=False))
    return about


def fragment(cal, source: str, model_name: str, noise=None) -> str:
    """The robot-file lines ``--robot`` reads: ``servo:`` per arm, ``delay:``, for what ``--fit``
    added ``joint_dynamics:`` per arm (the MJCF joints' damping, friction loss, armature), and with
    ``noise`` (a :class:`jaxsync.calibrate.sensor.SensorNoise`) ``sensor:``."""
    n = len(cal.joints) // 2
    rnd = lambda a: [float(f"{v:.6g}") for v in a]  # noqa: E731
    arms = (("right", slice(0, n)), ("left", slice(n, 2 * n)))
    w, f = STRUCTURES[cal.structure]
    doc = {
        "servo": {"weight_compensation": w, "velocity_feedforward": f,
                  **{arm: {"stiffness": rnd(cal.fitted.stiffness[sl]), "damping": rnd(cal.fitted.damping[sl])}
                     for arm, sl in arms}},
        "delay": {"periods": int(cal.delay), "control_rate": float(f"{1.0 / cal.period:.6g}")},
    }  # fmt: skip
    extra = [f for f in cal.fields if f not in ("stiffness", "damping")]
    if extra:  # the replay's names -> the robot file's (the MJCF joint attributes)
        key = {"joint_damping": "damping", "frictionloss": "frictionloss", "armature": "armature"}
        doc["joint_dynamics"] = {arm: {key[f]: rnd(getattr(cal.fitted, f)[sl]) for f in extra} for arm, sl in arms}
    if noise is not None:
        doc["sensor"] = {"force_noise": rnd([noise.force_noise])[0], "torque_noise": rnd([noise.torque_noise])[0]}
    head = (
        f"# jaxsync calibrate, {datetime.date.today().isoformat()}: {source} on {model_name}\n"
        f"# the servo's structure ({cal.structure}"
        + (f"; the next {1 + cal.structure_margin:.3g}x its cost on held-out windows" if cal.structure_margin else "")
        + ")\n# each joint's servo (N m/rad, N m s/rad; joints in the robot file's order) and the command delay"
        + (
            "; joint_dynamics: the MJCF joints' damping (N m s/rad), frictionloss (N m), armature (kg m^2)"
            if extra
            else ""
        )
        + ("; sensor: the wrist sensors' white noise (N, N m)" if noise is not None else "")
        + ";\n# put these keys in the robot file (they replace its servo:)\n"
    )
    return head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)


def _plot(path, prob, pd0, pd, title: str) -> None:
    # matplotlib is imported here, not at the top: only the job that draws loads it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after choosing the file backend: no display needed

    _, t, q_rec, q0 = prob.tracking(pd0)
    _, _, _, q1 = prob.tracking(pd)
    n = len(prob.names) // 2
    fig, axes = plt.subplots(n, 2, figsize=(12, 1.7 * n + 1), sharex=True, squeeze=False)
    for a in range(2):
        for j in range(n):
            ax, c = axes[j, a], a * n + j
            ax.plot(t, 1e3 * (q0[:, c] - q_rec[:, c]), ".", ms=1, color="tab:red", label="before the fit")
            ax.plot(t, 1e3 * (q1[:, c] - q_rec[:, c]), ".", ms=1, color="tab:blue", label="fitted")
            ax.set_ylabel(f"{prob.names[c]}\nmrad", fontsize=7)
            ax.tick_params(labelsize=7)
            motion = ax.twinx()  # the recorded motion, for where the errors happen
            motion.plot(t, q_rec[:, c], ",", color="0.6")
            motion.tick_params(labelsize=6, colors="0.5")
    axes[0, 0].legend(fontsize=7, markerscale=8, loc="upper right", title="simulated - recorded", title_fontsize=7)
    axes[-1, 0].set_xlabel("s (grey: the recorded joint position, rad, right axis)")
    axes[-1, 1].set_xlabel("s")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def calibrate_job(
    out,
    model,
    bag,
    *,
    state_topic: str = bags.STATE_TOPIC,
    command_topic: str = bags.COMMAND_TOPIC,
    joints=None,
    command_joints=None,
    min_samples: int = 500,
    report: bool = True,
    progress=None,
    wrench_topics=(),
    force: bool = False,
    **fit_kw,
) -> dict:
    """Read ``bag``, fit, and write ``out``: calibration.yaml (the robot-file lines), calibration.json
    (every figure), calibration.png (recorded against simulated) and report/report.html (the toolbox's).
    ``wrench_topics`` (right arm's sensor, then left's): their noise while still, for ``sensor:``.

    Raises:
      UntrustedResultError: a calibration the recording does not support (``Calibration.problems``),
        nothing written; ``force``: written, each problem a WARNING in calibration.yaml."""

    names = tuple(joints) if joints else _excite.bag_joint_names(model)
    if len(names) != len(_excite.bag_joint_names(model)):
        raise ConfigError(f"joints: {len(names)} names given, the robot has {len(_excite.bag_joint_names(model))}",
                          inputs=("joints",))  # fmt: skip
    if wrench_topics and len(wrench_topics) != 2:
        raise ConfigError(f"wrench_topics: one per arm, right then left, got {list(wrench_topics)}",
                          inputs=("wrench_topics",))  # fmt: skip
    rec = bags.read_recording(bag, names, state_topic, command_topic, command_joints, min_samples, wrench_topics)
    rec = dataclasses.replace(rec, joints=_excite.bag_joint_names(model))
    noise = _sensor.estimate(rec, rec.wrenches) if wrench_topics else None  # before the fit: fail fast
    with _new_folder(out) as tmp:
        cal, prob, pd0, pd, result = calibrate(model, rec, progress=progress, **fit_kw)
        if cal.problems and not force:
            raise UntrustedResultError(
                f"{bag}: no calibration written, the recording does not support one: " + "; ".join(cal.problems)
                + f" (fitted delay {cal.delay}; --force writes it with these as WARNINGs; docs/calibrate.md)"
            )  # fmt: skip
        model_name = model.robot.name if getattr(model, "robot", None) else os.path.basename(model.path)
        warnings = "".join(f"# WARNING: {p}\n" for p in cal.problems)
        (tmp / "calibration.yaml").write_text(warnings + fragment(cal, str(bag), model_name, noise))
        summary = {
            "bag": str(bag),
            "duration_s": rec.duration,
            "state_samples": len(rec.state_times),
            "command_period_s": cal.period,
            "delay_periods": cal.delay,
            "structure": cal.structure,
            "structure_held_out_costs": dict(cal.structure_costs),
            "structure_margin": cal.structure_margin,
            "delay_costs": {str(k): v for k, v in cal.delay_costs.items()},
            "windows": cal.windows,
            "seconds": cal.seconds,
            "joints": {
                name: {
                    **{f"{f}_{UNITS[f]}": float(getattr(cal.fitted, f)[k]) for f in cal.fields},
                    **{f"{f}_before": float(getattr(cal.nominal, f)[k]) for f in cal.fields},
                    **{
                        f"{f}_interval95": float(cal.intervals.get(f, np.full(len(cal.joints), np.nan))[k])
                        for f in cal.fields
                    },
                    **{  # what each stated half-width is the largest of (the motion's; Calibration.interval_parts)
                        f"{f}_interval95_{part}": float(parts[f][k])
                        for part, parts in cal.interval_parts.items()
                        for f in cal.fields
                        if f in parts
                    },
                    "rms_before_rad": float(cal.rms_before[k]),
                    "rms_after_rad": float(cal.rms_after[k]),
                    "motion_rms_rad": float(cal.motion[k]),
                    # the joint's fastest mode at the fitted gains; quicker than the samples: not resolved
                    "fastest_mode_s": float(cal.fastest_mode[k]),
                    "resolved": not bool(cal.unresolved[k]),
                }
                for k, name in enumerate(cal.joints)
            },
            "poor_fit": cal.poor,
            "noise_rad": {name: float(v) for name, v in zip(cal.joints, cal.noise, strict=True)},
            "problems": list(cal.problems),
        }
        if cal.efforts is not None:
            summary["efforts"] = cal.efforts.to_dict(cal.joints)
            summary["gains_from_efforts"] = list(cal.from_efforts)
        if noise is not None:
            summary["sensor"] = {"topics": list(wrench_topics), **noise.to_dict()}
        (tmp / "calibration.json").write_text(json.dumps(summary, indent=1, default=float))
        _plot(tmp / "calibration.png", prob, pd0, pd, f"{bag}: delay {cal.delay} periods")
        if report and result is not None:
            (tmp / "report").mkdir()
            prob.sysid.default_report(
                [prob.sequences], pd0, pd, prob.residual_fn, result, title=f"jaxsync calibrate: {bag}",
                save_path=tmp / "report", build_model=lambda p, spec: prob.replay.m, generate_videos=False,
            )  # fmt: skip
    return summary | {"calibration": cal, "noise": noise}
