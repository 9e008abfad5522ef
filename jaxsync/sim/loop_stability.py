"""The stability margin of the coupled loop on position-controlled arms.

The admittance rule alone is checked axis by axis at the update rate
(``jaxsync.control.ros2_admittance.stability_index``). The coupling family
(``jaxsync.control.coupling``) feeds one arm's errors into the other's
target, through the reference joints, the command delay and the joint
servos, so its stability is a property of the whole closed loop. This
module linearises that loop, as ``jaxsync.sim.rollout`` runs it on the
position stack, over one control period about the settled hold:

    x_{k+1} = F(x_k),   A = dF/dx (x*),   rho(A) = max |eig A|

x the loop's true state: the MJX data's qpos, qvel and act, the wrist
sensors' readings and the end effectors' accelerations of the last
constraint solve (the controller reads them one physics step late), the
reference joints q_ref and both arms' rule states, the coupling's filters,
the command buffer and the integrated command. Time, the step counter and
the pads' start (constant once the task has started) are not state; every
other field of ``mjx.Data`` is recomputed by the step from these, and the
solver's warm start is held at the hold's (the converged Newton solve does
not depend on it; its derivative is the implicit one,
``jaxsync.physics.step.solve_implicit``). ``jax.jacfwd`` gives A, float64;
NumPy its eigenvalues. The loop is stable about the hold where rho < 1.
What the period overwrites (the rule's joint acceleration, a filter with
coefficient 1, the buffer past the entries the delay reads, the integrated
command the rule does not read) gives zero columns: A e_j = 0, so each
such row and column is deflated first (eigenvalue 0, exactly), 260 of the
407 entries at delay 1 on the paper model.

Modes at 1 whatever the gains. The hold has them (measured on the paper
model: rho(A) = 1.0000345 for the rule alone, tests/test_loop_stability.py):

  N  the object's orientation (its quaternion): a sphere of isotropic
     inertia, nothing the loop reads depends on it once the object does
     not spin (the hold is taken with its angular velocity zero: the spin
     the task left it is one of a family of holds, no torsional friction
     with condim-3 pads). Invariant: A_RN = 0.
  M  ros2_controllers' rule moves its joint offset only through
     (J^T J + alpha I)^-1 J^T, so each 7-joint arm's offset and rate along
     the null space of its pad Jacobian J are driven by nothing (a Jordan
     block at 1: a null-space offset stays, and the arm holds it).
     Receives from nothing else: A_MR = 0.
  H  held at the hold, not tested: the object's spin rate about the axis
     through the two contacts (free but for the contacts' offset from
     antipodal) and its position in the plane normal to that axis (MuJoCo's
     friction is a velocity-level constraint: nothing restores it, and the
     pads' sphere caps make it drift, 1 + 4e-5 per period: the object's
     creep down the pads, docs/model.md). A real grip holds it by stiction.

In an orthonormal basis [N, M, H, R] the split is block triangular but for
what H holds, and

    rho = max |eig A_RR|,   A_RR = Q_R^T A Q_R,

with eig A_NN, eig A_MM, eig A_HH (at 1) reported as ``removed`` and the
largest entry of A_RN, A_HN, A_MN, A_MR, A_MH (what the split neglects) as
``residual``. Rollouts decide whether holding H changes the answer: they
agree with rho on both sides of its boundary (docs/loop-stability.md).

The margin is the rule's own: the loop is stable with margin when it stays
stable with every coupling gain (cpl_rel, cpl_own, cpl_other, cpl_force
and cpl_block) multiplied by ``scale`` (1.5, ``DEPLOY_MARGIN``): the
coupling's offset o_i, as a whole, 1.5 times larger. ros2_synchronous runs
as its family form (``jaxsync.control.coupling.of_synchronous``: rel =
(k_rk, -k_lk), own = k_il - 1, other = -k_il, the same loop to rounding),
so scaling it is o_i = k_ik (delta_r - delta_l) + k_il (e_i - e_j) - e_i
times 1.5, the whole offset that ros2_synchronous adds to the rule's, and
its rule alone is ros2_admittance with its gains. ``radius_late`` is the
loop as given at delay + 1 (a deployment's delay may be a period longer
than measured; even and odd delays can differ, docs/loop-stability.md):
reported, not in the verdict, whose delay is the caller's. Every variant is
linearised about one hold, the rule alone's (the family zeroed): a loop
that is unstable has no hold of its own, and the family's moves the
operating point by a fraction of a millimetre (docs/loop-stability.md).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import controller as _controller
from jaxsync.control import coupling as _coupling
from jaxsync.control import gains as _gains
from jaxsync.control.controller import ControllerOptions
from jaxsync.control.names import FAMILY, POSITION_ONLY
from jaxsync.control.ros2_admittance import DEPLOY_MARGIN
from jaxsync.physics import step as _physics
from jaxsync.runtime import programs
from jaxsync.sim import actuation as _actuation
from jaxsync.sim import closed_loop as _closed_loop
from jaxsync.sim import rollout as _rollout
from jaxsync.sim import scenario as _scenario

HOLD_S = 1.8
"""s of hold before the loop is linearised (the comparison's 4 s: the default
task's hold starts at 2.2 s)."""
PASSES = "mjx"  # the rollout's own tree passes (jaxsync.sim.rollout's default)
VERDICTS = ("stable with margin", "within margin", "unstable")


class LoopState(NamedTuple):
    """What one control period carries to the next: the loop's true state."""

    qpos: jax.Array  # (nq,)
    qvel: jax.Array  # (nv,)
    act: jax.Array  # (na,)
    sensors: jax.Array  # the acceleration-stage sensors' entries (the wrists' force/torque)
    cacc: jax.Array  # (2, 6) the end effectors' com-based accelerations (the wrist compensation's)
    ros2: object  # q_ref and both rules' states (jaxsync.control.ros2_loop.Ros2State)
    coupling: object  # the family's filters (jaxsync.control.coupling.CouplingState)
    buffer: jax.Array  # (MAX_DELAY + 2, 2 n) the commands on their way to the servo
    command: jax.Array  # (2 n,) the integrated command


class LoopMargin(NamedTuple):
    """What :func:`loop_margin` measured: spectral radii of the period map's
    Jacobian over the tested part (module docstring), and its verdict."""

    radius: float  # the loop as given
    radius_scaled: float  # every coupling gain times ``scale``
    radius_rule: float  # the rule alone (the family zeroed)
    radius_late: float  # the loop as given at delay + 1 (nan at MAX_DELAY)
    radius_whole: float  # the loop as given over the whole state, the removed modes included
    scale: float
    delay: int
    verdict: str  # one of VERDICTS (radius and radius_scaled decide)
    phrase: str  # one line for an error message, with the numbers
    state_size: int  # entries of x
    tested_size: int  # dim R: x less the removed modes and the entries the period overwrites
    removed: np.ndarray  # the removed modes' eigenvalues (at 1)
    residual: float  # the largest Jacobian entry that the split neglects
    hold_speed: float  # the fastest joint or object speed at the hold, rad/s or m/s


def family_form(gains, controller: str):
    """(placement, gains as the coupling family runs them) for a position-only
    controller: ros2_admittance the family zeroed, ros2_synchronous its
    family form (``coupling.of_synchronous``), the family's own as given."""
    if controller not in POSITION_ONLY:
        raise ConfigError(
            f"loop_margin: controller must be one of {list(POSITION_ONLY)} (the position stack), got {controller!r}",
            inputs=("controller",),
        )
    if controller == "ros2_admittance":
        return "reference", scaled(gains, 0.0)
    if controller == "ros2_synchronous":
        return "reference", _coupling.of_synchronous(gains)
    return FAMILY[controller], gains


def scaled(gains, factor: float):
    """``gains`` with every coupling gain (``coupling.GAIN_FIELDS`` and
    ``BLOCK_FIELD``) times ``factor``; the filters as they are."""
    fields = (*_coupling.GAIN_FIELDS, _coupling.BLOCK_FIELD)
    return gains._replace(**{f: getattr(gains, f) * factor for f in fields})


def _layout(x: LoopState) -> dict[str, tuple[int, tuple[int, ...]]]:
    """Each leaf's name -> (offset in the flat state, shape)."""
    out, start = {}, 0
    for path, leaf in jax.tree_util.tree_flatten_with_path(x)[0]:
        out[jax.tree_util.keystr(path)] = (start, tuple(np.shape(leaf)))
        start += int(np.size(leaf))
    return out


def _ravel(x: LoopState) -> jax.Array:
    return jnp.concatenate([jnp.ravel(leaf) for leaf in jax.tree_util.tree_leaves(x)])


def _unravel(flat: jax.Array, like: LoopState) -> LoopState:
    leaves, treedef = jax.tree_util.tree_flatten(like)
    out, start = [], 0
    for leaf in leaves:
        out.append(flat[start : start + leaf.size].reshape(leaf.shape))
        start += leaf.size
    return jax.tree_util.tree_unflatten(treedef, out)


@programs.memoize(maxsize=8)
def _programs(model, placement: str, distro: str, substeps: int):
    """(settle, jacobian, split, dt) for one placement, release and control
    period, the first two jitted: ``settle(gains, s, n) -> (d, controller
    state, (command, buffer), pad_start)`` after n periods from the task's
    start; ``jacobian(gains, s, d, cstate, held, pad_start, k) -> (A, x,
    aux)``, A = dF/dx of period k about that state, x its flat state, aux
    the pad Jacobians and contact points there; ``split`` the
    :class:`LoopState` of a carry; dt the period, s."""
    kind = "ros2_coupled" if placement == "reference" else "ros2_coupled_direct"
    options = ControllerOptions(kind=kind, distro=distro)
    consts = _closed_loop.consts(model)
    pc = _actuation.position_consts(model)
    q0 = _closed_loop.initial_command(model, consts)
    index, unroll = model.index, model.solver_unroll
    d_template = _physics.put_data(model.mj_model, mujoco.MjData(model.mj_model))
    m = model.mj_model
    acc = np.nonzero(np.asarray(m.sensor_needstage) == mujoco.mjtStage.mjSTAGE_ACC)[0]
    sensor_adr = np.array([a for i in acc for a in range(m.sensor_adr[i], m.sensor_adr[i] + m.sensor_dim[i])], int)
    ee = np.array([a.ee_body for a in index.arms])
    dt = float(m.opt.timestep) * substeps

    def physics_model(s):
        return _rollout.scenario_model(model, s, pc)

    def period(mx, gains, s, d, cstate, held, pad_start, k):
        # jaxsync.sim.rollout's position stack, its own pieces (a test compares the two)
        t = k * dt
        d, pad_start, _, sensed = _rollout.sense_period(mx, consts, index, s, d, pad_start, k, PASSES)
        arms = (sensed.right, sensed.left)
        command, buffer = held
        command, sent, cstate, _, _, _ = _closed_loop.control_position(
            options, gains, s, consts, cstate, arms, pad_start, t, dt, command
        )
        aux = (jnp.stack([a.jac for a in arms]), jnp.stack([d._impl.contact.pos[a.contact_id] for a in index.arms]))
        d, buffer, _ = _rollout.servo_period(mx, pc, consts, s, d, buffer, sent, dt, substeps, PASSES, unroll)
        return (d, cstate, (command, buffer), pad_start), aux

    def settle(gains, s, n):
        mx = physics_model(s)
        d0 = d_template.replace(qpos=_closed_loop.initial_qpos(model, consts, s))
        held = (jnp.asarray(q0), _actuation.initial_buffer(q0))
        init = (d0, _controller.init(jnp.asarray(q0)), held, jnp.zeros((len(index.arms), 3), d0.qpos.dtype))
        return jax.lax.fori_loop(0, n, lambda k, c: period(mx, gains, s, *c, k)[0], init)

    def split(d, cstate, held) -> LoopState:
        return LoopState(
            d.qpos, d.qvel, d.act, d.sensordata[sensor_adr], d._impl.cacc[ee], cstate.ros2, cstate.coupling, *held[::-1]
        )

    def jacobian(gains, s, d, cstate, held, pad_start, k):
        mx = physics_model(s)
        like = split(d, cstate, held)

        def f(flat):
            x = _unravel(flat, like)
            dd = d.replace(qpos=x.qpos, qvel=x.qvel, act=x.act, sensordata=d.sensordata.at[sensor_adr].set(x.sensors))
            dd = dd.tree_replace({"_impl.cacc": d._impl.cacc.at[ee].set(x.cacc)})
            cs = cstate._replace(ros2=x.ros2, coupling=x.coupling)
            (dd, cs, hh, _), aux = period(mx, gains, s, dd, cs, (x.command, x.buffer), pad_start, k)
            return _ravel(split(dd, cs, hh)), aux

        flat = _ravel(like)
        a, aux = jax.jacfwd(f, has_aux=True)(flat)
        return a, flat, aux

    return jax.jit(settle), jax.jit(jacobian), split, dt


def removed_bases(layout, flat, aux, model):
    """(N, M, H), orthonormal columns over the flat state (module docstring):
    N the object's quaternion; M each 7-joint arm's rule offset and rate
    along the null space of its pad Jacobian; H the object's spin rate about
    the axis through the two contacts and its position in the plane normal
    to that axis. ``aux``: the pad Jacobians (2, 6, n) and the pads' contact
    points (2, 3) at the hold."""
    size, index, eye = flat.size, model.index, np.eye(flat.size)
    qa = index.object_qpos_adr + layout[".qpos"][0]
    va = index.object_dof_adr + layout[".qvel"][0]
    jac, contact = (np.asarray(x, dtype=float) for x in aux)
    toward = [(p - flat[qa : qa + 3]) / np.linalg.norm(p - flat[qa : qa + 3]) for p in contact]
    axis = (toward[0] - toward[1]) / np.linalg.norm(toward[0] - toward[1])
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, flat[qa + 3 : qa + 7])
    held = np.zeros((size, 3))
    held[va + 3 : va + 6, 0] = rot.reshape(3, 3).T @ axis  # a free joint's angular velocity is in the body frame
    held[qa : qa + 3, 1:] = np.linalg.svd(axis[None, :])[2][1:].T  # the plane normal to the axis
    m_cols = []
    for i, j in enumerate(jac):
        null = np.linalg.svd(j)[2][j.shape[0] :]  # none for a 6-joint arm
        for name in (".ros2.rule.joint_pos", ".ros2.rule.joint_vel"):
            start, shape = layout[name]
            for v in null:
                col = np.zeros(size)
                col[start + i * shape[1] : start + (i + 1) * shape[1]] = v
                m_cols.append(col)
    m_basis = np.stack(m_cols, axis=1) if m_cols else np.zeros((size, 0))
    return eye[:, qa + 3 : qa + 7], m_basis, held


