"""The controller gains: one pytree whose leaves are what jax.grad and optax see."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import coupling as _coupling
from jaxsync.control import ros2_admittance as _ra
from jaxsync.physics.inertia import pad_apparent_inertia
from jaxsync.physics.servo import joint_inertia, servo_of


class Gains(NamedTuple):
    """All controller parameters. Per-arm arrays are (2, 6): rows right, left;
    columns the pad frame's x, y, z (z: the pad normal) then rotations about
    them. Scalars are () arrays.

    imp_mass, imp_damping, imp_stiffness: M_d, B_d, K_d of eqs. 8-10, 15.
    k_rk, k_lk: relative-error factors of eq. 13 (|k| <= 1).
    k_rl, k_ll: factors of the compliant offsets in eq. 17.
    kp_pos, kd_pos: inner position loop on x_ik - x_i (eq. 18), 1/s^2 and 1/s,
      translation and rotation.
    kp_null, kd_null: null-space posture term of eq. 18.
    ff_vel, ff_acc: position-controlled arms only: the joint command's
      feed-forward of the plan, s and s^2. The command sent to the servo is
      the integrated command plus J# (ff_vel dx_plan + ff_acc ddx_plan)
      (``jaxsync.control.joint_space.plan_feedforward``): a lead over the
      command delay, and the inverse of a joint servo's inertial lag (I_j /
      k_j = 1 / w_j^2). Zero by default (none).

    The baselines' own gains ((6,) arrays in the planned pad frame of the
    right arm, which is the object frame: x, y tangential, z the clamp
    normal, then rotations; ``jaxsync.control.baselines``):
    obj_mass, obj_damping, obj_stiffness: the object-level (external)
      impedance M_E, D_E, K_E of Caccavale et al. 2008 ("object_impedance";
      its internal impedance is imp_mass, imp_damping, imp_stiffness).
    force_p, force_i: the proportional (m/N, rad/(N m)) and integral
      (m/(N s), rad/(N m s)) gains of the internal-force loop on the relative
      variable ("task_space", Chiacchio, Chiaverini and Siciliano 1996).

    The coupling family on top of ros2_controllers' rule ("ros2_coupled",
    ``jaxsync.control.coupling``), (2, 6) per arm and pad axis:
    cpl_rel, cpl_own, cpl_other, cpl_force: each channel's gain (0: none,
      |c| <= 2) on the absolute errors' difference, the arm's own rule
      offset, the other arm's, and the other arm's wrench error over the
      arm's own admittance;
    cpl_rel_a, cpl_own_a, cpl_other_a, cpl_force_a: each channel's
      first-order filter coefficient, (0, 1] (1: unfiltered);
    cpl_block: (4, 2, 6, 6), each channel's full pad-frame block per arm
      off its diagonal (the diagonal is the channel's gain; 0: diagonal).
    """

    imp_mass: jax.Array
    imp_damping: jax.Array
    imp_stiffness: jax.Array
    k_rk: jax.Array
    k_lk: jax.Array
    k_rl: jax.Array
    k_ll: jax.Array
    kp_pos: jax.Array
    kd_pos: jax.Array
    kp_null: jax.Array
    kd_null: jax.Array
    obj_mass: jax.Array
    obj_damping: jax.Array
    obj_stiffness: jax.Array
    force_p: jax.Array
    force_i: jax.Array
    ff_vel: jax.Array
    ff_acc: jax.Array
    cpl_rel: jax.Array
    cpl_own: jax.Array
    cpl_other: jax.Array
    cpl_force: jax.Array
    cpl_rel_a: jax.Array
    cpl_own_a: jax.Array
    cpl_other_a: jax.Array
    cpl_force_a: jax.Array
    cpl_block: jax.Array


# the gains each controller reads besides the shared joint-space law's (kp_pos, kd_pos, kp_null, kd_null)
IMPEDANCE_FIELDS = ("imp_mass", "imp_damping", "imp_stiffness")
COUPLING_FIELDS = ("k_rk", "k_lk", "k_rl", "k_ll")  # the paper's relative-error and cross-term factors
FAMILY_FIELDS = _coupling.FIELDS
USED = {
    "classical": IMPEDANCE_FIELDS,
    "synchronous": IMPEDANCE_FIELDS + COUPLING_FIELDS,
    "object_impedance": IMPEDANCE_FIELDS + ("obj_mass", "obj_damping", "obj_stiffness"),
    "task_space": ("force_p", "force_i"),
    # ros2_controllers' rule: mass, D (as its damping ratio) and K per arm; its reference joints follow
    # the plan with the joint-space law's gains
    "ros2_admittance": IMPEDANCE_FIELDS,
    # the rule plus the coupling: its relative-error and cross-term factors
    "ros2_synchronous": IMPEDANCE_FIELDS + COUPLING_FIELDS,
    # the rule plus the coupling family (jaxsync.control.coupling): its channels' gains and filters
    "ros2_coupled": IMPEDANCE_FIELDS + FAMILY_FIELDS,
    "ros2_coupled_direct": IMPEDANCE_FIELDS + FAMILY_FIELDS,
}


RULE_RELATIVE_FACTOR = 0.25
"""ros2_synchronous's default relative-error factor, k_rk = -k_lk (half the
synchronous law's 0.5): through ros2_controllers' rule on the position stack
the full factor drops or chatters the ball on the iiwa-like pair in 3 of its
16 held-out scenarios, half holds every one on all three test models
(docs/ros2-rule.md)."""


def default_gains(model=None, actuation: str = "torque", controller: str | None = None) -> Gains:
    """The default gains of ``model``: the paper comparison's for the paper model
    or None (docs/controller.md says why these); for a robot file's model, the
    same with the normal-axis mass each arm's pad needs at the grasp
    (:func:`stable_defaults`). On position-controlled arms
    (``actuation="position"``) the inner loop's bandwidth is held below the
    robot's slowest joint servo (:func:`position_loop_gains`) and the masses
    are raised where ros2_controllers' admittance rule would run them near its
    stability bound (:func:`deployable_gains`). ``controller``
    "ros2_synchronous" takes its own relative-error factor
    (``RULE_RELATIVE_FACTOR``); "ros2_admittance", the rule alone, none of the
    paper's coupling (factors 0: the rule never reads them, and an export
    configures the coupling its gains set); any other or None, the gains every
    controller shares. Every command and library job takes a model's defaults from here.

    Example:
      >>> float(default_gains().imp_mass[0, 2])
      2.0
    """
    if controller == "ros2_admittance":
        g = default_gains(model, actuation)
        zero = jnp.zeros_like(g.k_rk)
        return g._replace(k_rk=zero, k_lk=zero, k_rl=zero, k_ll=zero)
    if controller == "ros2_synchronous":
        g = default_gains(model, actuation)
        k = jnp.full_like(g.k_rk, RULE_RELATIVE_FACTOR)  # full_like keeps the (strong) dtype
        return g._replace(k_rk=k, k_lk=-k)
    if actuation == "position" and model is not None:
        dt = float(model.mj_model.opt.timestep)
        return servo_lag_lead(deployable_gains(position_loop_gains(default_gains(model), model), dt), model)
    if model is not None and getattr(model, "robot", None) is not None:
        return stable_defaults(pad_apparent_inertia(model.mj_model), float(model.mj_model.opt.timestep))
    # Pad frame: x, y tangential, z along the normal. Soft along the normal
    # (the grip force is regulated through it), stiff tangentially and in
    # rotation so the grasp keeps its geometry while the object is carried.
    mass = np.array([2.0, 2.0, 2.0, 0.05, 0.05, 0.05])
    stiffness = np.array([1500.0, 1500.0, 50.0, 40.0, 40.0, 40.0])
    zeta = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    damping = 2 * zeta * np.sqrt(mass * stiffness)
    damping[2] = 2000.0  # normal: dominated by damping, an integrating force loop
    two = lambda v: np.stack([v, v])  # noqa: E731
    g = Gains(
        imp_mass=two(mass),
        imp_damping=two(damping),
        imp_stiffness=two(stiffness),
        k_rk=0.5,
        k_lk=-0.5,
        k_rl=0.5,
        k_ll=0.5,
        kp_pos=1600.0,
        kd_pos=80.0,
        kp_null=100.0,
        kd_null=20.0,
        # the object-level impedance at twice one arm's: a force on the object
        # moves it as the classical controller moves both pads (docs/controller.md)
        obj_mass=2 * mass,
        obj_damping=2 * damping,
        obj_stiffness=2 * stiffness,
        # the internal-force loop: along the normal, integral at the classical
        # normal axis's 1/B_d with a small proportional part; tangentially and
        # in rotation proportional at the classical 1/K_d
        force_p=np.array([1 / 1500, 1 / 1500, 1e-4, 1 / 40, 1 / 40, 1 / 40]),
        force_i=np.array([1e-4, 1e-4, 1 / 2000, 1e-3, 1e-3, 1e-3]),
        ff_vel=0.0,
        ff_acc=0.0,
        # no coupling: ros2_coupled starts as the rule alone
        **{f: np.zeros((2, 6)) for f in _coupling.GAIN_FIELDS},
        **{f: np.ones((2, 6)) for f in _coupling.FILTER_FIELDS},
        cpl_block=np.zeros((len(_coupling.CHANNELS), 2, 6, 6)),
    )
    return strongly_typed(g)


SERVO_SEPARATION = 3.0
"""How many times slower than the slowest joint servo the position stack's
inner loop closes (:func:`position_loop_gains`)."""


def position_loop_gains(g: Gains, model) -> Gains:
    """``g`` with the inner loop's bandwidth lambda = 2 kp_pos / kd_pos held at
    or below min_j sqrt(k_j / I_j) / ``SERVO_SEPARATION``, the slowest joint
    servo's natural frequency (``jaxsync.physics.servo``) over 3: an outer
    loop that closes faster than the servo it commands rings with it, and a
    command delay makes that ring grow (measured on the iiwa-like pair, whose
    MJCF servo gives its shoulder 28 rad/s at a damping ratio of 0.35: at
    lambda = 40 1/s the synchronous controller dropped the object at 2 and 3
    periods of delay; at 9.4 1/s it held it at every delay from 0 to 3).
    Unchanged where the servo is fast enough (the paper model, 25 Hz servos)."""
    servo = servo_of(model)
    slowest = float(np.min(np.sqrt(servo.stiffness / joint_inertia(model))))
    lam = 2.0 * float(g.kp_pos) / float(g.kd_pos)
    if lam * SERVO_SEPARATION <= slowest:
        return g
    return g._replace(kp_pos=jnp.asarray(slowest / SERVO_SEPARATION * float(g.kd_pos) / 2.0))


def servo_lag_lead(g: Gains, model) -> Gains:
    """``g`` with the plan's velocity feed-forward ``ff_vel`` at the servo's lag
    b_j / k_j (the median over the joints, at most ``FF_VEL_MAX``) where the
    servo does not feed the command's velocity forward itself
    (``jaxsync.physics.servo``): such a servo holds b_j q_dot against a moving
    command, and J# ff_vel x_dot_plan sent on top gives back
    k_j ff_vel q_dot_plan = b_j q_dot_plan. Measured on a pair with the FR3's
    servo as written (b / k = 0.1 s): at ff_vel = 0 the classical law dropped
    the object at every delay 0-3; at 0.05 s it held it (docs/servo.md).
    Unchanged (0) where the servo feeds the velocity forward."""
    servo = servo_of(model)
    if servo.velocity_feedforward:
        return g
    lag = float(np.median(servo.damping / servo.stiffness))
    return g._replace(ff_vel=jnp.asarray(min(max(lag, 0.0), FF_VEL_MAX), dtype=jnp.asarray(g.ff_vel).dtype))


def servo_limits_loop(model) -> bool:
    """Whether the robot's slowest joint servo lowers the position stack's
    inner loop below the default gains' (:func:`position_loop_gains`): the
    iiwa-like pair yes, the paper model and the UR5e-like pair no. Where it
    does, the loop's bandwidth is a trade the delay and the servo decide, and
    the tuner moves kp_pos too (``optimize.tuning.params.TuneSpec.for_model``)."""
    g = default_gains()
    return float(position_loop_gains(g, model).kp_pos) < float(g.kp_pos)


def deployable_gains(g: Gains, dt: float) -> Gains:
    """``g`` with each impedance mass raised where ros2_controllers' admittance
    rule, explicit in D and K, would run the axis at control period ``dt``
    within its margin of instability
    (``jaxsync.control.ros2_admittance.deployable_mass``: stable with D/M and
    K/M raised 1.5 times). On the paper model's normal axis (D = 2000 N s/m,
    2 ms) the mass goes from 2 to 3 kg; the other axes are far from it."""
    mass = _ra.deployable_mass(np.asarray(g.imp_mass), np.asarray(g.imp_damping), np.asarray(g.imp_stiffness), dt)
    return g._replace(imp_mass=jnp.asarray(mass, dtype=jnp.asarray(g.imp_mass).dtype))


# ------------------------------------------------------- stable at the control period

STABILITY_MARGIN = 1.5
"""How far the normal axis's effective virtual mass must exceed the pad's
apparent inertia along the normal (``stability_ratio``) for a robot's default gains."""
NORMAL = 2  # the pad frame's normal axis in the (x, y, z, rx, ry, rz) impedance vectors


