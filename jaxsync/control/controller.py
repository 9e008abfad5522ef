"""The two controllers of the paper, as pure functions over explicit state.

``classical``: impedance only (eqs. 8-11, 15): x_ic = x_id + e_i.
``synchronous``: impedance plus absolute/relative errors (eqs. 12-17):
x_ik = x_id + delta_ik + k_il (e_i + T_ij e_j).
Both end in the same joint-space law (eqs. 18, 19).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxsync._errors import ConfigError
from jaxsync.control import impedance as _impedance
from jaxsync.control import joint_space as _joint_space
from jaxsync.control import so3 as _so3
from jaxsync.control import sync as _sync
from jaxsync.control.gains import Gains
from jaxsync.physics.sensing import ArmState

CONTROLLERS = ("classical", "synchronous")


@dataclasses.dataclass(frozen=True)
class ControllerOptions:
    """Static choices (changing them recompiles; they are never traced).

    Example:
      >>> ControllerOptions(kind="classical")
      ControllerOptions(kind='classical', cross_term='squeeze')
    """

    kind: str = "synchronous"  # "classical" or "synchronous"
    cross_term: str = "squeeze"  # eq. 16's T_ij e_j, see jaxsync.control.sync.CROSS_TERMS

    def __post_init__(self):

        if self.kind not in CONTROLLERS:
            raise ConfigError(f"controller must be one of {CONTROLLERS}, got {self.kind!r}")
        if self.cross_term not in _sync.CROSS_TERMS:
            raise ConfigError(f"cross_term must be one of {_sync.CROSS_TERMS}, got {self.cross_term!r}")


class ControllerSwitch(NamedTuple):
    """The controller choice as arrays, traced: one compiled program serves
    both controllers and every cross term (``jaxsync.rollout``'s program; a
    static :class:`ControllerOptions` compiles one per choice). Each choice
    computes exactly what its static counterpart computes.

    Example:
      >>> ControllerSwitch.of(ControllerOptions(kind="classical")).synchronous
      Array(False, dtype=bool)
    """

    synchronous: jax.Array  # bool: the synchronous controller, else the classical one
    cross_term: jax.Array  # int: index into jaxsync.control.sync.CROSS_TERMS

    @classmethod
    def of(cls, options: ControllerOptions) -> ControllerSwitch:
        return cls(
            synchronous=jnp.asarray(options.kind == "synchronous"),
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
    impedance: _impedance.ImpedanceState


class ControlInfo(NamedTuple):
    """Internals recorded for metrics and plots."""

    offset: jax.Array  # (2, 6) x_ik - x_id (the classical: e_i)
    delta: jax.Array  # (2, 6) absolute errors delta_i = x_id - x_i (eq. 12)
    force_error: jax.Array  # (2, 6) f_i - f_id


def init() -> ControllerState:
    """The controller's state at rest: both admittance filters at zero offset and rate.

    Example:
      >>> state = init()
      >>> state.impedance.offset.shape
      (2, 6)
    """
    return ControllerState(impedance=_impedance.init())


def step(
    options: ControllerOptions | ControllerSwitch,
    gains: Gains,
    state: ControllerState,
    arms: tuple[ArmState, ArmState],
    ref: Reference,
    dt: float,
) -> tuple[jax.Array, ControllerState, ControlInfo]:
    """One control period of either controller.

    Args:
      options: static controller choice (or a traced :class:`ControllerSwitch`).
      gains: the gain pytree.
      state: the admittance filters.
      arms: sensed (right, left) arm states; ``wrench`` is the wrist reading.
      ref: planned poses and desired wrenches.
      dt: control period, s.
    Returns:
      (14,) joint torques (right arm's 7, then left's), the new state, info.

    Example (one period, from a sensed state ``sensed = jaxsync.sense(...)``):
      >>> state = init()
      >>> tau, state, info = step(ControllerOptions(), jaxsync.default_gains(), state,
      ...                         (sensed.right, sensed.left), ref, dt=0.002)  # doctest: +SKIP
      >>> tau.shape  # doctest: +SKIP
      (14,)
    """
    wrench = jnp.stack([a.wrench for a in arms])
    force_error = wrench - ref.wrench
    imp, dde = _impedance.step(
        state.impedance, gains.imp_mass, gains.imp_damping, gains.imp_stiffness, ref.pad_rot, force_error, dt
    )
    e, de = imp.offset, imp.rate
    delta = jnp.stack(
        [_sync.absolute_error(ref.pad_pos[i], ref.pad_rot[i], arms[i].pad_pos, arms[i].pad_rot) for i in range(2)]
    )
    if isinstance(options, ControllerSwitch):  # both, the choice traced
        terms = _sync.CROSS_TERMS
        cross = lambda v: jnp.stack([_sync.cross_mapped(v, ref.pad_pos, t) for t in terms])[options.cross_term]  # noqa: E731
        synchronous = _synchronous_offsets(gains, delta, e, de, dde, cross)
        pick = lambda a, b: jnp.where(options.synchronous, a, b)  # noqa: E731
        off, off_vel, off_acc = (pick(a, b) for a, b in zip(synchronous, (e, de, dde), strict=True))
    elif options.kind == "classical":
        off, off_vel, off_acc = e, de, dde  # x_ic = x_id + e_i (eq. 11)
    else:
        cross = lambda v: _sync.cross_mapped(v, ref.pad_pos, options.cross_term)  # noqa: E731
        off, off_vel, off_acc = _synchronous_offsets(gains, delta, e, de, dde, cross)

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
    return jnp.concatenate(taus), ControllerState(impedance=imp), info


def _synchronous_offsets(gains: Gains, delta, e, de, dde, cross):
    """x_ik - x_id and its rate and acceleration (eqs. 13-17); ``cross`` maps
    (2, 6) offsets through eq. 16's cross term."""
    k_il = jnp.stack([gains.k_rl, gains.k_ll])
    delta_k = _sync.relative_compensation(delta, gains.k_rk, gains.k_lk)
    off = _sync.synchronous_offset(delta_k, k_il, cross(e))
    return off, k_il[:, None] * cross(de), k_il[:, None] * cross(dde)