class Split(NamedTuple):
    """:func:`split_radius`'s answer."""

    radius: float  # rho(A_RR)
    whole: float  # rho(A), the removed modes included
    removed: np.ndarray  # eig A_NN, eig A_MM, eig A_HH
    residual: float  # the largest entry of A_RN, A_HN, A_MN, A_MR, A_MH: what the split neglects
    tested: int  # dim R


def overwritten(a: np.ndarray) -> np.ndarray:
    """The entries the period overwrites, found by deflation: a zero column
    j of A means A e_j = 0, an eigenvalue 0 on an invariant direction, so
    row and column j go; repeated, this takes the buffer's unread tail
    after the entry that feeds it. The rest's eigenvalues are A's but those
    zeros. Returns a boolean mask of the entries kept."""
    keep = np.ones(a.shape[0], dtype=bool)
    while True:
        dead = keep & ~np.any(a[keep] != 0.0, axis=0)
        if not dead.any():
            return keep
        keep &= ~dead


def split_radius(a: np.ndarray, n_basis: np.ndarray, m_basis: np.ndarray, h_basis: np.ndarray) -> Split:
    """rho(Q_R^T A Q_R), R the orthogonal complement of N (invariant), M
    (receiving from nothing else) and H (held), each an orthonormal basis,
    within the entries the period does not overwrite (:func:`overwritten`)."""
    keep = overwritten(a)
    a = a[np.ix_(keep, keep)]
    n_basis, m_basis, h_basis = (b[keep] for b in (n_basis, m_basis, h_basis))
    removed = np.concatenate([n_basis, m_basis, h_basis], axis=1)
    rest = np.linalg.qr(removed, mode="complete")[0][:, removed.shape[1] :]
    block = lambda rows, cols: rows.T @ a @ cols  # noqa: E731
    eig = lambda basis: np.linalg.eigvals(block(basis, basis)) if basis.shape[1] else np.zeros(0)  # noqa: E731
    neglected = [block(rest, n_basis), block(h_basis, n_basis), block(m_basis, n_basis)]
    neglected += [block(m_basis, rest), block(m_basis, h_basis)]
    return Split(
        radius=float(np.max(np.abs(eig(rest)))),
        whole=float(np.max(np.abs(np.linalg.eigvals(a)))),
        removed=np.concatenate([eig(n_basis), eig(m_basis), eig(h_basis)]),
        residual=max((float(np.max(np.abs(x))) for x in neglected if x.size), default=0.0),
        tested=rest.shape[1],
    )