def stability_ratio(g: Gains, apparent_inertia, dt: float) -> np.ndarray:
    """(2,) per arm: (M_n + B_n dt + K_n dt^2) / Lambda_n along the pad normal.

    Why (docs/robots.md): the admittance filter, integrated implicitly,
    answers a change df in the measured force within one control period with
    an acceleration df / (M + B dt + K dt^2); the joint-space law commands
    that acceleration through the arm's inertia, so against a stiff contact
    the pad pushes back with Lambda / (M + B dt + K dt^2) times df one period
    later. Above one that loop grows, flipping sign every period (chatter at
    half the control rate); below one it decays. Measured: the paper model's
    defaults stand at 1.31 (stable; its softest contacts chattered after the
    tuner lowered the ratio by a few per cent), the UR5e-like arm at 0.87
    chattered, the iiwa-14-like arm at 1.38 did not.

    ``apparent_inertia``: (2, 6) from ``jaxsync.physics.inertia.pad_apparent_inertia``.
    """
    lam = np.asarray(apparent_inertia, dtype=float)[:, NORMAL]
    m, b, k = (np.asarray(x, dtype=float)[:, NORMAL] for x in (g.imp_mass, g.imp_damping, g.imp_stiffness))
    return (m + b * dt + k * dt**2) / lam


