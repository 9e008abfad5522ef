"""The servo read from recorded joint efforts, where the recording has them.

A position-controlled joint's servo applies (``jaxsync.physics.servo``)

    tau = clip(k (q_cmd - q) + b (f dq_cmd - dq) + w c(q, dq), +-tau_max)

with ``q_cmd`` the command acting after the delay and ``c`` the arm's bias
forces (gravity and Coriolis). For a structure (w, f) and a delay, tau - w c
is linear in (k, b) on every sample inside the limit, so where the
recording's joint states carry each joint's torque (``JointState.effort``,
what ros2_control's ``joint_state_broadcaster`` publishes from the effort
state interface) every structure and delay is fitted in closed form, one
joint at a time, in milliseconds, with no rollout. Samples at the torque
limit (``SATURATED`` of it) carry no information on the gains and are left
out; their share is reported per joint.

``calibrate`` fits the recorded motion (``jaxsync.calibrate.fit``); this is
a second, independent reading of the same arm from another signal. Where
the two disagree on the delay, the structure or a gain beyond what the
motion fit claims to determine, the calibration is not trusted
(``fit.problems``).
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from jaxsync.calibrate.replay import Replay
from jaxsync.physics.servo import STRUCTURES

DECISIVE = 0.3  # the runner-up delay and structure this much worse: the efforts decide them (else the motion)
SATURATED = 0.98  # a sample with |tau| at this share of the joint's limit or above: at the limit
MIN_SAMPLES = 50  # unsaturated samples a joint needs for its two gains
GROUPS = 4  # interleaved sets of 0.5 s blocks whose gains' spread gives the half-widths
SMOOTH_S = 0.05  # s: both sides of the regression averaged over this window (the servo's law is linear and
# time-invariant, so averaging keeps it) before the fit: the velocity's noise, in a regressor, would pull the
# damping low by its variance over the tracking error's (tens of per cent at 500 Hz, measured)


@dataclasses.dataclass(frozen=True)
class EffortFit:
    """The servo the efforts say, ((2 n,) arrays, right arm then left)."""

    structure: str
    delay: int
    stiffness: np.ndarray  # N m/rad
    damping: np.ndarray  # N m s/rad
    rms: np.ndarray  # N m: each joint's residual torque at the chosen structure and delay
    saturated: np.ndarray  # each joint's share of samples at its torque limit
    costs: dict  # (structure, delay) -> sum over joints of the mean square residual, (N m)^2
    intervals: dict = dataclasses.field(default_factory=dict)  # field -> (2 n,) half-widths (fit_efforts)

    def margin(self, over: str = "structure") -> float | None:
        """How much worse the best other structure (``over="structure"``) or delay ("delay") explains the
        efforts (0.3: 30 %), None where there is no other."""
        best = self.costs[(self.structure, self.delay)]
        if over == "structure":
            others = [c for (s, _), c in self.costs.items() if s != self.structure]
        else:
            others = [c for (s, d), c in self.costs.items() if s == self.structure and d != self.delay]
        return min(others) / max(best, 1e-300) - 1.0 if others else None

    def delay_of(self, structure: str, margin: float = DECISIVE) -> int | None:
        """The delay the efforts give ``structure``, where its next-best delay explains them at least
        ``margin`` worse and it is not the last one scanned; None elsewhere (a servo with velocity
        feed-forward trades delay against damping, and its efforts' cost may fall to the end of the scan)."""
        own = {d: c for (s, d), c in self.costs.items() if s == structure}
        if len(own) < 2:
            return None
        best = min(own, key=own.get)
        runner = min(c for d, c in own.items() if d != best)
        return best if best != max(own) and runner >= (1 + margin) * own[best] else None

    def decisive(self, margin: float = DECISIVE) -> bool:
        """Whether every other delay and structure explains the efforts at least ``margin`` worse (a
        servo with velocity feed-forward nearly trades one period of delay for k P of its damping, so
        its efforts may not tell the delays apart where its motion does)."""
        return all(m is None or m >= margin for m in (self.margin("delay"), self.margin("structure")))

    def to_dict(self, joints) -> dict:
        return {
            "structure": self.structure,
            "delay_periods": self.delay,
            "structure_margin": self.margin("structure"),
            "delay_margin": self.margin("delay"),
            "decisive": self.decisive(),
            "joints": {
                name: {
                    "stiffness_N m/rad": float(self.stiffness[k]),
                    "damping_N m s/rad": float(self.damping[k]),
                    "stiffness_interval95": float(self.intervals.get("stiffness", np.full(k + 1, np.nan))[k]),
                    "damping_interval95": float(self.intervals.get("damping", np.full(k + 1, np.nan))[k]),
                    "residual_rms_Nm": float(self.rms[k]),
                    "saturated_share": float(self.saturated[k]),
                }
                for k, name in enumerate(joints)
            },
        }


def bias_forces(replay: Replay, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """(S, 2 n) the arms' bias forces c(q, dq) (gravity and Coriolis, N m) at each sample, the rest of the
    scene at the grasp keyframe (contacts off)."""
    m, d, pc = replay.m, replay.d, replay.pc
    out = np.empty_like(q)
    for i in range(len(q)):
        d.qpos[:] = replay.base_qpos
        d.qpos[pc.qpos_adr] = q[i]
        d.qvel[:] = 0.0
        d.qvel[pc.dof_adr] = dq[i]
        mujoco.mj_fwdPosition(m, d)
        mujoco.mj_fwdVelocity(m, d)
        out[i] = d.qfrc_bias[pc.dof_adr]
    return out


def fit_efforts(model, rec, delays=range(0, 5), structures=None) -> EffortFit:
    """Each structure and delay fitted to ``rec.effort`` (a ``jaxsync.io.bags.Recording`` with efforts)
    joint by joint; the one whose least-squares residual is least chosen, its gains by instrumental
    variables (:func:`_instrumented`) with 95 % half-widths: the largest of the batch-means spread over
    ``GROUPS`` interleaved sets of 0.5 s blocks (their median absolute deviation, a Student quantile), the gap
    to least squares, and the move to every other delay and structure the efforts do not exclude."""
    if rec.effort is None:
        raise ValueError("the recording carries no joint efforts")
    import scipy.special  # noqa: PLC0415 -- with the toolbox, only calibration needs it

    replay = Replay(model)
    q, tau = np.asarray(rec.q, float), np.asarray(rec.effort, float)
    dq = np.asarray(rec.dq, float) if rec.dq is not None else np.gradient(q, rec.state_times, axis=0)
    c = bias_forces(replay, q, dq)
    limit = np.asarray(replay.limit, float)
    at_limit = np.abs(tau) >= SATURATED * limit
    width = max(1, int(round(SMOOTH_S / float(np.median(np.diff(rec.state_times))))))
    smooth = lambda x: _boxcar(x, width)  # noqa: E731
    inside = smooth(at_limit.astype(float)) == 0.0  # no sample of the window at the limit
    inside[: width // 2 + 1] = inside[-(width // 2 + 1) :] = False  # the averages the ends cut short
    period = rec.command_period
    names = list(STRUCTURES) if structures is None else list(structures)
    n = q.shape[1]

    def regressors(delay: int, name: str):
        """(smoothed command error, smoothed velocity term, smoothed torque less w c), each (S, 2 n)."""
        cmd, vel = replay.acting(rec.state_times, rec.command_times, rec.commands, int(delay), period)
        w, f = (float(x) for x in STRUCTURES[name])
        return smooth(cmd - q), smooth(f * vel - dq), smooth(tau - w * c)

    costs, rms, ols = {}, {}, {}
    for delay in delays:
        for name in names:
            x1, x2, y = regressors(delay, name)
            ms, sols = np.full(n, np.inf), np.full((2, n), np.nan)
            for j in range(n):
                rows = inside[:, j]
                if rows.sum() >= MIN_SAMPLES:
                    X = np.column_stack([x1[rows, j], x2[rows, j]])
                    sols[:, j], *_ = np.linalg.lstsq(X, y[rows, j], rcond=None)
                    ms[j] = float(np.mean((y[rows, j] - X @ sols[:, j]) ** 2))
            key = (name, int(delay))
            costs[key], rms[key], ols[key] = float(np.sum(ms)), np.sqrt(ms), sols
    best = min(costs, key=costs.get)
    x1, x2, y = regressors(best[1], best[0])
    gains, groups = np.full((2, n), np.nan), np.full((GROUPS, 2, n), np.nan)
    for j in range(n):
        args = (x1[:, j], x2[:, j], y[:, j], inside[:, j], 2 * width)
        gains[:, j] = _instrumented(*args)
        for h in range(GROUPS):
            groups[h, :, j] = _instrumented(*args, group=(h, GROUPS))
    # the spread of the gains fitted on each of GROUPS interleaved sets of blocks (batch means: a Student
    # quantile on GROUPS - 1 degrees of freedom; the median absolute deviation, since a set the excitation
    # barely moves a joint in gives wild instrumental gains), or where larger the gap to least squares: its attenuation
    # is the noise's share of the regressors, so a wide gap says the joint barely moved above its noise
    # (an FR3 wrist at +97 % had least squares at -37 %)
    mad = np.median(np.abs(groups - np.median(groups, axis=0)), axis=0)
    # 1.4826 MAD: a normal's standard deviation; Student's 97.5 % quantile on GROUPS - 1 degrees of freedom
    spread = scipy.special.stdtrit(GROUPS - 1, 0.975) * 1.4826 * mad / np.sqrt(GROUPS)
    half_width = np.fmax(spread, np.abs(gains - ols[best]))
    # and the move to every other delay and structure the efforts do not exclude (within DECISIVE of the best
    # cost): on a joint whose command error follows its velocity (an overdamped, weight-compensated servo) a
    # period of delay trades for damping, least squares' cost favours the delay whose gains it pulls lowest,
    # and the gains at the delay chosen can sit 30-45 % off with a narrow spread (measured: FR3 figures)
    for key in _near(costs, best):
        x1n, x2n, yn = regressors(key[1], key[0])
        other = np.array([_instrumented(x1n[:, j], x2n[:, j], yn[:, j], inside[:, j], 2 * width) for j in range(n)]).T
        half_width = np.fmax(half_width, np.abs(other - gains))
    half_width = np.where(np.isfinite(half_width), half_width, np.inf)
    return EffortFit(best[0], best[1], gains[0], gains[1], rms[best], at_limit.mean(axis=0), costs,
                     {"stiffness": half_width[0], "damping": half_width[1]})  # fmt: skip


def _near(costs: dict, best: tuple, margin: float = DECISIVE) -> list[tuple]:
    """The other (structure, delay) candidates whose cost is within ``margin`` of ``best``'s: the efforts do not
    exclude them."""
    return [k for k, c in costs.items() if k != best and c <= (1.0 + margin) * costs[best]]


def _instrumented(x1, x2, y, rows, lag: int, group: tuple[int, int] | None = None):
    """(k, b) of y = k x1 + b x2 by instrumental variables: each regressor instrumented by itself ``lag``
    samples earlier. The samples' noise (in q and dq, so in both regressors) is white, or differenced white,
    and averaged over fewer than ``lag`` samples, so uncorrelated with its value ``lag`` earlier, while the
    arm's motion is slow: no attenuation, where least squares pulls both gains low by the noise's share of
    the regressors' variance (tens of per cent on a wrist the excitation barely moves)."""
    use = rows.copy()
    use[:lag] = False
    use[lag:] &= rows[:-lag]
    idx = np.flatnonzero(use)
    if group is not None:  # (g, G): every G-th block of 5 lags from the g-th (each holds every part of the motion)
        idx = idx[(idx // (5 * lag)) % group[1] == group[0]]
    if len(idx) < MIN_SAMPLES:
        return np.nan, np.nan
    X = np.column_stack([x1[idx], x2[idx]])
    Z = np.column_stack([x1[idx - lag], x2[idx - lag]])
    try:
        return tuple(np.linalg.solve(Z.T @ X, Z.T @ y[idx]))
    except np.linalg.LinAlgError:
        return np.nan, np.nan


def _boxcar(x: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average of ``width`` samples along axis 0 (the ends averaged over what there is)."""
    if width <= 1:
        return np.asarray(x, float)
    kernel = np.ones(width) / width
    return np.apply_along_axis(lambda col: np.convolve(col, kernel, mode="same"), 0, np.asarray(x, float))


def determined(ef: EffortFit, shares: dict) -> np.ndarray:
    """(2 n,) the joints whose stiffness and damping the efforts fix: both positive, each half-width
    within its share in ``shares`` ({"stiffness": 0.1, "damping": 0.2})."""
    ok = np.ones(len(ef.stiffness), bool)
    for field, share in shares.items():
        value = getattr(ef, field)
        half = ef.intervals.get(field, np.full(len(value), np.inf))
        with np.errstate(invalid="ignore", divide="ignore"):
            ok &= np.isfinite(value) & (value > 0) & (half <= share * np.abs(value))
    return ok


def take_open_gains(ef: EffortFit, pd, names, nominal, intervals: dict, shares: dict, bounds, unresolved=None) -> tuple:
    """Where the motion's fit leaves a joint's stiffness or damping open (its half-width in ``intervals``
    over its share) or cannot resolve them (``unresolved``, (2 n,) bool: ``fit.Calibration.unresolved``)
    and the efforts fix both, the efforts' gains into ``pd`` (the toolbox's parameters, factors on
    ``nominal`` within ``bounds``) and their half-widths into ``intervals``, in place. Returns the names of
    those joints."""
    motion = np.ones(len(names), bool)  # the joints whose stiffness and damping the motion fixes
    if unresolved is not None:
        motion &= ~np.asarray(unresolved, bool)
    for field, share in shares.items():
        value = np.asarray([float(pd[f"{nm} {field}"].value[0]) for nm in names]) * getattr(nominal, field)
        motion &= intervals[field] <= share * value
    fixed = determined(ef, shares) & ~motion
    for k in np.flatnonzero(fixed):
        for field in shares:
            pd[f"{names[k]} {field}"].value[0] = float(np.clip(getattr(ef, field)[k] / getattr(nominal, field)[k],
                                                               *bounds))  # fmt: skip
            intervals[field][k] = ef.intervals[field][k]
    return tuple(names[k] for k in np.flatnonzero(fixed))


def problems(ef: EffortFit, cal, shares: dict, delays) -> list[str]:
    """Why the efforts' reading cannot be stood behind, or contradicts ``cal`` (a ``fit.Calibration``),
    one phrase each: where the efforts are decisive (:meth:`EffortFit.decisive`), their delay at the end
    of the scan or another delay or structure than ``cal``'s; joints whose gains the efforts do not fix;
    a stiffness or damping both readings determine off by more than its share in ``shares``."""
    out = []
    delays = [int(d) for d in delays]
    if ef.decisive() and len(delays) > 1 and ef.delay == max(delays):
        out.append(f"the joint efforts' delay, {ef.delay} periods, is the last one scanned: the arm may lag more "
                   f"(scan further: --delays 0:{ef.delay + 4})")  # fmt: skip
    if ef.decisive() and (ef.delay != cal.delay or ef.structure != cal.structure):
        out.append(
            f"the joint efforts say the {ef.structure} servo at delay {ef.delay}, the motion the {cal.structure} "
            f"one at delay {cal.delay}"
        )
    both = determined(ef, shares)
    # where the torques do not fix the gains of a joint whose fastest mode the samples cannot resolve, its
    # motion alone is not stood behind: it sets the stiffness over the damping, and a fit to it can sit far
    # along that valley claiming a few per cent (measured: +125 % claiming +-2 % on an as-written FR3 wrist)
    quick = np.asarray(getattr(cal, "unresolved", np.ones(len(both), bool)), bool)
    if (quick & ~both).any():
        loose = [j for j, ok, q in zip(cal.joints, both, quick, strict=True) if q and not ok]
        out.append(
            f"the joint efforts do not fix the gains of {len(loose)} joint(s) ({', '.join(loose[:3])}"
            f"{' ...' if len(loose) > 3 else ''}) whose fastest mode is quicker than the recording's samples, "
            "and their motion alone is not stood behind: record faster, or move those joints more (a larger "
            "--amplitude or --speed in jaxsync excite) for efforts that fix them"
        )
    for field, share in shares.items():
        mine, theirs = getattr(ef, field), getattr(cal.fitted, field)
        half = cal.intervals.get(field, np.full(len(theirs), np.inf))
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = np.abs(mine - theirs) / np.abs(theirs)
            sure = both & (half <= share * np.abs(theirs))
        off = [(j, r) for j, r, ok in zip(cal.joints, rel, sure, strict=True) if ok and not r <= share]
        if off:
            j, r = max(off, key=lambda x: x[1] if np.isfinite(x[1]) else np.inf)
            k = list(cal.joints).index(j)
            out.append(
                f"the joint efforts and the motion disagree on the {field} of {len(off)} joint(s) by more than "
                f"{share:.0%} (worst {j}: {mine[k]:.4g} against {theirs[k]:.4g})"
            )
    return out
