"""One physics step split around the controller, and MJX's private helpers.

``mjx.step`` is ``forward`` then ``integrate``. A controller needs the
kinematics and dynamics of the *current* state, but the wrist sensors and
contact forces come out of the constraint solve, which needs the torques: an
algebraic loop that a real robot breaks with a one-sample delay. So, like
MuJoCo C's ``mj_step1``/``mj_step2``:

  ``before_control``: position and velocity stages at the current state
     (kinematics, mass matrix, bias forces, Jacobians);
  the controller reads them, plus the force/torque sensors and body
     accelerations of the previous step's solve;
  ``after_control``: actuation, acceleration, constraint solve, acceleration
     sensors, Euler integration.

The pair costs exactly one ``mjx.forward``. MJX's private API is used in this
module only.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from mujoco import mjx
from mujoco.mjx._src import collision_driver as _collision_driver
from mujoco.mjx._src import constraint as _constraint
from mujoco.mjx._src import math as _math
from mujoco.mjx._src import passive as _passive
from mujoco.mjx._src import smooth as _smooth
from mujoco.mjx._src import solver as _solver
from mujoco.mjx._src import support as _support
from mujoco.mjx._src.types import ConeType, DisableBit, IntegratorType, SensorType

from jaxsync.physics import body_tree as _body_tree

PASSES = ("mjx", "tree")
"""How the body tree's passes are computed: ``"mjx"`` MJX's own stages (what
forward rollouts and batches run), ``"tree"`` jaxsync's vectorised ones
(:mod:`jaxsync.physics.body_tree`, the same values to rounding and a far smaller program:
what gradient programs run)."""


def _world_acc(m: mjx.Model) -> jax.Array:
    """The world's ``cacc`` (6,): [0, -g], zero with gravity disabled (MJX's RNE)."""
    if m.opt.disableflags & DisableBit.GRAVITY:
        return jnp.zeros(6)
    return jnp.concatenate([jnp.zeros(3), -m.opt.gravity])


def tree_covered(m: mjx.Model, passes: str) -> bool:
    """Whether ``passes`` asks for :mod:`jaxsync.physics.body_tree` and it covers ``m``'s tree."""
    if passes not in PASSES:
        raise ValueError(f"passes must be one of {PASSES}, got {passes!r}")
    return passes == "tree" and _body_tree.kinematics_plan(m) is not None


def fwd_position(m: mjx.Model, d: mjx.Data, passes: str = "mjx") -> mjx.Data:
    """``mjx.fwd_position`` (MJX 3.17's stages, in its order); with
    ``passes="tree"`` jaxsync's tree passes (kinematics level by level, the
    subtree sums of ``com_pos`` and ``crb`` as products with static matrices)
    in place of MJX's where the model's tree allows."""
    if not tree_covered(m, passes):
        return mjx.fwd_position(m, d)
    d = _body_tree.kinematics(m, d)
    d = _body_tree.com_pos(m, d)
    d = _smooth.camlight(m, d)
    d = _smooth.tendon(m, d)
    crb = _body_tree.crb_body(m, d)
    crb_cdof = _body_tree.inert_mul(crb[np.asarray(m.dof_bodyid)], d.cdof)
    d = d.tree_replace({"_impl.crb": crb, "_impl.M": _support.make_m(m, crb_cdof, d.cdof, m.dof_armature)})
    d = _smooth.tendon_armature(m, d)
    d = _smooth.factor_m(m, d)
    d = _collision_driver.collision(m, d)
    d = _constraint.make_constraint(m, d)
    return _smooth.transmission(m, d)


def fwd_velocity(m: mjx.Model, d: mjx.Data, passes: str = "mjx") -> mjx.Data:
    """``mjx.fwd_velocity``; with ``passes="tree"`` jaxsync's ``com_vel`` and
    bias forces (one product down the tree, one up) where the tree allows."""
    if not tree_covered(m, passes):
        return mjx.fwd_velocity(m, d)
    d = d.tree_replace(
        {"_impl.actuator_velocity": d._impl.actuator_moment @ d.qvel, "_impl.ten_velocity": d._impl.ten_J @ d.qvel}
    )
    d = _body_tree.com_vel(m, d)
    d = _passive.passive(m, d)
    d = d.replace(qfrc_bias=_body_tree.bias_force(m, d, _world_acc(m)))
    return _smooth.tendon_bias(m, d)