def stable_defaults(apparent_inertia, dt: float, base: Gains | None = None) -> Gains:
    """``base`` (the default gains) with each arm's normal-axis impedance mass
    raised, where needed, until ``stability_ratio`` is ``STABILITY_MARGIN``;
    damping and stiffness kept (the normal axis stays an integrating force
    loop, its time constant M/B a few milliseconds)."""
    g = base if base is not None else default_gains()
    lam = np.asarray(apparent_inertia, dtype=float)[:, NORMAL]
    mass = np.array(g.imp_mass, dtype=float)
    b, k = (np.asarray(x, dtype=float)[:, NORMAL] for x in (g.imp_damping, g.imp_stiffness))
    need = STABILITY_MARGIN * lam - b * dt - k * dt**2
    mass[:, NORMAL] = np.maximum(mass[:, NORMAL], need)
    # the object-level impedance answers with both pads: per pad, half its mass
    obj_mass = np.array(g.obj_mass, dtype=float)
    obj_mass[NORMAL] = max(obj_mass[NORMAL], 2 * float(mass[:, NORMAL].max()))
    return strongly_typed(g._replace(imp_mass=mass, obj_mass=obj_mass))


def strongly_typed(g):
    """``g`` (gains, or any pytree of them: a schedule) with every weakly
    typed or non-float leaf (a Python number, or ``jnp.asarray(0.2)``) made a
    strongly typed float array; float arrays are kept as they are. Works on
    traced values too. A jitted rollout compiles
    once per argument type, and a weak float is another type: ``k_rl=0.2``
    beside the default gains compiled a second 1.7 s rollout for 29 s on 2
    cores (measured); :func:`jaxsync.rollout` calls this first.

    Example:
      >>> g = strongly_typed(default_gains()._replace(k_rl=0.2))
      >>> g.k_rl.weak_type, g.k_rl.dtype == g.k_ll.dtype
      (False, True)
    """

    def strong(x):
        x = jnp.asarray(x)
        if x.weak_type or not jnp.issubdtype(x.dtype, jnp.floating):
            return jnp.asarray(x, dtype=jnp.result_type(float))
        return x

    return jax.tree_util.tree_map(strong, g)


