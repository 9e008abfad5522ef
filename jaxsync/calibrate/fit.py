"""Each joint's servo and the command delay, fitted to a recording with MuJoCo's identification toolbox.

Built on ``mujoco.sysid``: the parameters are its ``Parameter``s (each
joint's servo stiffness and damping as a factor on the position stack's,
optionally its joint damping, friction loss and armature), the residual its
``build_residual_fn``'s over ``ModelSequences`` of short windows (computed
here without the toolbox's per-window copies, number for number), each started
from the recorded state, rolled out by :mod:`jaxsync.calibrate.replay` (the
position stack's own servo and delay) as the toolbox's custom rollout; the
fit its bounded least squares with MuJoCo's finite-difference Jacobians
(``optimize``), the intervals ``calculate_intervals`` and
:mod:`jaxsync.calibrate.uncertainty`, the HTML report ``default_report``.

The delay is whole control periods: at each candidate the parameters are
fitted joint by joint (each joint's windows, both arms' parameters of that
joint) on the model's own step, the candidates compared on every window.
At the best one the gains are fitted again on a step fine enough for the
servo (:func:`replay_step`), joint by joint, then all together. The fit's
rollouts are MuJoCo's own actuators in ``mujoco.rollout``
(:class:`jaxsync.calibrate.replay.NativeReplay`); the tracking errors
reported run the position stack's servo code itself.
"""

from __future__ import annotations

import io
import time

import mujoco
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.calibrate import efforts as _efforts
from jaxsync.calibrate.excite import bag_joint_names, check_symmetric
from jaxsync.calibrate.replay import FIELDS, Joints, NativeReplay, replay_step
from jaxsync.calibrate.uncertainty import clustered_intervals, noise_floor
from jaxsync.calibrate.verdict import (  # noqa: F401  (the result's names, read here too)
    DETERMINED,
    FACTOR_BOUNDS,
    FACTORS,
    Calibration,
    fastest_mode,
    problems,
)
from jaxsync.calibrate.windows import halved as _halved
from jaxsync.calibrate.windows import split as _split
from jaxsync.calibrate.windows import subset as _subset
from jaxsync.physics.servo import STRUCTURES, joint_inertia

SIGMA_Q = 1e-3  # rad: a position residual of one
SIGMA_DQ = 2e-2  # rad/s: a velocity residual of one
ABSOLUTE_BOUNDS = {"joint_damping": (0.0, 100.0), "frictionloss": (0.0, 20.0), "armature": (0.0, 5.0)}
SCAN_ITERS = 2  # per joint and delay on the model's step: enough to tell the delays apart
# per joint for each half of the windows, from the result (tests/test_calibrate.py's recording: the halves'
# spread after 2 iterations within 1.5e-6 of a value of that after 4, in 2.2 s against 15.4 s)
HALF_ITERS = 2
# the replay step's bias, about linear in the step (tests/test_calibrate.py's stiffnesses: +2.3-4.5 % at 0.5 ms,
# -1.1-1.9 % at 0.125 ms): each joint fitted again on half the step, twice the move taken
STEP_ITERS = 1
HELD_OUT_EVERY = 4  # every fourth window held out to choose the structure
SCREEN_FACTOR = 10.0  # a structure this far behind another's best training cost stops its delay scan
FD_STEP = 1e-3  # the finite-difference step on the gain factors (~1): above the friction loss's roughness


def _spec(model):
    """The model's spec with joint position and velocity sensors on the arm joints (what a window records)."""
    robot = getattr(model, "robot", None)
    spec = robot.spec.copy() if robot is not None else mujoco.MjSpec.from_file(model.path)
    for s in list(spec.sensors):
        spec.delete(s)
    m = model.mj_model
    names = bag_joint_names(model)
    dofs = [i for a in model.index.arms for i in a.dof_adr]
    for kind, suffix in ((mujoco.mjtSensor.mjSENS_JOINTPOS, "q"), (mujoco.mjtSensor.mjSENS_JOINTVEL, "dq")):
        for name, dof in zip(names, dofs, strict=True):
            joint = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, int(m.dof_jntid[dof]))
            spec.add_sensor(name=f"{name} {suffix}", type=kind, objtype=mujoco.mjtObj.mjOBJ_JOINT, objname=joint)
    return spec