@functools.partial(jax.jit, static_argnames="passes")
def before_control(m: mjx.Model, d: mjx.Data, passes: str = "mjx") -> mjx.Data:
    """Position and velocity stages of ``mjx.forward`` (MuJoCo's mj_step1);
    ``passes`` (:data:`PASSES`) chooses MJX's tree passes or jaxsync's."""
    d = fwd_position(m, d, passes)
    d = mjx.sensor_pos(m, d)
    d = fwd_velocity(m, d, passes)
    return mjx.sensor_vel(m, d)


def forget_stage_traces() -> None:
    """Drop the traces of :func:`before_control` and :func:`after_control`
    (and the derivatives built on them). Called once a gradient has been
    traced (``optimize.tune``): the stage traces it leaves made programs traced
    after it lower differently from the same programs in a process that read
    the gradient from disk instead, so the persistent cache missed them
    (measured in the test suite: three programs compiled again, 77 s, in the
    first warm run after a cold one). The next program traces the stages
    again (a few seconds)."""
    before_control.clear_cache()
    after_control.clear_cache()


# ------------------------------------------------ implicit adjoint of the solve


def constraint_residual(m: mjx.Model, d: mjx.Data, qacc: jax.Array):
    """MJX's optimality condition of the constraint solve at ``qacc``, and its forces.

    The Newton solver minimises the Gauss cost plus the constraint cost; its
    gradient is r(qacc) = M qacc - qfrc_smooth - J^T f(J qacc - aref) (MJX's
    ``ctx.grad``, with M (qacc - qacc_smooth) = M qacc - qfrc_smooth). It is
    zero at the solution, and its Jacobian in qacc is the Newton Hessian
    H = M + J^T D_active J (plus the elliptic cone's Hessian in the cone's
    middle zone). Returns (r (nv,), qfrc_constraint (nv,), efc_force (nefc,)),
    all differentiable in ``qacc`` and in everything the solve reads (M,
    qfrc_smooth, efc_J, efc_aref, efc_D, friction).
    """
    ctx = _solver.Context.create(m, d.replace(qacc=qacc), grad=False)
    return ctx.Ma - d.qfrc_smooth - ctx.qfrc_constraint, ctx.qfrc_constraint, ctx.efc_force


def newton_hessian(m: mjx.Model, d: mjx.Data, qacc: jax.Array) -> jax.Array:
    """H = dr/dqacc (nv, nv) at ``qacc``: the mass matrix plus J^T C J, with C
    the active rows' D and the elliptic cone's Hessian blocks (MJX's Newton
    Hessian, ``solver._update_gradient``), symmetrised."""
    ctx = _solver.Context.create(m, d.replace(qacc=qacc), grad=False)
    efc_d = d._impl.efc_D
    if m.opt.cone == ConeType.ELLIPTIC:
        cm = jnp.diag(efc_d * ctx.active)
        contact = d._impl.contact
        cone = contact.dim > 1
        for i, (condim, addr) in enumerate(zip(contact.dim[cone], contact.efc_address[cone], strict=True)):
            cm = cm.at[addr : addr + condim, addr : addr + condim].add(ctx.h[i, :condim, :condim])
        h = d._impl.efc_J.T @ cm @ d._impl.efc_J
    else:
        h = (d._impl.efc_J.T * (efc_d * ctx.active)) @ d._impl.efc_J
    h = _support.full_m(m, d) + h
    return 0.5 * (h + h.T)


SOLVE_OUTPUTS = "jaxsync_solve_outputs"
"""The name (``jax.ad_checkpoint.checkpoint_name``) of the converged solve's
outputs: ``jax.checkpoint(..., policy=REMAT_POLICY)`` saves them."""

REMAT_POLICY = jax.checkpoint_policies.save_only_these_names(SOLVE_OUTPUTS)