def classical_equivalent(g: Gains) -> Gains:
    """The synchronous gains that reduce it to the classical controller
    (k_rk = k_lk = 0, k_rl = k_ll = 1; the cross term is switched off
    separately: ``ControllerOptions(cross_term="none")``)."""
    z, o = jnp.zeros_like(g.k_rk), jnp.ones_like(g.k_rl)  # zeros_like keeps the (strong) dtype
    return g._replace(k_rk=z, k_lk=z, k_rl=o, k_ll=o)


# ----------------------------------------------------------------- validation

FF_VEL_MAX = 0.05
"""|ff_vel| <= 0.05 s: 25 control periods of lead at 500 Hz."""
FF_ACC_MAX = 0.01
"""|ff_acc| <= 0.01 s^2: the inertial lag of a joint servo of 10 rad/s."""

_BOUNDS = {
    "imp_mass": (0.0, math.inf, False),
    "imp_damping": (0.0, math.inf, False),
    "imp_stiffness": (0.0, math.inf, True),
    "k_rk": (-1.0, 1.0, True),
    "k_lk": (-1.0, 1.0, True),
    "k_rl": (-1.0, 1.0, True),
    "k_ll": (-1.0, 1.0, True),
    "kp_pos": (0.0, math.inf, False),
    "kd_pos": (0.0, math.inf, False),
    "kp_null": (0.0, math.inf, True),
    "kd_null": (0.0, math.inf, True),
    "obj_mass": (0.0, math.inf, False),
    "obj_damping": (0.0, math.inf, False),
    "obj_stiffness": (0.0, math.inf, True),
    "force_p": (0.0, math.inf, True),
    "force_i": (0.0, math.inf, True),
    "ff_vel": (-FF_VEL_MAX, FF_VEL_MAX, True),
    "ff_acc": (-FF_ACC_MAX, FF_ACC_MAX, True),
    **{f: (-_coupling.GAIN_MAX, _coupling.GAIN_MAX, True) for f in _coupling.GAIN_FIELDS},
    **{f: (0.0, 1.0, False) for f in _coupling.FILTER_FIELDS},
    _coupling.BLOCK_FIELD: (-_coupling.GAIN_MAX, _coupling.GAIN_MAX, True),
}


