"""What a calibration found, and whether calibrate stands behind it.

:class:`Calibration` holds the fitted servo, delay and structure with their
half-widths and the recording's noise; :func:`problems` names every reason
the result cannot be trusted (docs/calibrate.md, "What calibrate stands
behind"); :func:`fastest_mode` says which joints the recording's samples
resolve.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxsync.calibrate import efforts as _efforts
from jaxsync.calibrate.replay import Joints

FACTOR_BOUNDS = (0.1, 10.0)  # stiffness and damping, as factors on the position stack's
FACTORS = ("stiffness", "damping")
POOR_FIT = 0.1  # an RMS error over this share of the joint's own motion: the model does not explain it
# what calibrate stands behind (Calibration.problems): a residual within this many times the recording's own
# noise, no other delay within this share of the best's cost, gains off their bounds by this share, and 95 %
# half-widths within these shares of the fitted value
NOISE_MULTIPLE = 2.0
DELAY_MARGIN = 0.02
STRUCTURE_MARGIN = 0.05  # held-out cost: another structure within 5 % of the winner's explains the arm as well
BOUND_MARGIN = 0.01
DETERMINED = {"stiffness": 0.10, "damping": 0.20}


@dataclasses.dataclass
class Calibration:
    """What ``calibrate`` found (arrays (2 n,), right arm then left)."""

    joints: tuple[str, ...]
    delay: int  # control periods
    period: float  # s
    fitted: Joints
    nominal: Joints
    intervals: dict  # field -> (2 n,) 95 % half-widths, in the field's units
    rms_before: np.ndarray  # rad
    rms_after: np.ndarray  # rad
    motion: np.ndarray  # rad, RMS of each joint's recorded motion about its pose
    delay_costs: dict  # delay -> sum of squared residuals after its fit
    fields: tuple[str, ...]
    seconds: float
    windows: int
    noise: np.ndarray  # rad, each joint's position noise in the recording (noise_floor)
    problems: tuple[str, ...] = ()  # why the result cannot be trusted (none: it can)
    structure: str = "feedforward"  # the servo structure fitted (jaxsync.physics.servo.STRUCTURES)
    structure_costs: dict = dataclasses.field(default_factory=dict)  # structure -> held-out cost
    efforts: object = None  # the servo the recording's joint efforts say (efforts.EffortFit), where it has them
    from_efforts: tuple = ()  # the joints whose gains come from the efforts (the motion leaves them open)
    # the half-widths' parts, name -> field -> (2 n,): the stated is the largest (calibrate); "windows_se" too
    interval_parts: dict = dataclasses.field(default_factory=dict)
    inertia: np.ndarray | None = None  # kg m^2, each joint's own inertia at the grasp (armature included)
    sample_period: float | None = None  # s, the recording's joint states

    @property
    def fastest_mode(self) -> np.ndarray:
        """(2 n,) s: the time constant of each joint's fastest mode, I s^2 + (b + joint damping) s + k at the
        fitted gains (1 / the larger pole's magnitude; an underdamped joint's 1 / its natural frequency);
        NaN without the inertia."""
        if self.inertia is None:
            return np.full(len(self.joints), np.nan)
        return fastest_mode(self.inertia, self.fitted)

    @property
    def unresolved(self) -> np.ndarray:
        """(2 n,) bool: the joints whose fastest mode is quicker than the recording's sample period. Their
        motion sets the stiffness over the damping (the slow pole) and hardly each: that the fit claims
        each anyway comes from what the samples cannot show (an FR3-like wrist, 0.4 ms against 2 ms
        samples: 62 % off claiming +-1.9 %)."""
        if self.sample_period is None:
            return np.zeros(len(self.joints), bool)
        return self.fastest_mode < self.sample_period

    @property
    def structure_margin(self) -> float | None:
        """How much worse the runner-up structure explains the held-out windows (0.3: 30 %), None with one."""
        others = [c for k, c in self.structure_costs.items() if k != self.structure]
        if not others:
            return None
        return min(others) / max(self.structure_costs[self.structure], 1e-300) - 1.0

    @property
    def poor(self) -> list[str]:
        """The joints whose motion the fitted model does not explain (RMS error over ``POOR_FIT`` of it)."""
        return [j for j, e, s in zip(self.joints, self.rms_after, self.motion, strict=True) if e > POOR_FIT * s]


def fastest_mode(inertia, joints: Joints) -> np.ndarray:
    """s: the time constant of each joint's fastest mode, I s^2 + b s + k = 0 with ``joints``' servo gains
    (b: the servo's damping and the joint's own) and ``inertia`` (1 / the larger pole's magnitude: an
    overdamped joint's fast pole, an underdamped one's natural frequency)."""
    inertia, k = np.asarray(inertia, float), np.asarray(joints.stiffness, float)
    b = np.asarray(joints.damping, float) + np.asarray(joints.joint_damping, float)
    root = np.sqrt(np.maximum(b * b - 4.0 * inertia * k, 0.0))
    fast = np.where(root > 0.0, (b + root) / (2.0 * inertia), np.sqrt(np.maximum(k, 0.0) / inertia))
    with np.errstate(divide="ignore"):
        return 1.0 / fast


def problems(cal: Calibration, delays: list[int], pd) -> list[str]:
    """Why ``cal`` cannot be trusted, one phrase each (none: it can): the delay at the scan's end or another
    nearly as good, a gain on its bound, a residual over ``NOISE_MULTIPLE`` times the noise, a gain (and so
    the delay fitted with it) the recording does not determine, a delay, structure or gain the efforts deny."""
    out = []
    ef = getattr(cal, "efforts", None)
    if ef is not None:  # where the efforts chose the delay and the structure: their checks, and agreement
        out.extend(_efforts.problems(ef, cal, DETERMINED, delays))
    elif cal.unresolved.any():
        quick = [j for j, q in zip(cal.joints, cal.unresolved, strict=True) if q]
        out.append(
            f"the fastest mode of {len(quick)} joint(s) ({', '.join(quick[:3])}{' ...' if len(quick) > 3 else ''}; "
            f"{1e3 * np.nanmin(cal.fastest_mode):.2g} ms) is quicker than the recording's samples "
            f"({1e3 * cal.sample_period:.2g} ms): their motion sets the stiffness over the damping, not each "
            "(record faster, or with the joints' efforts)"
        )
    if (
        (ef is None or not ef.decisive())
        and len(delays) > 1
        and cal.delay == max(delays)
        and max(cal.delay_costs) == cal.delay
    ):
        out.append(f"the delay found, {cal.delay} periods, is the last one scanned: the arm may lag more "
                   f"(scan further: --delays 0:{cal.delay + 4})")  # fmt: skip
    best = cal.delay_costs[cal.delay]
    near = [d for d, c in cal.delay_costs.items() if d != cal.delay and c <= (1 + DELAY_MARGIN) * best]
    if near:
        out.append(f"delays {near} explain the recording within {DELAY_MARGIN:.0%} of delay {cal.delay}'s cost")
    margin = cal.structure_margin
    if margin is not None and margin < STRUCTURE_MARGIN:
        runner = min((k for k in cal.structure_costs if k != cal.structure), key=cal.structure_costs.get)
        out.append(f"the {runner} servo explains the held-out windows within {margin:.1%} of the {cal.structure} "
                   f"one's cost: the recording does not tell the structures apart")  # fmt: skip
    lo, hi = FACTOR_BOUNDS
    bound = []
    for key in pd.keys():
        v = float(pd[key].value[0])
        name, field = key.rsplit(" ", 1)
        if field in FACTORS and (v <= lo * (1 + BOUND_MARGIN) or v >= hi * (1 - BOUND_MARGIN)):
            bound.append(f"{name}'s {field} ({v:.3g} times the robot file's)")
    if bound:
        more = f" and {len(bound) - 2} more" if len(bound) > 2 else ""
        out.append(f"{len(bound)} gain(s) sit on their bounds: {', '.join(bound[:2])}{more}")
    worse = [(j, e, n) for j, e, n in zip(cal.joints, cal.rms_after, cal.noise, strict=True)
             if e > NOISE_MULTIPLE * max(n, 1e-9)]  # fmt: skip
    if worse:
        j, e, n = max(worse, key=lambda w: w[1] / max(w[2], 1e-9))
        out.append(f"the fitted servo leaves {len(worse)} joint(s) over {NOISE_MULTIPLE:g} times the recording's "
                   f"noise (worst {j}: {e * 1e3:.3g} mrad RMS against {n * 1e3:.2g} mrad of noise): the servo law "
                   "or the delay does not describe this arm")  # fmt: skip
    open_gains = False
    for field, share in DETERMINED.items():
        rel = cal.intervals.get(field, np.zeros(len(cal.joints))) / getattr(cal.fitted, field)
        loose = [(j, r) for j, r in zip(cal.joints, rel, strict=True) if not np.isfinite(r) or r > share]
        open_gains = open_gains or bool(loose)
        if loose:
            j, r = max(loose, key=lambda w: w[1] if np.isfinite(w[1]) else np.inf)
            width = f"+-{r:.0%}" if np.isfinite(r) else "no interval"
            out.append(f"the recording does not determine the {field} of {len(loose)} joint(s) to {share:.0%} "
                       f"(worst {j}: {width})")  # fmt: skip
    if open_gains and (ef is None or not (ef.decisive() or ef.delay_of(cal.structure) is not None)):
        out.append(f"the delay found ({cal.delay} periods) was fitted with those gains: not stood behind either")
    return out
