"""The task as data: a scenario pytree (batchable with vmap) and its plan.

Default task (paper section 5): the pads start 30 mm from the object (the
``approach`` keyframe), close until they press into it, squeeze up to the grip
force f_d, lift and carry the object along a smooth path, and hold it.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from jaxsync._errors import ConfigError

GRAVITY = np.array([0.0, 0.0, -9.81])
STAND_TOP_Z = 0.8  # the stand's plane, mjcf/dual_arm.xml
NOMINAL_XY = np.array([0.65, 0.0])
MAX_DELAY = 8  # control periods a position command can wait (the command buffer's length - 1)


class Scenario(NamedTuple):
    """One task. Every field is an array, so scenarios batch with vmap.

    object_mass: kg (true, simulated). mass_estimate: kg, what the controller
      assumes when it shares the object's weight between the arms.
    object_radius: m. object_offset: (3,) m, where the object really starts
      relative to the nominal grasp centre the plan assumes.
    grip_force: f_d, N. intrusion: m, how far the planned pad poses press into
      the (nominal) surface.
    lift: (3,) m, the planned displacement of the object from its start.
    t_close, t_squeeze, t_carry: phase durations, s (approach and close; ramp
      of the grip force; lift and carry). The hold lasts the rest.
    settle_time: s after the start of the hold before metrics are taken.
    contact_timeconst: s, MuJoCo solref time constant of the pad contacts.
    friction: pad-object sliding friction coefficient.
    force_noise, torque_noise: N, N m; std of white noise on each wrist-sensor axis.
    noise_key: a jax PRNG key (raw uint32 (2,)) for the sensor noise.
    delay: whole control periods between a joint position command and the
      servo acting on it (position-controlled arms only; 0 to
      ``MAX_DELAY``, a float holding a whole number).
    servo_scale: factor on the joint servos' stiffness and damping
      (position-controlled arms only; 1: as the robot states them).
    ft_filter: the F/T filter of ros2_controllers' admittance rule,
      ``ft_sensor.filter_coefficient`` (the weight of each new sample; 1:
      unfiltered), on position-controlled arms: the rule's controllers
      (ros2_admittance, ros2_synchronous) and jaxsync's own laws read the
      force error through it.
    """

    object_mass: jax.Array
    mass_estimate: jax.Array
    object_radius: jax.Array
    object_offset: jax.Array
    grip_force: jax.Array
    intrusion: jax.Array
    lift: jax.Array
    t_close: jax.Array
    t_squeeze: jax.Array
    t_carry: jax.Array
    settle_time: jax.Array
    contact_timeconst: jax.Array
    friction: jax.Array
    force_noise: jax.Array
    torque_noise: jax.Array
    noise_key: jax.Array
    delay: jax.Array
    servo_scale: jax.Array
    ft_filter: jax.Array


FORCE_NOISE_N = 0.1  # the default task's wrist force noise (std per axis); a robot file's sensor: replaces it


def model_object(model) -> dict:
    """The scenario fields a model brings: a robot file's object (its mass, which
    the controller also assumes unless a ``mass_estimate`` is given, and its
    radius); none for the paper model, whose object is the default scenario's."""
    robot = getattr(model, "robot", None)
    if robot is None:
        return {}
    sensor = getattr(robot, "sensor", None) or {}
    return {"object_mass": float(robot.object_mass), "object_radius": float(robot.object_radius), **sensor}


def default_scenario(model=None, /, **overrides) -> Scenario:
    """The paper comparison's task (docs/scenario.md explains each choice), with
    ``model``'s object (:func:`model_object`) and then ``overrides``. Every
    command and library job takes a model's task from here.

    Example:
      >>> float(default_scenario(grip_force=12.0).grip_force)
      12.0
    """
    overrides = {**model_object(model), **overrides}
    values = dict(
        object_mass=0.5,
        mass_estimate=None,
        object_radius=0.1,
        object_offset=[0.0, 0.003, 0.0],  # 3 mm towards the left arm: the arms do not act alike
        grip_force=10.0,
        intrusion=0.001,
        lift=[0.05, 0.0, 0.10],
        t_close=0.6,
        t_squeeze=0.4,
        t_carry=1.2,
        settle_time=0.3,
        contact_timeconst=0.02,
        friction=1.0,
        force_noise=FORCE_NOISE_N,
        torque_noise=0.005,
        noise_key=np.asarray(jax.random.key_data(jax.random.key(0))),
        delay=0.0,
        servo_scale=1.0,
        ft_filter=1.0,
    )
    unknown = set(overrides) - set(values)
    if unknown:
        raise ConfigError(f"unknown scenario field(s) {sorted(unknown)}; known: {list(Scenario._fields)}")
    values.update(overrides)
    if values["mass_estimate"] is None:
        values["mass_estimate"] = values["object_mass"]
    # numpy first: strongly typed arrays, so user-built scenarios share the compiled rollout
    arrays = {
        k: jnp.asarray(np.asarray(v, dtype=np.uint32 if k == "noise_key" else np.float64)) for k, v in values.items()
    }
    return validate(Scenario(**arrays))


