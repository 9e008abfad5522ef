"""How the arms are driven: joint torques, or joint position commands through a servo.

``"torque"``: each joint a torque motor; the controller's joint-space law
(``jaxsync.control.joint_space.torques``) acts within the same physics step.

``"position"``: what a position-controlled arm runs (ros2_control's position
command interfaces). Each control period the controller turns its Cartesian
targets into joint position commands (``jaxsync.control.joint_space.
command_rate``, integrated); a command waits ``Scenario.delay`` control
periods in a buffer; the robot's own servo (``jaxsync.physics.servo``)
tracks the command it holds on every physics substep. The servo's damping
is MuJoCo's joint damping (integrated implicitly), set per scenario with
``Scenario.servo_scale``.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control.names import DEFAULT_DISTRO, DISTROS
from jaxsync.physics.servo import servo_of
from jaxsync.sim.scenario import MAX_DELAY

ACTUATIONS = ("torque", "position")


def check_distro(distro: str) -> str:
    if distro not in DISTROS:
        raise ConfigError(f"distro must be one of {list(DISTROS)}, got {distro!r}", inputs=("distro",))
    return distro


def check(actuation: str) -> str:
    if actuation not in ACTUATIONS:
        raise ConfigError(f"actuation must be one of {list(ACTUATIONS)}, got {actuation!r}", inputs=("actuation",))
    return actuation


@dataclasses.dataclass(frozen=True)
class Stack:
    """The stack a job simulates: how the arms are driven, how often the
    controller runs, and the command delay (control periods: one value, or a
    range ``(lo, hi)`` that randomised scenarios draw from).

    Example:
      >>> Stack("position", delay=(2, 2)).scenario_delay()
      2
    """

    actuation: str = "torque"
    control_rate: float | None = None  # Hz; None: every physics step
    delay: tuple[int, int] = (0, 0)
    distro: str = DEFAULT_DISTRO  # the ros2_controllers release controller "ros2_admittance" runs

    def __post_init__(self):
        check(self.actuation)
        check_distro(self.distro)
        lo, hi = check_delay(self.delay)
        if hi > 0 and self.actuation != "position":
            raise ConfigError(
                f"delay applies to position-controlled arms (actuation='position'), got delay {hi} with "
                f"actuation={self.actuation!r}",
                inputs=("delay", "actuation"),
            )

    @classmethod
    def of(cls, actuation: str = "torque", control_rate: float | None = None, delay=0, distro=DEFAULT_DISTRO) -> Stack:
        """``delay`` one number of control periods N, or a range (lo, hi)."""
        return cls(actuation, control_rate, check_delay(delay), distro)

    def substeps(self, model) -> int:
        return substeps_for_rate(model, self.control_rate)

    def rollout_options(self, model) -> dict:
        """``actuation``, ``control_substeps`` and ``distro`` for ``rollout``/``make_rollout``."""
        return {"actuation": self.actuation, "control_substeps": self.substeps(model), "distro": self.distro}

    def scenario_delay(self) -> int:
        """The one delay of a job that runs one scenario; refuses a range."""
        lo, hi = self.delay
        if lo != hi:
            raise ConfigError(
                f"delay: one scenario runs one delay, got the range {lo}:{hi} (a range is drawn per scenario "
                "where scenarios are randomised)",
                inputs=("delay",),
            )
        return lo

    def to_dict(self, model=None) -> dict:
        out = {"actuation": self.actuation, "control_rate_Hz": self.control_rate, "delay": list(self.delay)}
        if self.actuation == "position":
            out["ros_distro"] = self.distro
        if model is not None:
            out["control_period_s"] = float(model.mj_model.opt.timestep) * self.substeps(model)
            if self.actuation == "position":
                out["servo"] = servo_of(model).to_dict()
        return out


class PositionConsts(NamedTuple):
    """The position stack's constants, in the torque vector's order (right arm's n, then left's)."""

    stiffness: np.ndarray  # (2 n,) N m/rad
    damping: np.ndarray  # (2 n,) N m s/rad
    dof_adr: np.ndarray  # (2 n,)
    qpos_adr: np.ndarray  # (2 n,)
    joint_damping: np.ndarray  # (2 n,) the model's own joint damping, N m s/rad
    actuator_ids: np.ndarray  # (2 n,) the joints' torque motors
    joint_ids: np.ndarray  # (2 n,) the arm joints
    weight: np.ndarray  # (2 n,) 1 where the servo compensates the bias forces, else 0
    feedforward: np.ndarray  # (2 n,) 1 where its damping acts on the velocity error, 0: on the velocity
    command_lo: np.ndarray  # (2 n,) the commands' range, rad (-inf: none)
    command_hi: np.ndarray  # (2 n,)


def position_consts(model, servo=None) -> PositionConsts:
    """The constants of ``servo`` (default: the model's, ``jaxsync.physics.servo.servo_of``)."""
    servo = servo_of(model) if servo is None else servo
    dofs = np.array([i for a in model.index.arms for i in a.dof_adr])
    rng = servo.command_range if servo.command_range is not None else np.full((*servo.stiffness.shape, 2), np.inf)
    rng = np.where(np.isfinite(rng), rng, np.array([-np.inf, np.inf]))
    ones = np.ones(servo.stiffness.size)
    return PositionConsts(
        stiffness=servo.stiffness.reshape(-1),
        damping=servo.damping.reshape(-1),
        dof_adr=dofs,
        qpos_adr=np.array([i for a in model.index.arms for i in a.qpos_adr]),
        joint_damping=np.asarray(model.mj_model.dof_damping)[dofs].copy(),
        actuator_ids=np.array([i for a in model.index.arms for i in a.actuator_ids]),
        joint_ids=np.asarray(model.mj_model.dof_jntid)[dofs].copy(),
        weight=ones * float(servo.weight_compensation),
        feedforward=ones * float(servo.velocity_feedforward),
        command_lo=rng[..., 0].reshape(-1),
        command_hi=rng[..., 1].reshape(-1),
    )


UNCLAMPED = 1e9  # N m: the motors' control range while the servo clips its own torque


def model_updates(pc: PositionConsts, servo_scale) -> tuple:
    """(field, index, value) entries (``jaxsync.sim.scenario._model_updates``'s
    form, for either engine): the joint damping the servo adds, and the
    motors' control range and the joints' actuator force range
    (``actuatorfrcrange``) opened. The servo clips its own torque to the
    joint's limit (:func:`servo_torque`); the motor then adds the part that
    cancels the implicit damping, which a limit on the motor or on the joint's
    actuator force would clip too: it would brake the joint above
    ``limit / damping`` rad/s, which no servo does."""
    return (
        ("dof_damping", (pc.dof_adr,), pc.joint_damping + servo_scale * pc.damping),
        ("actuator_ctrlrange", (pc.actuator_ids, 0), -UNCLAMPED),
        ("actuator_ctrlrange", (pc.actuator_ids, 1), UNCLAMPED),
        ("jnt_actfrcrange", (pc.joint_ids, 0), -UNCLAMPED),
        ("jnt_actfrcrange", (pc.joint_ids, 1), UNCLAMPED),
    )


def servo_torque(pc: PositionConsts, qpos, qvel, qfrc_bias, command, command_vel, servo_scale, limit, xp=jnp):
    """The servo's torque, clipped to the joint's limit, and the motor torque
    that applies it beside the implicit joint damping, both (2 n,):

        tau   = clip(s (k (clip(q_cmd, lo, hi) - q) + b (f dq_cmd - dq)) + w c, +-limit)
        motor = tau + s b dq

    ``s`` the scenario's servo scale, (w, f) the servo's structure
    (``jaxsync.physics.servo``: w = 1 compensates the bias forces c, f = 1
    feeds the command's velocity forward; both 0 is MuJoCo's ``<position>``
    actuator as written). MuJoCo adds -s b dq' (the damping at the step's
    end velocity, implicit), so the joint gets tau to first order in dt and
    the damping stays stable at any gain. With f = 1 the command carries its
    velocity, as ros2_control's position-based controllers write one beside
    the position (without it a servo lags b / k dq behind a moving command
    and holds b dq against it). The limit clips the torque the servo would
    apply, nothing else (``model_updates``). MuJoCo C, MJX, the calibration's
    replay and the tests' references all compute this law."""
    q, dq = qpos[pc.qpos_adr], qvel[pc.dof_adr]
    command = xp.clip(command, pc.command_lo, pc.command_hi)
    tau = servo_scale * (pc.stiffness * (command - q) + pc.damping * (pc.feedforward * command_vel - dq))
    tau = xp.clip(tau + pc.weight * qfrc_bias[pc.dof_adr], -limit, limit)
    return tau, tau + servo_scale * pc.damping * dq


def delay_steps(s) -> jax.Array:
    """The scenario's delay as an index into the command buffer."""
    return jnp.clip(jnp.round(s.delay), 0, MAX_DELAY).astype(jnp.int32)


def push(buffer: jax.Array, command: jax.Array) -> jax.Array:
    """(MAX_DELAY + 2, 2 n): the newest command first, the oldest dropped."""
    return jnp.concatenate([command[None], buffer[:-1]])


def acting(buffer: jax.Array, delay, dt: float):
    """The command the servo holds after ``delay`` periods, and its velocity
    (the difference with the one before it over the control period ``dt``)."""
    command = buffer[delay]
    return command, (command - buffer[delay + 1]) / dt


def initial_buffer(q0) -> jax.Array:
    return jnp.broadcast_to(jnp.asarray(q0), (MAX_DELAY + 2, *jnp.shape(q0)))


def substeps_for_rate(model, control_rate: float | None) -> int:
    """Physics steps per control period for ``control_rate`` Hz (None: every step).

    Raises ConfigError unless the rate divides the model's physics rate."""
    if control_rate is None:
        return 1
    step = float(model.mj_model.opt.timestep)
    physics = 1.0 / step
    if not (isinstance(control_rate, (int, float)) and control_rate > 0):
        raise ConfigError(
            f"control_rate must be a positive number of Hz, got {control_rate!r}", inputs=("control_rate",)
        )
    n = physics / float(control_rate)
    if n < 1 - 1e-9 or abs(n - round(n)) > 1e-6:
        rates = ", ".join(f"{physics / k:g}" for k in range(1, 5))
        raise ConfigError(
            f"control_rate {control_rate:g} Hz must divide the physics rate {physics:g} Hz "
            f"(timestep {step:g} s): e.g. {rates}",
            inputs=("control_rate",),
        )
    return int(round(n))


def check_delay(delay) -> tuple[int, int]:
    """``delay`` (whole control periods: N, or a range (lo, hi) that scenarios draw from) ->
    (lo, hi), 0 <= lo <= hi <= MAX_DELAY; a ConfigError names anything else."""
    pair = tuple(delay) if isinstance(delay, tuple | list) else (delay, delay)
    ok = len(pair) == 2 and all(isinstance(x, int | np.integer) and not isinstance(x, bool) for x in pair)
    if not ok or not 0 <= pair[0] <= pair[1] <= MAX_DELAY:
        raise ConfigError(
            f"delay must be whole control periods N or a range (lo, hi) within 0..{MAX_DELAY}, got {delay!r}",
            inputs=("delay",),
        )
    return int(pair[0]), int(pair[1])


def check_ft_filter(value, one: bool = False) -> tuple[float, float]:
    """``value`` (the F/T filter coefficient A, or a range (lo, hi) drawn per scenario) -> (lo, hi),
    0.001 <= lo <= hi <= 1; ``one``: a single coefficient only (what one file or one scenario holds)."""
    pair = tuple(value) if isinstance(value, tuple | list) else (value, value)
    numbers = len(pair) == 2 and all(isinstance(x, int | float | np.number) and not isinstance(x, bool) for x in pair)
    lo, hi = (float(pair[0]), float(pair[1])) if numbers else (None, None)
    if lo is None or not 1e-3 <= lo <= hi <= 1.0:
        raise ConfigError(
            f"ft_filter must be a filter coefficient A or a range (lo, hi) within 0.001..1 (1: unfiltered), "
            f"got {value!r}",
            inputs=("ft_filter",),
        )
    if one and lo != hi:
        raise ConfigError(f"ft_filter: one coefficient here, got the range {value!r}", inputs=("ft_filter",))
    return lo, hi


TORQUE = Stack()
"""The ideal torque-controlled stack: every job's default."""