def solve_implicit(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """``mjx.solve`` (converged, its ``while_loop``) with an implicit derivative.

    The forward pass is MJX's own solve, to its iterations and tolerance. The
    derivative is not taken through the iterations (reverse mode cannot pass
    MJX's ``while_loop``, and unrolling them costs memory and time): by the
    implicit function theorem at r(qacc*) = 0 (:func:`constraint_residual`),
    d qacc* = -H^-1 (dr/dp) dp with H the Newton Hessian at the solution
    (:func:`newton_hessian`, factored once per step by Cholesky):
    ``jax.lax.custom_root``, so forward mode (``jax.jvp``) and reverse mode
    both work. The constraint forces are then recomputed from qacc* so that
    their derivatives flow to the contact forces and the wrist sensors.
    Forward values are exactly MJX's: the recomputed forces only carry
    derivatives (x + (y - stop_gradient(y)) adds exactly zero).
    """
    d_const = jax.lax.stop_gradient(d)
    solved = mjx.solve(m, d_const)
    # named so that a rematerialised scan keeps them (REMAT_POLICY): the
    # backward pass then never runs the solve's while loops again
    solved = solved.tree_replace(
        {
            "qacc": checkpoint_name(solved.qacc, SOLVE_OUTPUTS),
            "qfrc_constraint": checkpoint_name(solved.qfrc_constraint, SOLVE_OUTPUTS),
            "_impl.efc_force": checkpoint_name(solved._impl.efc_force, SOLVE_OUTPUTS),
        }
    )
    chol = jax.scipy.linalg.cho_factor(newton_hessian(m, d_const, solved.qacc))

    def residual(qacc):
        return constraint_residual(m, d, qacc)[0]

    qacc = jax.lax.custom_root(
        residual,
        solved.qacc,
        solve=lambda _, guess: solved.qacc,
        tangent_solve=lambda _, y: jax.scipy.linalg.cho_solve(chol, y),
    )
    _, qfrc, efc = constraint_residual(m, d, qacc)

    def carry(value, differentiable):
        return jax.lax.stop_gradient(value) + (differentiable - jax.lax.stop_gradient(differentiable))

    return d.tree_replace(
        {
            "qacc": qacc,
            "qfrc_constraint": carry(solved.qfrc_constraint, qfrc),
            "_impl.efc_force": carry(solved._impl.efc_force, efc),
        }
    )


@functools.partial(jax.jit, static_argnames="solver_unroll")
def after_control(m: mjx.Model, d: mjx.Data, ctrl: jax.Array, solver_unroll: int = 1) -> mjx.Data:
    """Actuation, constraint solve, acceleration sensors and integration (mj_step2).

    With ``m.opt.iterations > 1`` (jaxsync's one solver setting) the solve is
    MJX's converged Newton solve, differentiated implicitly
    (:func:`solve_implicit`). With ``m.opt.iterations == 1`` (the
    "unrolled" setting: a reference path the benchmark and the gradient tests
    compare against) the one-iteration solve runs ``solver_unroll`` times,
    each warm-started from the last, and reverse mode differentiates through
    the iterations.
    """
    d = d.replace(ctrl=ctrl)
    d = mjx.fwd_actuation(m, d)
    d = mjx.fwd_acceleration(m, d)
    if d._impl.efc_J.size == 0:
        d = d.replace(qacc=d.qacc_smooth)
    else:
        if m.opt.iterations > 1:
            d = solve_implicit(m, d)
        elif solver_unroll > 1:
            # a scan traces the solve once (unrolled, the program held three
            # copies; same values to 1e-14, docs/performance.md)

            def one_solve(dd, _):
                dd = mjx.solve(m, dd)
                return dd.replace(qacc_warmstart=dd.qacc), None  # mjx.euler sets the next warm start

            d, _ = jax.lax.scan(one_solve, d, None, length=solver_unroll)
        else:
            d = mjx.solve(m, d)
        plan = leaf_sensor_plan(m)
        d = mjx.sensor_acc(m, d) if plan is None else leaf_sensor_acc(m, d, plan)
    if m.opt.integrator != IntegratorType.EULER:
        raise NotImplementedError("jaxsync steps the Euler integrator only")
    return mjx.euler(m, d)


def local_device():
    """This process's first device. MJX's own default is ``jax.devices()[0]``,
    which in a multi-process run (jaxsync.runtime.distributed) is process 0's."""
    return jax.local_devices()[0]


def put_data(mj_model, mj_data) -> mjx.Data:
    """``mjx.put_data`` with the contact geom ids in the integer dtype that
    MJX's collision step produces (int64 under x64), so the data can be the
    carry of a ``lax.scan`` over steps."""
    d = mjx.put_data(mj_model, mj_data, device=local_device(), impl="jax")
    c = d._impl.contact
    c = c.replace(**{k: jnp.asarray(np.asarray(getattr(c, k), np.int64)) for k in ("geom", "geom1", "geom2")})
    return d.tree_replace({"_impl.contact": c})


def static_contact_geoms(m: mjx.Model) -> np.ndarray:
    """(ncon, 2) geom ids of MJX's contact list, in MJX's order, without tracing.

    MJX fixes its contact list at trace time: one group per collision
    function, each repeated by the function's contact count, then ordered by
    condim (``collision_driver.collision``). This replays that ordering.
    """
    by_condim: dict[int, list[np.ndarray]] = {}
    for key, geom_ids in _collision_driver._geom_groups(m).items():
        geom = np.array(geom_ids)[:, :2]
        ncon = _collision_driver._COLLISION_FUNC[key.types].ncon
        by_condim.setdefault(key.condim, []).append(np.repeat(geom, ncon, axis=0))
    groups = [g for c in sorted(by_condim) for g in by_condim[c]]
    return np.concatenate(groups) if groups else np.zeros((0, 2), int)


def contact_force_on(m: mjx.Model, d: mjx.Data, contact_id: int, on_geom1: bool) -> jax.Array:
    """World-frame force (3,) on one geom of contact ``contact_id``.

    MuJoCo's contact normal points from geom1 to geom2 and a positive normal
    force pushes them apart: the contact-frame force acts on geom2 as it is
    and on geom1 with the opposite sign. Which geom is which is static
    (:func:`static_contact_geoms`).
    """
    f = _support.contact_force(m, d, contact_id, to_world_frame=True)[:3]
    return -f if on_geom1 else f


def contact_distance(d: mjx.Data, contact_id: int) -> jax.Array:
    """Signed distance of a contact (negative: penetration)."""
    return d._impl.contact.dist[contact_id]


def jac(m: mjx.Model, d: mjx.Data, point: jax.Array, body_id: int, passes: str = "mjx"):
    """(nv, 3) translational and rotational Jacobians of a point on a body
    (MJX's ``jac``; with ``passes="tree"`` the chain's mask static)."""
    return _body_tree.jac(m, d, point, body_id) if tree_covered(m, passes) else mjx.jac(m, d, point, body_id)


def jac_dot(m: mjx.Model, d: mjx.Data, point: jax.Array, body_id: int, passes: str = "mjx"):
    """(nv, 3) time derivatives of the translational and rotational Jacobians."""
    if tree_covered(m, passes):
        return _body_tree.jac_dot(m, d, point, body_id)
    return _support.jac_dot(m, d, point, body_id)


def inertial_wrench(cinert: jax.Array, cvel: jax.Array, cacc: jax.Array) -> jax.Array:
    """cinert*cacc + cvel x* (cinert*cvel) of one body (6,), com-based, [torque, force].

    The net wrench the body needs for its acceleration (gravity included:
    MuJoCo's ``cacc`` carries -g). MuJoCo's ``cfrc_int`` of a leaf body equals
    it minus the external (contact) wrench.
    """
    return _math.inert_mul(cinert, cacc) + _math.motion_cross_force(cvel, _math.inert_mul(cinert, cvel))


# ------------------------------------------------ the wrist force/torque sensors


def leaf_sensor_plan(m: mjx.Model) -> tuple | None:
    """What :func:`leaf_sensor_acc` reads from the model (all static), or None
    when MJX's own ``sensor_acc`` has to run: every acceleration-stage sensor
    must be a force or torque sensor on a site of a leaf body (no child
    bodies) that no equality constraint holds, as the dual-arm model's two
    wrist sensors are. One row per sensor: (type, adr, site, body, root,
    cutoff, dof mask of the body's chain)."""
    stage_acc = np.asarray(m.sensor_needstage) == mujoco.mjtStage.mjSTAGE_ACC
    if m.opt.disableflags & DisableBit.SENSOR or not stage_acc.any():
        return ()
    rows = np.nonzero(stage_acc)[0]
    if not all(int(m.sensor_type[i]) in (SensorType.FORCE, SensorType.TORQUE) for i in rows):
        return None
    parent = np.asarray(m.body_parentid)
    held = set(np.asarray(m.eq_obj1id).tolist()) | set(np.asarray(m.eq_obj2id).tolist()) if m.neq else set()
    plan = []
    for i in rows:
        site = int(m.sensor_objid[i])
        body = int(m.site_bodyid[site])
        if body == 0 or (parent[1:] == body).any() or body in held or site in held:
            return None
        chain = np.zeros(m.nv)
        b = body
        while b > 0:  # the dofs between the world and the body
            chain[int(m.body_dofadr[b]) : int(m.body_dofadr[b]) + int(m.body_dofnum[b])] = 1.0
            b = int(parent[b])
        row = (int(m.sensor_type[i]), int(m.sensor_adr[i]), site, body, int(m.body_rootid[body]))
        plan.append((*row, float(m.sensor_cutoff[i]), chain))
    return tuple(plan)


def leaf_sensor_acc(m: mjx.Model, d: mjx.Data, plan: tuple) -> mjx.Data:
    """MJX's ``sensor_acc`` for force/torque sensors on leaf bodies (``plan``
    from :func:`leaf_sensor_plan`), without its RNE over the whole tree.

    MuJoCo's force sensor reads ``cfrc_int`` of the site's body, the wrench its
    parent exerts on it; for a leaf body that is its inertial wrench
    (cinert cacc + cvel x* cinert cvel) less the external (contact and applied)
    wrench on it. ``cacc`` of the body is the sum along its chain of
    cdof_dot qvel + cdof qacc from the world's -g (MJX's forward pass,
    summed in one go). The same values as ``mjx.sensor_acc`` to rounding
    (tests/test_sensing.py); ``d._impl.cacc`` is set for the sensors' bodies
    only (the controller's wrist compensation reads it), ``cfrc_int`` and
    ``cfrc_ext`` are not set. MJX's RNE runs the tree level by level, a
    quarter of a step's program; this is a few dozen operations.
    """
    if not plan:
        return d
    cacc0 = _world_acc(m)
    geom_body = np.asarray(m.geom_bodyid)[static_contact_geoms(m)] if d._impl.contact.dim.size else np.zeros((0, 2))

    def com_based(frc, offset):  # [force, torque] at a point -> [torque, force] about point + offset
        return jnp.concatenate([frc[3:] - jnp.cross(offset, frc[:3]), frc[:3]])

    inner, cacc_of = {}, {}
    for _, _, _, body, root, _, chain in plan:
        if body in inner:
            continue
        com = d.subtree_com[root]
        cacc = cacc0 + d.cdof_dot.T @ (chain * d.qvel) + d.cdof.T @ (chain * d.qacc)
        ext = com_based(d.xfrc_applied[body], com - d.xipos[body])
        for i, (b1, b2) in enumerate(geom_body):
            if body in (b1, b2):  # the contact force acts on geom2 as it is, on geom1 opposed
                f = _support.contact_force(m, d, i, to_world_frame=True)
                ext = ext + (1.0 if b2 == body else -1.0) * com_based(f, com - d._impl.contact.pos[i])
        inner[body] = inertial_wrench(d._impl.cinert[body], d.cvel[body], cacc) - ext
        cacc_of[body] = cacc

    sensordata = d.sensordata
    for kind, adr, site, body, root, cutoff, _ in plan:
        frc, rot = inner[body], d.site_xmat[site]
        if kind == SensorType.FORCE:
            value = rot.T @ frc[3:]
        else:
            value = rot.T @ (frc[:3] - jnp.cross(d.site_xpos[site] - d.subtree_com[root], frc[3:]))
        if cutoff > 0:  # mjDATATYPE_REAL
            value = jnp.clip(value, -cutoff, cutoff)
        sensordata = sensordata.at[adr : adr + 3].set(value)
    bodies = np.array(list(cacc_of))
    cacc = d._impl.cacc.at[bodies].set(jnp.stack([cacc_of[b] for b in bodies]))
    return d.replace(sensordata=sensordata).tree_replace({"_impl.cacc": cacc})


def full_mass_matrix(m: mjx.Model, d: mjx.Data) -> jax.Array:
    return mjx.full_m(m, d)
