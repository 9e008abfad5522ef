"""Closed-loop rollouts: one jit-compiled ``lax.scan`` over MJX steps.

``make_rollout`` returns a pure function ``(gains, scenario) -> Trajectory``
that can be jitted, vmapped over gains and scenarios, and differentiated.
``rollout`` is the convenient, cached, jitted entry point; its
``backend="mujoco"`` runs the very same jitted control law against MuJoCo C
(one environment, no gradient), so the two engines can be compared.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import mujoco

from jaxsync._errors import ConfigError
from jaxsync.control import controller as _controller
from jaxsync.control import gains as _gains
from jaxsync.control import ros2_loop as _ros2_loop
from jaxsync.control.controller import ControllerOptions, ControllerSwitch
from jaxsync.control.gains import Gains
from jaxsync.control.names import POSITION_ONLY
from jaxsync.physics import step as _physics
from jaxsync.physics.model import DualArmModel
from jaxsync.physics.sensing import sense
from jaxsync.runtime import programs
from jaxsync.sim import actuation as _actuation
from jaxsync.sim import closed_loop as _closed_loop
from jaxsync.sim import scenario as _scenario
from jaxsync.sim import trajectory as _trajectory
from jaxsync.sim.closed_loop import REST_KEY, START_KEY
from jaxsync.sim.rollout_mujoco import rollout_mujoco
from jaxsync.sim.scenario import Scenario
from jaxsync.sim.trajectory import Trajectory


def make_rollout(
    model: DualArmModel,
    controller: str = "synchronous",
    duration: float = 4.0,
    control_substeps: int = 1,
    cross_term: str = "squeeze",
    remat: bool = False,
    truncate_every: int | None = None,
    start: str = START_KEY,
    passes: str = "mjx",
    actuation: str = "torque",
    distro: str = "jazzy",
):
    """Build ``fn(gains, scenario) -> Trajectory`` for one static configuration.

    Args:
      model: from :func:`jaxsync.load_model` (its solver setting is used).
      controller: one of ``jaxsync.control.names.ALL_CONTROLLERS``
        ("ros2_admittance" and "ros2_synchronous" with ``actuation="position"`` only).
      duration: seconds simulated.
      control_substeps: physics steps per control period (1: control at the
        simulation rate, 500 Hz for the paper model).
      cross_term: reading of eq. 16's cross term (see jaxsync.control.sync).
      remat: ``jax.checkpoint`` the scan body, keeping the solve's outputs
        (for long reverse-mode gradients: the backward pass does not solve
        again).
      truncate_every: if set, stop gradients through the simulator and
        controller state every this many control steps (truncated
        backpropagation in windows; the forward values are unchanged).
      start: keyframe the arms start from: "approach" (pads 30 mm off, the
        paper's task) or "grasp" (pads touching: short horizons in contact).
      passes: how the body tree's kinematics, inertias and Jacobians are
        computed (``jaxsync.physics.step.PASSES``): "mjx", MJX's own stages
        (faster vmapped over large batches: forward programs), or "tree",
        jaxsync's vectorised passes (the same values to rounding, a far
        smaller program to differentiate and compile: gradient programs pass
        ``remat=True, passes="tree"``).
      actuation: "torque" (joint torque motors) or "position" (joint
        position commands through the robot's servo, delayed by the
        scenario's ``delay``: ``jaxsync.sim.actuation``).
      distro: the ros2_controllers release "ros2_admittance" runs
        (``jaxsync.control.ros2_admittance.DISTROS``).

    Example:
      >>> fn = make_rollout(jaxsync.load_model(), "synchronous", duration=2.0)
      >>> batch = jax.jit(jax.vmap(fn, in_axes=(None, 0)))  # one gain set, many scenarios
      >>> traj = batch(jaxsync.default_gains(), scenarios)  # doctest: +SKIP
      >>> traj.pad_forces.shape  # doctest: +SKIP
      (B, 1000, 2, 3)
    """
    options = ControllerOptions(kind=controller, cross_term=cross_term, distro=distro)
    _ros2_loop.check_actuation(controller, _actuation.check(actuation))
    core = _controlled_rollout(model, duration, control_substeps, remat, truncate_every, start, passes, actuation)

    def fn(gains: Gains, s: Scenario) -> Trajectory:
        return core(gains, s, options)

    fn.n_steps = core.n_steps
    fn.dt = core.dt
    fn.options = options
    return fn


def scenario_model(model: DualArmModel, s: Scenario, pc=None):
    """The MJX model scenario ``s`` runs: its object and contacts, and on position-controlled arms
    (``pc``, ``jaxsync.sim.actuation.position_consts``) the servo's damping as MuJoCo's joint damping."""
    mx = _scenario.apply_to_model(model.mjx_model, s, model.index)
    if pc is not None:
        for name, where, value in _actuation.model_updates(pc, s.servo_scale):
            mx = mx.replace(**{name: getattr(mx, name).at[where].set(value)})
    return mx


def sense_period(mx, consts, index, s: Scenario, d, pad_start, k, passes):
    """The start of control period ``k``: MJX's position stages, the pads where the task starts (read at the
    first period: the program holds the position stages once, in the loop, not a second time for the initial
    state), the sensors with their noise. Returns (d, pad_start, the noisy data, the sensed state)."""
    d = _physics.before_control(mx, d, passes)
    pads = jnp.stack([d.site_xpos[a.pad_site] for a in index.arms])
    pad_start = jnp.where(k == 0, pads, pad_start)
    noisy = d.replace(sensordata=d.sensordata + _closed_loop.noise(s, consts, k))
    return d, pad_start, noisy, sense(mx, noisy, index, passes)


def servo_period(mx, pc, consts, s: Scenario, d, buffer, sent, dt, substeps, passes, unroll):
    """The rest of a position-stack period: ``sent`` joins the commands on their way (``buffer``), the one
    the delay lets act drives the joint servos on each physics substep. Returns (d, buffer, the last
    substep's servo torque)."""
    buffer = _actuation.push(buffer, sent)
    acting, acting_vel = _actuation.acting(buffer, _actuation.delay_steps(s), dt)
    limit = jnp.asarray(consts.torque_limit)
    for sub in range(substeps):
        if sub:
            d = _physics.before_control(mx, d, passes)
        tau, motor = _actuation.servo_torque(pc, d.qpos, d.qvel, d.qfrc_bias, acting, acting_vel, s.servo_scale, limit)
        d = _physics.after_control(mx, d, motor[consts.act_order], unroll)
    return d, buffer, tau


def _controlled_rollout(
    model, duration, control_substeps, remat, truncate_every, start, passes="mjx", actuation="torque"
):
    """``fn(gains, scenario, options) -> Trajectory``: ``options`` a static
    :class:`ControllerOptions` (closed over by :func:`make_rollout`) or a
    traced :class:`~jaxsync.control.controller.ControllerSwitch` (one program for
    every controller choice: :func:`rollout`'s)."""
    if passes not in _physics.PASSES:
        raise ConfigError(f"passes must be one of {list(_physics.PASSES)}, got {passes!r}")
    if start not in (START_KEY, REST_KEY):
        raise ConfigError(f"start must be {START_KEY!r} or {REST_KEY!r}, got {start!r}")
    if truncate_every is not None and truncate_every < 1:
        raise ConfigError(f"truncate_every must be a positive number of steps, got {truncate_every}")
    if control_substeps < 1 or int(control_substeps) != control_substeps:
        raise ConfigError(f"control_substeps must be a positive integer, got {control_substeps}")
    sim_dt = float(model.mj_model.opt.timestep)
    dt = sim_dt * control_substeps
    n_steps = int(round(duration / dt))
    if n_steps < 1:
        raise ConfigError(f"duration must be at least one control period ({dt} s), got {duration}")
    consts = _closed_loop.consts(model, start)
    position = _actuation.check(actuation) == "position"
    pc = _actuation.position_consts(model) if position else None
    q0 = _closed_loop.initial_command(model, consts)
    index = model.index
    unroll = model.solver_unroll
    d_template = _physics.put_data(model.mj_model, mujoco.MjData(model.mj_model))

    def fn(gains: Gains, s: Scenario, options) -> Trajectory:
        mx = scenario_model(model, s, pc)
        d0 = d_template.replace(qpos=_closed_loop.initial_qpos(model, consts, s))

        def body(carry, k):
            state, pad_start = carry
            if truncate_every is not None:
                cut = (k % truncate_every == 0) & (k > 0)
                state = jax.tree_util.tree_map(
                    lambda x: (
                        jnp.where(cut, jax.lax.stop_gradient(x), x) if jnp.issubdtype(x.dtype, jnp.inexact) else x
                    ),
                    state,
                )
            d, cstate, held = state
            t = k * dt
            d, pad_start, noisy, sensed = sense_period(mx, consts, index, s, d, pad_start, k, passes)
            arms = (sensed.right, sensed.left)
            if position:
                command, buffer = held
                command, sent, cstate, info, pl, _ = _closed_loop.control_position(
                    options, gains, s, consts, cstate, arms, pad_start, t, dt, command
                )
                d, buffer, tau = servo_period(mx, pc, consts, s, d, buffer, sent, dt, control_substeps, passes, unroll)
                held = (command, buffer)
            else:
                tau, cstate, info, pl = _closed_loop.control(options, gains, s, consts, cstate, arms, pad_start, t, dt)
                ctrl = tau[consts.act_order]
                d = _physics.after_control(mx, d, ctrl, unroll)
                for _ in range(control_substeps - 1):
                    d = _physics.after_control(mx, _physics.before_control(mx, d, passes), ctrl, unroll)
            forces = jnp.stack([_physics.contact_force_on(mx, d, a.contact_id, a.object_is_geom1) for a in index.arms])
            row = _trajectory.row(
                t,
                noisy.qpos,
                noisy.qvel,
                sensed.obj.pos,
                sensed.obj.linvel,
                pl,
                arms,
                forces,
                tau,
                info,
                cstate,
                limit=consts.torque_limit,
            )
            return ((d, cstate, held), pad_start), row

        if remat:  # the solve's outputs are kept: the backward pass does not solve again
            body = jax.checkpoint(body, policy=_physics.REMAT_POLICY)
        held = (jnp.asarray(q0), _actuation.initial_buffer(q0)) if position else ()
        init = ((d0, _controller.init(jnp.asarray(q0)), held), jnp.zeros((len(index.arms), 3), d0.qpos.dtype))
        _, traj = jax.lax.scan(body, init, jnp.arange(n_steps))
        return traj

    fn.n_steps = n_steps
    fn.dt = dt
    return fn


@programs.memoize(maxsize=8)
def _jitted_static(model, duration, control_substeps, actuation, controller, distro):
    """``rollout()``'s program for a controller that no switch holds (ros2_admittance)."""
    fn = make_rollout(model, controller, duration, control_substeps, actuation=actuation, distro=distro)
    return jax.jit(fn)


@programs.memoize(maxsize=32)
def _jitted(model, duration, control_substeps, actuation="torque"):
    """``rollout()``'s program: one for every controller and cross term."""
    return jax.jit(_controlled_rollout(model, duration, control_substeps, False, None, START_KEY, actuation=actuation))


def rollout(
    model: DualArmModel,
    gains: Gains,
    scenario: Scenario,
    *,
    controller: str = "synchronous",
    duration: float = 4.0,
    control_substeps: int = 1,
    cross_term: str = "squeeze",
    backend: str = "mjx",
    actuation: str = "torque",
    distro: str = "jazzy",
) -> Trajectory:
    """Run one closed-loop rollout (or a batch: vmap ``make_rollout`` instead).

    ``backend="mjx"`` compiles once per model, duration and substep count:
    the controller and the cross term are arguments of one program
    (:class:`~jaxsync.control.controller.ControllerSwitch`), so the classical and the
    synchronous rollouts of a comparison share it; ``backend="mujoco"``
    steps MuJoCo C with the same jitted control law. "ros2_admittance"
    (position-controlled arms only; ``distro`` its ros2_controllers release)
    compiles a program of its own.

    Example:
      >>> model, s = jaxsync.load_model(), jaxsync.short_task()
      >>> traj = rollout(model, jaxsync.default_gains(), s, controller="classical", duration=2.0)
      >>> traj.torque.shape
      (1000, 14)
    """
    _ros2_loop.check_actuation(controller, _actuation.check(actuation))
    if backend == "mjx" and controller in POSITION_ONLY:
        fn = _jitted_static(model, float(duration), int(control_substeps), actuation, controller, distro)
        args = (_gains.strongly_typed(gains), _scenario.strongly_typed(scenario))
        return fn(*jax.device_put(args, _physics.local_device()))
    if backend == "mjx":
        switch = ControllerSwitch.of(ControllerOptions(kind=controller, cross_term=cross_term))
        stack = () if _actuation.check(actuation) == "torque" else (actuation,)  # the torque stack's key as ever
        fn = _jitted(model, float(duration), int(control_substeps), *stack)
        # one program whatever the arguments' origin: strong dtypes (a Python
        # number is weak-typed) and committed to this process's device (an
        # array that a computation on the model's committed arrays returned is
        # committed, one built from Python or NumPy is not, and jit compiles a
        # program for each)
        args = (_gains.strongly_typed(gains), _scenario.strongly_typed(scenario), switch)
        args = jax.device_put(args, _physics.local_device())
        return fn(*args)
    if backend == "mujoco":
        return rollout_mujoco(
            model,
            gains,
            scenario,
            controller=controller,
            duration=duration,
            control_substeps=control_substeps,
            cross_term=cross_term,
            actuation=actuation,
            distro=distro,
        )
    raise ConfigError(f"backend must be 'mjx' or 'mujoco', got {backend!r}")


def steps_for(duration: float, model: DualArmModel, control_substeps: int = 1) -> int:
    return int(round(duration / (model.mj_model.opt.timestep * control_substeps)))


def cpu_vmap_limit() -> int | None:
    """The largest vmap batch that is safe on this backend, None if unlimited.

    jaxlib's CPU LAPACK kernels (the batched Cholesky of MJX's Newton solver)
    split large batches over XLA's intra-op thread pool and block waiting for
    the pieces; when as many of them run at once as the pool has threads they
    wait for each other for ever (gdb: every pool thread in
    ``lapack_dpotrf_ffi`` -> ``ParallelBatchMap`` -> ``BlockingCounter::Wait``).
    Measured on 2 cores with jaxlib 0.10.2: batch 64 runs, 128 and 256 hang.
    Not checked on other jaxlib versions, so the cap applies to every CPU
    backend; ``JAXSYNC_CPU_VMAP_LIMIT`` overrides it (0: no cap).
    """
    if jax.default_backend() != "cpu":
        return None
    env = os.environ.get("JAXSYNC_CPU_VMAP_LIMIT")
    if env is not None:
        try:
            n = int(env)
        except ValueError:
            raise ConfigError(f"JAXSYNC_CPU_VMAP_LIMIT must be a whole number (0: no cap), got {env!r}") from None
        return n if n > 0 else None
    return 64