def short_task(model=None, /, **overrides) -> Scenario:
    """The default task compressed into 2 s (close 0.3 s, squeeze 0.4 s, lift
    0.5 s, hold from 1.2 s, metrics from 1.5 s): the short horizon that the
    tuner's ``--task short``, the benchmark's gradient and the tests roll out
    (from :func:`min_duration`, 1.7 s, on). The squeeze is long enough for the
    grip force to settle: with a 0.2 s squeeze the unsettled grip error
    dominated the tuning cost and its gradient pushed k_rl, k_ll up, the
    opposite of what lowers the resultant on the full task (measured).

    Example:
      >>> s = short_task(object_mass=0.6)
      >>> round(min_duration(s), 6)
      1.7
    """
    values = dict(t_close=0.3, t_squeeze=0.4, t_carry=0.5, settle_time=0.3, lift=[0.02, 0.0, 0.05])
    values.update(overrides)
    return default_scenario(model, **values)


def to_dict(s: Scenario) -> dict:
    """A scenario as plain lists (what a result file records of the scenario base it ran)."""
    return {k: np.asarray(v).tolist() for k, v in s._asdict().items()}


def strongly_typed(s: Scenario) -> Scenario:
    """``s`` with every weakly typed field (``s._replace(ft_filter=jnp.asarray(0.2))``,
    a Python number) made the strongly typed array :func:`default_task` builds:
    float64 fields, the uint32 noise key. A jitted rollout compiles once per
    argument type; :func:`jaxsync.rollout` calls this first."""

    def strong(name, x):
        x = jnp.asarray(x)
        want = jnp.uint32 if name == "noise_key" else jnp.result_type(float)
        return x if (x.dtype == want and not x.weak_type) else jnp.asarray(x, dtype=want)

    return Scenario(*(strong(k, v) for k, v in zip(Scenario._fields, s, strict=True)))


def validate(s: Scenario) -> Scenario:
    """Eager range checks with messages that name the field."""
    checks = {
        "object_mass": (0.01, 20.0),
        "mass_estimate": (0.0, 20.0),
        "object_radius": (0.03, 0.2),
        "grip_force": (0.5, 100.0),
        "intrusion": (0.0, 0.02),
        "t_close": (0.01, 10.0),
        "t_squeeze": (0.01, 10.0),
        "t_carry": (0.01, 20.0),
        "settle_time": (0.0, 20.0),
        "contact_timeconst": (0.004, 0.2),
        "friction": (0.05, 3.0),
        "force_noise": (0.0, 10.0),
        "torque_noise": (0.0, 1.0),
        "delay": (0.0, MAX_DELAY),
        "servo_scale": (0.1, 10.0),
        "ft_filter": (1e-3, 1.0),
    }
    for name, (lo, hi) in checks.items():
        v = np.asarray(getattr(s, name))
        if not np.all((v >= lo) & (v <= hi)):
            raise ConfigError(f"scenario '{name}' must lie in [{lo}, {hi}], got {v.tolist()}")
    delay = np.asarray(s.delay)
    if not np.all(delay == np.round(delay)):
        raise ConfigError(f"scenario 'delay' must be whole control periods, got {delay.tolist()}")
    off = np.asarray(s.object_offset)
    if off.shape[-1:] != (3,) or not np.all(np.abs(off) <= 0.03):
        raise ConfigError(f"scenario 'object_offset' must be (3,) metres within +-0.03, got {off.tolist()}")
    return s


def phase_times(s: Scenario):
    """Start of squeeze, carry and hold (s)."""
    t_squeeze0 = s.t_close
    t_carry0 = t_squeeze0 + s.t_squeeze
    t_hold0 = t_carry0 + s.t_carry
    return t_squeeze0, t_carry0, t_hold0


def min_duration(s: Scenario) -> float:
    """The shortest rollout with a settled window: hold start + settle + 0.2 s."""
    _, _, t_hold = phase_times(s)
    return float(t_hold + s.settle_time) + 0.2


def nominal_centre(s: Scenario) -> jax.Array:
    """Where the plan assumes the object's centre is at the start."""
    return jnp.concatenate([jnp.asarray(NOMINAL_XY), jnp.atleast_1d(STAND_TOP_Z + s.object_radius)])