def _shared(key: str, kind, doc: str) -> property:
    """A setting of a :class:`Problem` held in its ``_shared`` dict, which its window subsets
    (``jaxsync.calibrate.windows``) hold by reference: set on one, set on all."""
    return property(lambda self: self._shared[key], lambda self, v: self._shared.__setitem__(key, kind(v)), doc=doc)


class Problem:
    """The recording cut into windows, as the toolbox's model sequences, and its residual."""

    def __init__(self, model, rec, window: float = 0.5, timestep: float | None = None, structure=None):
        # the toolbox is imported here, not at the top: only calibration needs it (mujoco[sysid])
        from mujoco import sysid

        self.sysid = sysid
        check_symmetric(model)
        spec = _spec(model)
        self.native = NativeReplay(model, spec, timestep=timestep, structure=structure)
        self.replay = self.native.exact
        # the delay and the replay mode, shared with every subset of the windows (_subset) by reference
        self._shared = {"delay": 0, "exact": False}
        self.names = bag_joint_names(model)
        if tuple(rec.joints) != self.names:
            raise ConfigError(f"the recording's joints {rec.joints} are not the model's {self.names}")
        self.rec = rec
        self.period = rec.command_period
        h = self.replay.timestep
        self.n_steps = int(round(window / h))
        if self.n_steps < 5 or window > rec.duration / 2:
            raise ConfigError(
                f"window must be 5 physics steps to half the recording, got {window} s", inputs=("window",)
            )
        nu = self.replay.m.nu
        acts = self.replay.pc.actuator_ids
        starts = np.arange(0, len(rec.state_times), max(1, int(round(window / np.median(np.diff(rec.state_times))))))
        self.dominant = []
        states, controls, sensors, seq = [], [], [], []
        mapping = None
        for i in starts:
            t0 = rec.state_times[i]
            inside = (rec.state_times > t0) & (rec.state_times <= t0 + window - 1e-9)
            if inside.sum() < 3 or t0 + window > rec.state_times[-1]:
                continue
            dq0 = rec.dq[i] if rec.dq is not None else np.zeros(len(self.names))
            states.append(self.replay.state(rec.q[i], dq0, t0))
            lo = max(0, np.searchsorted(rec.command_times, t0, side="right") - 12)
            hi = np.searchsorted(rec.command_times, t0 + window, side="right") + 1
            ctrl = np.zeros((hi - lo, nu))
            ctrl[:, acts] = rec.commands[lo:hi]
            controls.append(sysid.TimeSeries(rec.command_times[lo:hi], ctrl))
            meas = np.column_stack(
                [rec.q[inside], rec.dq[inside] if rec.dq is not None else np.zeros_like(rec.q[inside])]
            )
            if mapping is None:
                mapping = sysid.TimeSeries.compute_all_sensor_mapping(spec.compile())
            sensors.append(sysid.TimeSeries(rec.state_times[inside], meas, mapping))
            seq.append(f"{t0:.2f} s")
            moved = np.ptp(rec.commands[lo:hi], axis=0)
            self.dominant.append(int(np.argmax(moved)) % (len(self.names) // 2) if moved.max() > 1e-6 else -1)
        if len(states) < 2:
            raise ConfigError(f"the recording ({rec.duration:.2f} s) holds fewer than two windows of {window} s")
        self.sequences = sysid.ModelSequences("arms", spec, seq, states, controls, sensors)
        self.velocity = rec.dq is not None
        self.residual_fn = self.residual_over(self.sequences)

    delay = _shared("delay", int, "The delay the rollouts apply, control periods.")
    exact = _shared("exact", bool, "True: roll out through the position stack's own servo code (slower).")

    def residual_over(self, sequences):
        """The toolbox's residual over ``sequences``, rolled out by this problem's replay.

        What the toolbox's ``build_residual_fn`` returns with this problem's rollout and residual
        hooks, the same numbers in the same order; the fit's calls (no predictions asked for, MuJoCo's
        own actuators) take a shorter road: the gains of each finite-difference column turned into a
        model once, not once per window, and every window of every column in one threaded rollout.
        """
        toolbox = self.sysid.build_residual_fn(
            models_sequences=[sequences],
            build_model=lambda params, spec: self.replay.m,
            custom_rollout=self._rollout,
            modify_residual=self._residual,
            resample_true=False,
            n_threads=1,
        )

        def residual_fn(x, params, return_pred_all: bool = False, **kw):
            if return_pred_all or self.exact or kw:
                return toolbox(x, params, return_pred_all=return_pred_all, **kw)
            return self._windows_residual(np.asarray(x), params, sequences.measured_rollout)

        return residual_fn

    def _windows_residual(self, x, params, windows):
        """The toolbox's ``residual`` for every window: a list of (samples,) or (samples, columns)
        arrays, ``params`` left at the last column, as the toolbox leaves it."""
        cols = x.reshape(-1, 1) if x.ndim == 1 else x
        joints = []
        for i in range(cols.shape[1]):
            params.update_from_vector(cols[:, i])
            joints.append(self.joints_of(params))
        acts = self.replay.pc.actuator_ids
        jobs = [(j, w.initial_state, w.control.times, w.control.data[:, acts]) for j in joints for w in windows]
        runs = self.native.run_many(jobs, self.n_steps, self.delay, self.period)
        n = len(windows)
        out = []
        for k, w in enumerate(windows):
            res = [self._compare(runs[i * n + k][0], np.column_stack(runs[i * n + k][1:]), w.sensordata)[1]
                   for i in range(cols.shape[1])]  # fmt: skip
            stacked = np.stack(res, axis=0)
            out.append(stacked.ravel() if x.ndim == 1 else stacked.reshape(stacked.shape[0], -1).T)
        return out, [], []

    def _compare(self, times, data, meas):
        """The simulated (q, dq) ``data`` at ``times`` taken at the recorded times, and the weighted
        residual against the recording (flat)."""
        p = np.column_stack([np.interp(meas.times, times, data[:, c]) for c in range(data.shape[1])])
        n = p.shape[1] // 2
        sigma = np.concatenate([np.full(n, SIGMA_Q), np.full(n, SIGMA_DQ)])
        err = (p - meas.data) / sigma
        return p, (err if self.velocity else err[:, :n]).ravel()

    # the toolbox's hooks ------------------------------------------------------------------------
    def _rollout(self, models, datas, control_signal, initial_states, param_dicts, **_):
        n_chunks = len(models) // len(param_dicts)
        acts = self.replay.pc.actuator_ids
        joints = [self.joints_of(p) for p in param_dicts]
        jobs = [(joints[i // n_chunks], state, ctrl.times, ctrl.data[:, acts])
                for i, (ctrl, state) in enumerate(zip(control_signal, initial_states, strict=True))]  # fmt: skip
        if self.exact:
            runs = [self.replay.run(j, st, self.n_steps, ct, c, self.delay, self.period) for j, st, ct, c in jobs]
        else:
            runs = self.native.run_many(jobs, self.n_steps, self.delay, self.period)
        out = []
        for i, ((t, q, dq), ctrl, state) in enumerate(zip(runs, control_signal, initial_states, strict=True)):
            sens = self.sysid.TimeSeries(t, np.column_stack([q, dq]))
            out.append(self.sysid.SystemTrajectory(models[i], ctrl, sens, state,
                                                   self.sysid.TimeSeries(t, np.column_stack([t, q]))))  # fmt: skip
        return out

    def _residual(self, params, pred, meas, model, return_pred_all, **_):
        p, err = self._compare(pred.times, pred.data, meas)
        return err, self.sysid.TimeSeries(meas.times, p, meas.signal_mapping), meas

    # parameters ------------------------------------------------------------------------------------
    def parameters(self, nominal: Joints, fields) -> object:
        pd = self.sysid.ParameterDict()
        for field in fields:
            for k, name in enumerate(self.names):
                if field in FACTORS:
                    pd.add(self.sysid.Parameter(f"{name} {field}", 1.0, *FACTOR_BOUNDS))
                else:
                    lo, hi = ABSOLUTE_BOUNDS[field]
                    pd.add(self.sysid.Parameter(f"{name} {field}", float(getattr(nominal, field)[k]), lo, hi))
        self.nominal = nominal
        return pd

    def joints_of(self, pd) -> Joints:
        out = {}
        for field in FIELDS:
            base = np.array(getattr(self.nominal, field), float)
            for k, name in enumerate(self.names):
                key = f"{name} {field}"
                if key in pd:
                    v = float(pd[key].value[0])
                    base[k] = base[k] * v if field in FACTORS else v
            out[field] = base
        return Joints(**out)

    def intervals_of(self, pd, half: np.ndarray) -> dict:
        """The toolbox's half-widths (in the parameters' own units) in the fields' units."""
        out, i = {}, 0
        for key in pd.get_non_frozen_parameter_names():
            name, field = key.rsplit(" ", 1)
            k = self.names.index(name)
            scale = getattr(self.nominal, field)[k] if field in FACTORS else 1.0
            out.setdefault(field, np.full(len(self.names), np.nan))[k] = half[i] * scale
            i += 1
        return out

    def cost(self, pd) -> float:
        res, _, _ = self.residual_fn(pd.as_vector(), pd)
        r = np.concatenate(res)
        return float(r @ r)

    def tracking(self, pd, exact: bool = True):
        """(per joint RMS position error, rad; the recorded q, the simulated q, their times) over every
        window; ``exact``: through the position stack's own servo code."""
        self.exact = exact
        try:
            _, preds, records = self.residual_fn(pd.as_vector(), pd, return_pred_all=True)
        finally:
            self.exact = False
        n = len(self.names)
        records, preds = [r[0] for r in records], [p[0] for p in preds]
        t = np.concatenate([r.times for r in records])
        q_rec = np.concatenate([r.data[:, :n] for r in records])
        q_sim = np.concatenate([p.data[:, :n] for p in preds])
        return np.sqrt(np.mean((q_sim - q_rec) ** 2, axis=0)), t, q_rec, q_sim

    def fit(self, pd, free=None, max_iters: int = 20):
        """The toolbox's least squares over the parameters named in ``free`` (all: None)."""
        work = pd.copy()
        for key in work.keys():
            work[key].frozen = free is not None and key not in free
        if work.size == 0:
            return work, None
        opt, result = self.sysid.optimize(work, self.residual_fn, optimizer="mujoco", verbose=False,
                                          max_iters=max_iters, eps=FD_STEP, output=io.StringIO())  # fmt: skip
        for key in opt.keys():
            opt[key].frozen = False
        return opt, result


def calibrate(
    model,
    rec,
    *,
    delays=range(0, 5),
    fields=FACTORS,
    structures=None,
    window: float = 0.5,
    timestep: float | None = None,
    fine_iters: int = 2,
    final_iters: int = 2,
    progress=None,
) -> tuple[Calibration, Problem, object, object, object]:
    """Fit each joint's servo (and optionally joint damping, friction loss, armature), its structure
    and the delay.

    ``structures``: the candidate servo structures (``jaxsync.physics.servo.STRUCTURES`` names;
    default all three), each scanned over the delays on three windows in four and scored on the
    fourth (on every other in a recording of under 8 windows); the best is fitted on every window.

    Returns the :class:`Calibration` and, for the report, the problem, the
    starting and fitted ``ParameterDict`` and the toolbox's result."""
    unknown = [f for f in fields if f not in FIELDS]
    if unknown or not set(FACTORS) <= set(fields):
        raise ConfigError(f"fields must hold {list(FACTORS)} and any of {list(FIELDS[2:])}, got {list(fields)}",
                          inputs=("fit",))  # fmt: skip
    names = list(STRUCTURES) if structures is None else list(structures)
    bad = [n for n in names if n not in STRUCTURES]
    if bad or not names:
        raise ConfigError(f"structures must be one or more of {list(STRUCTURES)}, got {list(names)}",
                          inputs=("structures",))  # fmt: skip
    say = progress or (lambda text: None)
    start = time.perf_counter()
    scanned = [int(d) for d in delays]
    ef = None
    if rec.effort is not None:
        # the joints' torques read the delay and the structure directly (a linear fit, every candidate, in
        # a second): the motion is fitted at theirs, and the gains they fix are checked against it
        ef = _efforts.fit_efforts(model, rec, scanned, names)
        if ef.decisive():
            delays, names = [ef.delay], [ef.structure]
        say(f"joint efforts: the {ef.structure} servo at delay {ef.delay}"
            f"{'' if ef.decisive() else ' (not decisive: the motion decides)'} "
            f"({time.perf_counter() - start:.1f} s)")  # fmt: skip
    step = float(model.mj_model.opt.timestep)
    fine_step = timestep or replay_step(model)
    # each structure: the delay scanned (joint by joint, on the model's own step: the delay shows at any
    # step) on three windows in four, the held-out fourth scored at the best delay
    scans, held_costs, best_so_far = {}, {}, np.inf
    for name in names:
        coarse = Problem(model, rec, window, max(step, fine_step), structure=STRUCTURES[name])
        nominal = coarse.replay.nominal()
        pd0 = coarse.parameters(nominal, fields)
        train, held = (_split(coarse, HELD_OUT_EVERY, keep) for keep in (True, False))
        if len(names) == 1 or held is None:
            train = coarse
        costs, fitted = {}, {}
        fixed = ef.delay_of(name) if ef is not None and len(delays) > 1 else None
        if fixed is not None:
            say(f"{name}: the joint efforts give delay {fixed} (the next delay at least {_efforts.DECISIVE:.0%} worse)")
        for delay in delays if fixed is None else [fixed]:
            rising = len(costs) >= 2 and costs[max(costs)] > 2.0 * min(costs.values())
            if rising and max(costs) > min(costs, key=costs.get):
                break  # past the best delay and well above it: the cost rises from here on
            if costs and min(costs.values()) > SCREEN_FACTOR * best_so_far:
                break  # far behind another structure on the same windows: no delay brings it back
            costs[int(delay)], fitted[int(delay)] = _joint_by_joint(train, pd0, fields, int(delay), SCAN_ITERS)
            say(f"{name}, delay {delay}: joint-by-joint fit, cost {costs[int(delay)]:.4g} "
                f"({time.perf_counter() - start:.1f} s)")  # fmt: skip
        best = min(costs, key=costs.get)
        best_so_far = min(best_so_far, costs[best])
        if len(names) > 1 and held is not None:
            held.delay = best
            held_costs[name] = held.cost(fitted[best])
            say(f"{name}: held-out cost {held_costs[name]:.4g} at delay {best} ({time.perf_counter() - start:.1f} s)")
        scans[name] = (coarse, nominal, pd0, costs, fitted, best)
    chosen = min(held_costs, key=held_costs.get) if held_costs else names[0]
    coarse, nominal, pd0, costs, fitted, best = scans[chosen]
    fine = Problem(model, rec, window, fine_step, structure=STRUCTURES[chosen]) if fine_step < step else coarse
    fine.parameters(nominal, fields)
    prob = fine
    pd = fitted[best]
    if fine is not coarse:
        _, pd = _joint_by_joint(fine, pd, fields, best, fine_iters)
        say(f"{chosen}, delay {best}: joint-by-joint fit at a {fine.replay.timestep * 1000:g} ms step "
            f"({time.perf_counter() - start:.1f} s)")  # fmt: skip
    pd, result = prob.fit(pd, max_iters=final_iters)
    say(f"delay {best}: all {pd.size} parameters together ({time.perf_counter() - start:.1f} s)")
    half = np.full(pd.size, np.inf)  # without a Jacobian no parameter has an interval
    windows = (np.full(pd.size, np.nan),) * 3
    if result is not None and result.jac is not None:
        res, _, _ = prob.residual_fn(pd.as_vector(), pd)
        jac = np.asarray(result.jac)
        half = np.nan_to_num(np.asarray(prob.sysid.calculate_intervals(res, jac)[1], float), nan=np.inf)
        windows = clustered_intervals(res, jac)
    # the Jacobian's intervals see white noise only, not a model error the windows share (their sandwich), a
    # valley of gains (each half of the windows fitted again), a fit stopped short (the Gauss-Newton step
    # still open) or the replay step's bias (each joint fitted on half the step): the largest is stated
    halves = [_joint_by_joint(_halved(prob, k), pd, fields, best, HALF_ITERS)[1] for k in (0, 1)]
    spread = np.abs(halves[0].as_vector() - halves[1].as_vector())
    say(f"delay {best}: each half of the windows fitted again ({time.perf_counter() - start:.1f} s)")
    finer = Problem(model, rec, window, prob.replay.timestep / 2, structure=STRUCTURES[chosen])
    finer.parameters(nominal, fields)
    stepped = 2.0 * np.abs(pd.as_vector() - _joint_by_joint(finer, pd, fields, best, STEP_ITERS)[1].as_vector())
    say(f"delay {best}: each joint fitted again on half the step ({time.perf_counter() - start:.1f} s)")
    parts = {"jacobian": half, "windows": windows[0], "halves": spread, "open_step": windows[2], "step": stepped}
    half = np.fmax.reduce(list(parts.values()))
    parts = {k: prob.intervals_of(pd, v) for k, v in (*parts.items(), ("windows_se", windows[1]))}
    intervals = prob.intervals_of(pd, np.asarray(half))
    from_efforts = ()
    inertia = joint_inertia(model).reshape(-1)
    sample_period = float(np.median(np.diff(rec.state_times)))
    if ef is not None:  # where the motion leaves a joint's gains open, or cannot resolve them, and the efforts fix
        # them: theirs
        quick = fastest_mode(inertia, prob.joints_of(pd)) < sample_period
        from_efforts = _efforts.take_open_gains(ef, pd, prob.names, nominal, intervals, DETERMINED, FACTOR_BOUNDS,
                                                unresolved=quick)  # fmt: skip
        if from_efforts:
            say(f"gains of {len(from_efforts)} joint(s) the motion leaves open taken from the efforts")
    before = prob.tracking(pd0)[0]
    after = prob.tracking(pd)[0]
    motion = np.sqrt(np.mean((rec.q - rec.q.mean(axis=0)) ** 2, axis=0))
    cal = Calibration(
        joints=prob.names, delay=best, period=prob.period, fitted=prob.joints_of(pd), nominal=nominal,
        intervals=intervals, rms_before=before, rms_after=after, motion=motion,
        delay_costs=costs, fields=tuple(fields), seconds=time.perf_counter() - start,
        windows=len(prob.sequences.sequence_name), noise=noise_floor(rec.q), structure=chosen,
        structure_costs=held_costs, efforts=ef, from_efforts=from_efforts, interval_parts=parts,
        inertia=inertia, sample_period=sample_period,
    )  # fmt: skip
    cal.problems = tuple(problems(cal, scanned, pd))
    return cal, prob, pd0, pd, result


def _joint_by_joint(prob: Problem, pd, fields, delay: int, iters: int):
    """Each joint's parameters of both arms fitted on that joint's windows, in turn; the cost over all."""
    prob.delay = delay
    n = len(prob.names) // 2
    if not hasattr(prob, "blocks"):
        prob.blocks = []
        for j in range(n):
            rows = [i for i, d in enumerate(prob.dominant) if d == j]
            if rows:
                prob.blocks.append(
                    ([f"{prob.names[a * n + j]} {f}" for a in (0, 1) for f in fields], _subset(prob, rows))
                )
    pd = pd.copy()
    for keys, sub in prob.blocks:
        pd, _ = sub.fit(pd, free=keys, max_iters=iters)
    return prob.cost(pd), pd