def validate(g: Gains) -> Gains:
    """Check shapes and ranges eagerly (outside jit); raise ConfigError naming the field."""
    ref = default_gains()
    for name in Gains._fields:
        value = np.asarray(getattr(g, name), dtype=float)
        want = np.shape(getattr(ref, name))
        if value.shape != want:
            raise ConfigError(f"gain '{name}' must have shape {want}, got {value.shape}")
        if not np.all(np.isfinite(value)):
            raise ConfigError(f"gain '{name}' must be finite, got {value.tolist()}")
        lo, hi, closed = _BOUNDS[name]
        ok = (value >= lo) & (value <= hi) if closed else (value > lo) & (value <= hi)
        if not np.all(ok):
            rng = f"[{lo}, {hi}]" if closed else f"({lo}, {hi}]"
            raise ConfigError(f"gain '{name}' must lie in {rng}, got {value.tolist()}")
    block = np.asarray(getattr(g, _coupling.BLOCK_FIELD), dtype=float)
    if np.any(np.diagonal(block, axis1=-2, axis2=-1) != 0.0):
        raise ConfigError(
            f"gain '{_coupling.BLOCK_FIELD}' is each channel's block off its diagonal: its diagonal must be 0 "
            f"(the diagonal is the channel's own gain, {', '.join(_coupling.GAIN_FIELDS)})"
        )
    return g


def to_dict(g: Gains) -> dict:
    return {k: np.asarray(v).tolist() for k, v in g._asdict().items()}


def _is_numbers(v) -> bool:
    """A number, or a (nested) list of numbers; JSON's true/false are not numbers here."""
    if isinstance(v, bool | np.bool_):
        return False
    if isinstance(v, np.ndarray):
        return v.size > 0 and (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer))
    if isinstance(v, int | float | np.floating | np.integer):
        return True
    return isinstance(v, list | tuple) and len(v) > 0 and all(_is_numbers(x) for x in v)


def from_dict(d: dict, base: Gains | None = None) -> Gains:
    """Gains from a (possibly partial) dict; missing keys keep ``base`` (defaults)."""
    base = base if base is not None else default_gains()
    if not isinstance(d, dict):
        raise ConfigError(f"gains must be a JSON object of name: value, got {type(d).__name__} {d!r}")
    unknown = sorted(set(d) - set(Gains._fields))
    if unknown:
        raise ConfigError(f"unknown gain(s) {unknown}; known: {list(Gains._fields)}")
    fields = base._asdict()
    for k, v in d.items():
        ref = np.asarray(fields[k])
        if not _is_numbers(v):
            raise ConfigError(f"gain {k!r} must be a number or a list of numbers (not true/false or text), got {v!r}")
        arr = np.asarray(v, dtype=float)
        if arr.shape == () and ref.shape != ():
            arr = np.full(ref.shape, float(arr))  # a scalar for every arm and axis
        elif arr.shape == (6,) and ref.shape == (2, 6):
            arr = np.stack([arr, arr])  # the same per-axis values for both arms
        fields[k] = arr
    return validate(strongly_typed(Gains(**fields)))