def _min_jerk(tau: jax.Array):
    """Position, velocity, acceleration of the 0 -> 1 minimum-jerk blend at tau in [0, 1] (per unit time)."""
    tau = jnp.clip(tau, 0.0, 1.0)
    p = tau**3 * (10 - 15 * tau + 6 * tau**2)
    v = 30 * tau**2 * (1 - tau) ** 2
    a = 60 * tau * (1 - 3 * tau + 2 * tau**2)
    return p, v, a


class Plan(NamedTuple):
    """Planned object and pad motion at one instant (all world frame)."""

    obj_pos: jax.Array  # (3,) z_d
    obj_vel: jax.Array  # (3,)
    obj_acc: jax.Array  # (3,)
    pad_pos: jax.Array  # (2, 3) x_id position part
    pad_vel: jax.Array  # (2, 3)
    pad_acc: jax.Array  # (2, 3)
    grip_force: jax.Array  # () current f_d (ramped)
    weight_share: jax.Array  # () 0 before the lift, 1 once the arms carry the object
    phase: jax.Array  # () 0 close, 1 squeeze, 2 carry, 3 hold


def plan(s: Scenario, t: jax.Array, pad_start: jax.Array, pad_normal: jax.Array) -> Plan:
    """The planned object path z_d(t) and pad positions x_id(t) (paper section 2.2).

    Args:
      s: the scenario.
      t: time, s.
      pad_start: (2, 3) pad positions at t = 0.
      pad_normal: (2, 3) unit pad normals (pointing into the object) of the grasp.
    """
    t_sq, t_ca, t_ho = phase_times(s)
    centre0 = nominal_centre(s)
    # lift and carry: a minimum-jerk blend of the lift vector
    p, v, a = _min_jerk((t - t_ca) / s.t_carry)
    obj_pos = centre0 + p * s.lift
    obj_vel = v / s.t_carry * s.lift
    obj_acc = a / s.t_carry**2 * s.lift
    # close: from the start pose to the surface pressed in by the intrusion
    contact = centre0[None, :] - pad_normal * (s.object_radius - s.intrusion)
    pc, vc, ac = _min_jerk(t / s.t_close)
    pad_pos = pad_start + pc * (contact - pad_start) + (obj_pos - centre0)[None, :]
    pad_vel = vc / s.t_close * (contact - pad_start) + obj_vel[None, :]
    pad_acc = ac / s.t_close**2 * (contact - pad_start) + obj_acc[None, :]
    grip, _, _ = _min_jerk((t - t_sq) / s.t_squeeze)
    share, _, _ = _min_jerk((t - t_ca) / jnp.minimum(0.2, s.t_carry))
    phase = (t >= t_sq).astype(jnp.int32) + (t >= t_ca) + (t >= t_ho)
    return Plan(obj_pos, obj_vel, obj_acc, pad_pos, pad_vel, pad_acc, grip * s.grip_force, share, phase)


def desired_wrench(s: Scenario, pl: Plan, pad_normal: jax.Array) -> jax.Array:
    """f_id (2, 6): the wrench the object should exert on each arm.

    The grip force f_d pushes each pad back along its normal, and each arm
    carries half of what the planned motion needs, m_est (z''_d - g), once the
    arms carry the object (the object on arm i: minus that half).
    """
    carry = -0.5 * pl.weight_share * s.mass_estimate * (pl.obj_acc - jnp.asarray(GRAVITY))
    force = -pl.grip_force * pad_normal + carry[None, :]
    return jnp.concatenate([force, jnp.zeros((2, 3))], axis=1)


def _model_updates(s: Scenario, index) -> tuple:
    """The model entries a scenario sets, as (field, index, value): one
    definition for both engines (:func:`apply_to_model`, :func:`apply_to_mj_model`)."""
    b, g = index.object_body, index.object_geom
    inertia = 2.0 / 3.0 * s.object_mass * s.object_radius**2  # thin spherical shell
    pair_ids = np.array(index.pad_pair_ids)
    return (
        ("body_mass", (b,), s.object_mass),
        ("body_inertia", (b,), inertia),
        ("geom_size", (g, 0), s.object_radius),
        ("pair_solref", (pair_ids, 0), s.contact_timeconst),
        ("pair_friction", (pair_ids, 0), s.friction),
        ("pair_friction", (pair_ids, 1), s.friction),
    )


def apply_to_model(mx: mjx.Model, s: Scenario, index) -> mjx.Model:
    """The scenario's physical parameters written into the MJX model (traceable)."""
    fields = {}
    for name, where, value in _model_updates(s, index):
        fields[name] = fields.get(name, getattr(mx, name)).at[where].set(value)
    return mx.replace(**fields)


def apply_to_mj_model(m, s: Scenario, index) -> None:
    """The same parameters written, in place, into a ``mujoco.MjModel`` (MuJoCo C)."""
    for name, where, value in _model_updates(jax.tree_util.tree_map(np.asarray, s), index):
        getattr(m, name)[where] = value
