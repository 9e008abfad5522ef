"""The controllers, as pure functions over explicit state.

The paper's two:
``classical``: impedance only (eqs. 8-11, 15): x_ic = x_id + e_i.
``synchronous``: impedance plus absolute/relative errors (eqs. 12-17):
x_ik = x_id + delta_ik + k_il (e_i + T_ij e_j).
Two baselines of the dual-arm literature (``jaxsync.control.baselines``):
``object_impedance``: an external impedance of the object and an internal
impedance per pad (Caccavale, Chiacchio, Marino, Villani 2008).
``task_space``: the absolute variable tracked, the relative one corrected
by an internal-force PI loop (Chiacchio, Chiaverini, Siciliano 1996;
Caccavale, Chiacchio, Chiaverini 2000).
Every one computes the offset of the planned pad poses from the same
sensing and ends in the same joint-space law (eqs. 18, 19).
On position-controlled arms only (``jaxsync.control.ros2_loop``):
``ros2_admittance``: ros2_controllers' admittance rule per arm, as deployed,
offsetting a reference joint trajectory that follows the plan.
``ros2_synchronous``: the same rule, the reference it offsets following the
plan plus the synchronous offset of eqs. 12-17 less the rule's own, so that
the command carries the paper's law.
``ros2_coupled``: the same rule plus the coupling family of
``jaxsync.control.coupling`` (per-axis gains on the absolute errors'
difference, the rules' offsets and the other arm's wrench error, each
filtered), of which the other two are special cases, entering through the
reference's target; ``ros2_coupled_direct`` the same family put onto the
rule's reference joints in the same period.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxsync._errors import ConfigError
from jaxsync.control import baselines as _baselines
from jaxsync.control import coupling as _coupling
from jaxsync.control import impedance as _impedance
from jaxsync.control import joint_space as _joint_space
from jaxsync.control import ros2_admittance as _ra
from jaxsync.control import ros2_loop as _ros2_loop
from jaxsync.control import so3 as _so3
from jaxsync.control import sync as _sync
from jaxsync.control.gains import Gains
from jaxsync.control.names import (
    ALL_CONTROLLERS,
    CONTROLLERS,
    FAMILY,
    POSITION_ONLY,
)  # re-exported: jaxsync.CONTROLLERS
from jaxsync.physics.sensing import ArmState


@dataclasses.dataclass(frozen=True)
class ControllerOptions:
    """Static choices (changing them recompiles; they are never traced).

    Example:
      >>> ControllerOptions(kind="classical")
      ControllerOptions(kind='classical', cross_term='squeeze', distro='jazzy')
    """

    kind: str = "synchronous"  # one of ALL_CONTROLLERS
    cross_term: str = "squeeze"  # eq. 16's T_ij e_j, see jaxsync.control.sync.CROSS_TERMS
    distro: str = _ros2_loop.DEFAULT_DISTRO  # ros2_admittance's release (ros2_admittance.DISTROS)

    def __post_init__(self):

        if self.kind not in ALL_CONTROLLERS:
            raise ConfigError(f"controller must be one of {ALL_CONTROLLERS}, got {self.kind!r}")
        if self.cross_term not in _sync.CROSS_TERMS:
            raise ConfigError(f"cross_term must be one of {_sync.CROSS_TERMS}, got {self.cross_term!r}")
        if self.distro not in _ra.DISTROS:
            raise ConfigError(f"distro must be one of {_ra.DISTROS}, got {self.distro!r}")


class ControllerSwitch(NamedTuple):
    """The controller choice as arrays, traced: one compiled program serves
    every controller and every cross term (``jaxsync.rollout``'s program; a
    static :class:`ControllerOptions` compiles one per choice). Each choice
    computes exactly what its static counterpart computes.

    Example:
      >>> int(ControllerSwitch.of(ControllerOptions(kind="classical")).kind)
      0
    """

    kind: jax.Array  # int: index into CONTROLLERS
    cross_term: jax.Array  # int: index into jaxsync.control.sync.CROSS_TERMS

    @classmethod
    def of(cls, options: ControllerOptions) -> ControllerSwitch:
        if options.kind not in CONTROLLERS:
            raise ConfigError(f"controller {options.kind!r} runs from static ControllerOptions only, not a switch")
        return cls(
            kind=jnp.asarray(CONTROLLERS.index(options.kind)),
            cross_term=jnp.asarray(_sync.CROSS_TERMS.index(options.cross_term)),
        )


class Reference(NamedTuple):
    """The planned pad poses x_id and what the arms should feel, at one instant.

    Rollouts build it from the scenario's plan (``jaxsync.sim.closed_loop.reference``);
    a user's own loop can fill it directly.

    Example:
      >>> ref = Reference(pad_pos=jnp.zeros((2, 3)), pad_rot=jnp.stack([jnp.eye(3)] * 2),
      ...                 pad_vel=jnp.zeros((2, 6)), pad_acc=jnp.zeros((2, 6)),
      ...                 wrench=jnp.zeros((2, 6)), q_rest=jnp.zeros((2, 7)))
    """

    pad_pos: jax.Array  # (2, 3)
    pad_rot: jax.Array  # (2, 3, 3)
    pad_vel: jax.Array  # (2, 6) (the planned orientation is constant: angular part 0)
    pad_acc: jax.Array  # (2, 6)
    wrench: jax.Array  # (2, 6) f_id
    q_rest: jax.Array  # (2, 7) posture for the null-space term


class ControllerState(NamedTuple):
    """Every controller's state (a controller leaves the others' parts as they are)."""

    impedance: _impedance.ImpedanceState  # the per-pad admittance filters (object_impedance: the internal ones)
    object: _baselines.ObjectState  # object_impedance's compliant object frame
    force_integral: jax.Array  # (2, 6) task_space's integral of the internal wrench
    ros2: _ros2_loop.Ros2State  # ros2_admittance's reference joints q_ref and the two arms' rule states
    wrench_filter: jax.Array  # (2, 6) position-controlled arms: f_i - f_id through the F/T filter, world
    coupling: _coupling.CouplingState  # ros2_coupled's channel filters (jaxsync.control.coupling)


class ControlInfo(NamedTuple):
    """Internals recorded for metrics and plots."""

    offset: jax.Array  # (2, 6) x_ik - x_id (the classical: e_i)
    delta: jax.Array  # (2, 6) absolute errors delta_i = x_id - x_i (eq. 12)
    force_error: jax.Array  # (2, 6) f_i - f_id


def init(q0: jax.Array | None = None) -> ControllerState:
    """The controller's state at rest: both admittance filters at zero offset
    and rate. ``q0`` (2 n,): the arms' joint positions at the start, where
    ros2_admittance's reference joints begin (None: 7 joints per arm at zero,
    for the controllers that do not read them).

    Example:
      >>> state = init()
      >>> state.impedance.offset.shape
      (2, 6)
    """
    return ControllerState(
        impedance=_impedance.init(),
        object=_baselines.init_object(),
        force_integral=jnp.zeros((2, 6)),
        ros2=_ros2_loop.init(jnp.zeros(14) if q0 is None else q0),
        wrench_filter=jnp.zeros((2, 6)),
        coupling=_coupling.init(),
    )


class Pads(NamedTuple):
    """What a controller's offsets read of the arms: each pad's pose and the
    wrench the object exerts on it (world frame, about the pad)."""

    pos: jax.Array  # (2, 3)
    rot: jax.Array  # (2, 3, 3)
    wrench: jax.Array  # (2, 6)

    @classmethod
    def of(cls, arms) -> Pads:
        return cls(
            pos=jnp.stack([a.pad_pos for a in arms]),
            rot=jnp.stack([a.pad_rot for a in arms]),
            wrench=jnp.stack([a.wrench for a in arms]),
        )


def offsets(options, gains: Gains, state: ControllerState, pads: Pads, ref: Reference, dt: float, force_error=None):
    """Each pad's compliant offset from its plan (the part of a controller
    before the joint-space law).

    ``force_error`` (2, 6): what the laws read as f_i - f_id (None: from
    ``pads.wrench``, unfiltered). Returns ((off, off_vel, off_acc), the new
    state, delta, force_error): offsets x_ic - x_id, their rates and
    accelerations (2, 6) world frame, the absolute errors delta_i = x_id -
    x_i (eq. 12) and the force error read.
    """
    if force_error is None:
        force_error = pads.wrench - ref.wrench
    delta = jnp.stack(
        [_sync.absolute_error(ref.pad_pos[i], ref.pad_rot[i], pads.pos[i], pads.rot[i]) for i in range(2)]
    )
    args = (gains, state, ref, force_error, delta, dt)
    if isinstance(options, ControllerSwitch):  # every law, the choice traced

        def cross(v):
            return jnp.stack([_sync.cross_mapped(v, ref.pad_pos, t) for t in _sync.CROSS_TERMS])[options.cross_term]

        laws = [lambda a, k=k: _LAWS[k](*a, cross) for k in CONTROLLERS]
        out, state = jax.lax.switch(options.kind, laws, args)
    else:

        def cross(v):
            return _sync.cross_mapped(v, ref.pad_pos, options.cross_term)

        out, state = (_LAWS.get(options.kind) or _CARTESIAN_STANDINS[options.kind])(*args, cross)
    return out, state, delta, force_error


def step(
    options: ControllerOptions | ControllerSwitch,
    gains: Gains,
    state: ControllerState,
    arms: tuple[ArmState, ArmState],
    ref: Reference,
    dt: float,
) -> tuple[jax.Array, ControllerState, ControlInfo]:
    """One control period of any controller.

    Args:
      options: static controller choice (or a traced :class:`ControllerSwitch`).
      gains: the gain pytree.
      state: the controllers' filters.
      arms: sensed (right, left) arm states; ``wrench`` is the wrist reading.
      ref: planned poses and desired wrenches.
      dt: control period, s.
    Returns:
      (2 n,) joint torques (right arm's n, then left's), the new state, info.

    Example (one period, from a sensed state ``sensed = jaxsync.sense(...)``):
      >>> state = init()
      >>> tau, state, info = step(ControllerOptions(), jaxsync.default_gains(), state,
      ...                         (sensed.right, sensed.left), ref, dt=0.002)  # doctest: +SKIP
      >>> tau.shape  # doctest: +SKIP
      (14,)
    """
    if not isinstance(options, ControllerSwitch):
        _ros2_loop.check_actuation(options.kind, "torque")
    (off, off_vel, off_acc), state, delta, force_error = offsets(options, gains, state, Pads.of(arms), ref, dt)
    taus = []
    for i in range(2):
        pos_ref = ref.pad_pos[i] + off[i, :3]
        rot_ref = _so3.exp(off[i, 3:]) @ ref.pad_rot[i]
        ddx = _joint_space.reference_acceleration(
            arms[i],
            pos_ref,
            rot_ref,
            ref.pad_vel[i] + off_vel[i],
            ref.pad_acc[i] + off_acc[i],
            gains.kp_pos,
            gains.kd_pos,
        )
        taus.append(_joint_space.torques(arms[i], ddx, ref.q_rest[i], gains.kp_null, gains.kd_null, ref.wrench[i]))
    info = ControlInfo(offset=off, delta=delta, force_error=force_error)
    return jnp.concatenate(taus), state, info


def step_position(
    options: ControllerOptions | ControllerSwitch,
    gains: Gains,
    state: ControllerState,
    arms: tuple[ArmState, ArmState],
    ref: Reference,
    dt: float,
    command: jax.Array,
    ft_filter=1.0,
) -> tuple[jax.Array, ControllerState, ControlInfo]:
    """One control period on position-controlled arms: the same offsets as
    :func:`step`, then each arm's joint position command integrated toward its
    compliant target (``jaxsync.control.joint_space.command_rate``).

    The offsets read the force error through the F/T filter the admittance
    rule applies (ros2_controllers ``admittance_rule_impl.hpp`` J 346-350,
    ``jaxsync.control.ros2_admittance.process_wrench_measurements``), to the
    measurement plus the wrench set-point, world frame, zero at activation:
    h_i' = a (f_i - f_id) + (1 - a) h_i, the rule's ``wrench_world``, so
    that every controller on these arms reads what the rule reads (a = 1:
    the raw error, exactly).

    ``ros2_admittance`` (static options only) runs ros2_controllers' rule
    per arm instead (``jaxsync.control.ros2_loop``); its info's offset is the
    rules' J dq.

    Args: as :func:`step`, and ``command`` (2 n,) the last joint position
    commands (right arm's n, then left's); ``ft_filter`` the F/T filter
    coefficient a (``Scenario.ft_filter``). Returns the next commands (2 n,),
    the new state and info (its force_error from the filtered wrench).
    """
    if not isinstance(options, ControllerSwitch) and options.kind in POSITION_ONLY:
        return _ros2_admittance(options, gains, state, arms, ref, dt, ft_filter)
    pads = Pads.of(arms)
    filtered = ft_filter * (pads.wrench - ref.wrench) + (1.0 - ft_filter) * state.wrench_filter
    state = state._replace(wrench_filter=filtered)
    (off, off_vel, _), state, delta, force_error = offsets(options, gains, state, pads, ref, dt, filtered)
    n = command.shape[0] // 2
    out = []
    for i in range(2):
        q_cmd = command[i * n : (i + 1) * n]
        rate = _joint_space.command_rate(
            arms[i],
            q_cmd,
            ref.pad_pos[i] + off[i, :3],
            _so3.exp(off[i, 3:]) @ ref.pad_rot[i],
            ref.pad_vel[i] + off_vel[i],
            ref.q_rest[i],
            gains.kp_pos,
            gains.kd_pos,
            gains.kp_null,
            gains.kd_null,
            plan_vel=ref.pad_vel[i],
        )
        out.append(q_cmd + dt * rate)
    info = ControlInfo(offset=off, delta=delta, force_error=force_error)
    return jnp.concatenate(out), state, info


def command_feedforward(options: ControllerOptions | ControllerSwitch, gains: Gains, arms, ref: Reference) -> jax.Array:
    """(2 n,) what each arm's joint command gains on its way to the servo:
    the plan's feed-forward (``jaxsync.control.joint_space.plan_feedforward``,
    gains ``ff_vel`` and ``ff_acc``) for jaxsync's laws; zero for
    ros2_controllers' rule, which has none. :func:`step_position` returns
    the integrated command; the servo gets that plus this."""
    n = arms[0].jac.shape[1]
    if not isinstance(options, ControllerSwitch) and options.kind in POSITION_ONLY:
        return jnp.zeros(2 * n, dtype=arms[0].jac.dtype)
    return jnp.concatenate(
        [
            _joint_space.plan_feedforward(arms[i], ref.pad_vel[i], ref.pad_acc[i], gains.ff_vel, gains.ff_acc)
            for i in range(2)
        ]
    )


def sent_command(options: ControllerOptions | ControllerSwitch, gains: Gains, arms, ref: Reference, command):
    """(2 n,) what the servo gets: the integrated ``command`` plus :func:`command_feedforward`."""
    return command + command_feedforward(options, gains, arms, ref)


def _ros2_admittance(options, gains, state, arms, ref, dt, ft_filter):
    pads = Pads.of(arms)
    delta = jnp.stack(
        [_sync.absolute_error(ref.pad_pos[i], ref.pad_rot[i], pads.pos[i], pads.rot[i]) for i in range(2)]
    )
    coupled = options.kind == "ros2_synchronous"
    args = (gains, state.ros2, arms, ref, dt, options.distro, coupled, options.cross_term, ft_filter)
    if options.kind in FAMILY:
        command, ros2, off, family = _ros2_loop.step(*args, family=state.coupling, placement=FAMILY[options.kind])
        state = state._replace(coupling=family)
    else:
        command, ros2, off = _ros2_loop.step(*args)
    info = ControlInfo(offset=off, delta=delta, force_error=pads.wrench - ref.wrench)
    return command, state._replace(ros2=ros2), info


def _impedance_filters(gains, state, ref, force_error, dt):
    return _impedance.step(
        state.impedance, gains.imp_mass, gains.imp_damping, gains.imp_stiffness, ref.pad_rot, force_error, dt
    )


def _classical(gains, state, ref, force_error, delta, dt, cross):
    """x_ic = x_id + e_i (eq. 11)."""
    imp, dde = _impedance_filters(gains, state, ref, force_error, dt)
    return (imp.offset, imp.rate, dde), state._replace(impedance=imp)


def _synchronous(gains, state, ref, force_error, delta, dt, cross):
    """x_ik - x_id = delta_ik + k_il x_ild, with its rate and acceleration (eqs. 13-17)."""
    imp, dde = _impedance_filters(gains, state, ref, force_error, dt)
    k_il = jnp.stack([gains.k_rl, gains.k_ll])
    delta_k = _sync.relative_compensation(delta, gains.k_rk, gains.k_lk)
    off = _sync.synchronous_offset(delta_k, k_il, cross(imp.offset))
    return (off, k_il[:, None] * cross(imp.rate), k_il[:, None] * cross(dde)), state._replace(impedance=imp)


def _object_impedance(gains, state, ref, force_error, delta, dt, cross):
    """x_ic - x_id = T_i dx_o + dx_i (``jaxsync.control.baselines``)."""
    h_e, h_i = _baselines.split_wrenches(force_error, ref.pad_pos)
    obj, dx, ddx, dddx = _baselines.object_step(
        state.object, gains.obj_mass, gains.obj_damping, gains.obj_stiffness, ref.pad_rot[0], h_e, dt
    )
    imp, dde = _impedance_filters(gains, state, ref, h_i, dt)
    pads = ref.pad_pos
    move = lambda v: _baselines.transport_to_pads(v, pads)  # noqa: E731
    out = (move(dx) + imp.offset, move(ddx) + imp.rate, move(dddx) + dde)
    return out, state._replace(impedance=imp, object=obj)


def _task_space(gains, state, ref, force_error, delta, dt, cross):
    """x_ic - x_id = K_P h_I,i + K_I int h_I,i dt (``jaxsync.control.baselines``)."""
    _, h_i = _baselines.split_wrenches(force_error, ref.pad_pos)
    off, rate, acc, integral = _baselines.task_space_offsets(
        gains.force_p, gains.force_i, state.force_integral, h_i, ref.pad_rot, dt
    )
    return (off, rate, acc), state._replace(force_integral=integral)


_LAWS = {
    "classical": _classical,
    "synchronous": _synchronous,
    "object_impedance": _object_impedance,
    "task_space": _task_space,
}


# the controllers of position-controlled arms integrate in joint space; what the compliance probe reads of
# them is a Cartesian stand-in: the rule's offset as the classical filter's at the pad, and the rule plus the
# coupling, whose command carries the synchronous offset once the reference has caught up, as that law
def _coupled_family(gains, state, ref, force_error, delta, dt, cross):
    """The rule's offset e_i as the classical filter's plus the coupling
    family's o_i (``jaxsync.control.coupling``, the reference placement:
    the command carries e_i + o_i once the reference has caught up)."""
    imp, dde = _impedance_filters(gains, state, ref, force_error, dt)
    u, u_dot = _coupling.inputs(gains, delta, imp.offset, imp.rate, force_error, ref.pad_rot)
    o, o_vel, family = _coupling.step(gains, state.coupling, u, u_dot, ref.pad_rot)
    return (imp.offset + o, imp.rate + o_vel, dde), state._replace(impedance=imp, coupling=family)


_CARTESIAN_STANDINS = {
    "ros2_admittance": _classical,
    "ros2_synchronous": _synchronous,
    "ros2_coupled": _coupled_family,
    "ros2_coupled_direct": _coupled_family,
}