def loop_margin(
    model,
    gains,
    controller: str,
    *,
    delay: int,
    control_rate: float | None = None,
    distro: str = "jazzy",
    scale: float = DEPLOY_MARGIN,
    scenario=None,
) -> LoopMargin:
    """The coupled loop's stability about the settled hold (module docstring).

    Args:
      model: a loaded model (``jaxsync.load_model``).
      gains: constant ``Gains`` (a schedule: call once per phase).
      controller: one of ``jaxsync.control.names.POSITION_ONLY``.
      delay: the command delay, whole control periods.
      control_rate: Hz (None: every physics step), as ``Stack.control_rate``.
      distro: the ros2_controllers release the rule runs.
      scale: the margin: every coupling gain times this must stay stable.
      scenario: the task rolled to its hold (default: ``default_scenario(model)``,
        the comparison's); its sensor noise is turned off and its delay set.

    Returns a :class:`LoopMargin`: radius (the gains), radius_scaled (the
    coupling times ``scale``), radius_rule (the family zeroed), radius_late
    (delay + 1, reported, not in the verdict), the verdict ("stable with
    margin": radius_scaled < 1; "within margin": radius < 1 <= radius_scaled;
    "unstable": radius >= 1) and its phrase.

    Example:
      >>> r = loop_margin(model, gains, "ros2_coupled", delay=1)  # doctest: +SKIP
      >>> r.verdict, round(r.radius, 5)  # doctest: +SKIP
      ('stable with margin', 0.99995)
    """
    if not isinstance(gains, _gains.Gains):
        raise ConfigError("loop_margin: constant Gains (a schedule: one call per phase)", inputs=("gains",))
    lo, delay = _actuation.check_delay(delay)
    if lo != delay:
        raise ConfigError(f"loop_margin: one delay, got the range {lo}:{delay}", inputs=("delay",))
    if not (isinstance(scale, int | float) and np.isfinite(scale) and scale >= 1.0):
        raise ConfigError(f"loop_margin: scale must be a number >= 1, got {scale!r}", inputs=("scale",))
    _actuation.check_distro(distro)
    placement, family = family_form(_gains.strongly_typed(gains), controller)
    rule, stretched = scaled(family, 0.0), scaled(family, float(scale))
    base = _scenario.default_scenario(model) if scenario is None else scenario

    def task(n_delay):
        s = base._replace(force_noise=0.0, torque_noise=0.0, delay=float(n_delay))
        return _scenario.strongly_typed(_scenario.validate(s))

    s = task(delay)
    settle, jacobian, split, dt = _programs(model, placement, distro, _actuation.substeps_for_rate(model, control_rate))
    n = int(round((float(_scenario.phase_times(s)[2]) + HOLD_S) / dt))
    d, cstate, held, pad_start = settle(rule, s, n)
    gap = np.asarray([d._impl.contact.dist[a.contact_id] for a in model.index.arms])
    if not (np.all(np.isfinite(np.asarray(d.qpos))) and np.all(gap < 0.0)):
        raise ConfigError(
            f"loop_margin: the rule alone does not hold the object at the end of the task (pad gaps {gap} m): "
            "no hold to linearise about; its own stability comes first",
            inputs=("gains",),
        )
    va = model.index.object_dof_adr
    d = d.replace(qvel=d.qvel.at[va + 3 : va + 6].set(0.0))  # the hold without the object's free spin
    layout = _layout(split(d, cstate, held))

    def radius(g, s_) -> Split:
        a, flat, aux = jacobian(g, s_, d, cstate, held, pad_start, n)
        return split_radius(np.asarray(a), *removed_bases(layout, np.asarray(flat), aux, model))

    own = radius(family, s)  # every buffer row holds the one command at the hold: it serves delay + 1 too
    r, r_scaled, r_rule = own.radius, radius(stretched, s).radius, radius(rule, s).radius
    r_late = radius(family, task(delay + 1)).radius if delay < _scenario.MAX_DELAY else float("nan")
    verdict = VERDICTS[2] if r >= 1.0 else VERDICTS[1] if r_scaled >= 1.0 else VERDICTS[0]
    late = f"; {r_late:.5f} at delay {delay + 1}" if np.isfinite(r_late) else ""
    phrase = (
        f"the coupled loop ({controller}, delay {delay}) has spectral radius {r:.5f} per control period about the "
        f"hold, {r_scaled:.5f} with the coupling gains x{scale:g} (the rule alone {r_rule:.5f}{late}): {verdict}"
    )
    speed = float(np.max(np.abs(np.asarray(d.qvel))))
    return LoopMargin(
        radius=r,
        radius_scaled=r_scaled,
        radius_rule=r_rule,
        radius_late=r_late,
        radius_whole=own.whole,
        scale=float(scale),
        delay=delay,
        verdict=verdict,
        phrase=phrase,
        state_size=sum(int(np.prod(shape)) for _, shape in layout.values()),
        tested_size=own.tested,
        removed=own.removed,
        residual=own.residual,
        hold_speed=speed,
    )
