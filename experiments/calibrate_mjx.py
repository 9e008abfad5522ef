"""Fitting the servo through MJX's gradient against MuJoCo's toolbox, on one recording (docs/calibrate.md).

The recording of ``calibrate_accuracy.py`` (the default excitation, 20 s
at 500 Hz, UR5e-like pair, each joint's stiffness and damping drawn within
+-30 % of the robot file's, delay 2, MuJoCo C at 0.5 ms implicitfast,
sensor noise). Both fits get the delay and start from the robot file's
servo; both replay the same 0.5 s windows, each from its recorded state, at
the same 0.5 ms step, with the same residual (positions per 1 mrad,
velocities per 20 mrad/s):

- the toolbox: ``jaxsync.calibrate.fit.calibrate`` at the known delay
  (joint by joint, then all together: ``mujoco.sysid``'s least squares with
  finite-difference Jacobians on threaded MuJoCo C rollouts);
- MJX: the position stack's servo code (``jaxsync.sim.actuation.servo_torque``)
  stepped by ``jaxsync.physics.step`` in a ``lax.scan`` over every window
  (``vmap``), the residual's Jacobian by forward-mode ``jax.jacfwd`` over
  the 24 log-factors, Levenberg-Marquardt steps until one lowers the cost by
  less than 0.1 % (the noise floor), at most ``--max-iters``.

Prints each fit's wall time (the toolbox's whole ``calibrate`` call, its
tracking errors included; MJX's compilation, first Jacobian and iterations),
the largest stiffness and damping errors (MJX's after each iteration) and
the RMS position errors; one run, nothing else on the machine.

    JAXSYNC_CACHE_DIR=off python experiments/calibrate_mjx.py --out results/calibrate_mjx

(The compilation cache off: with it on, one run here stalled for 12 minutes
with every thread waiting, before its first Jacobian.)
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx
from mujoco.mjx._src.types import ConeType, DisableBit

from jaxsync.calibrate import excite, replay
from jaxsync.calibrate.fit import SIGMA_DQ, SIGMA_Q, calibrate
from jaxsync.io import bags
from jaxsync.physics import step as _step
from jaxsync.physics.model import load_model
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags
from jaxsync.sim import actuation as _actuation


def windows(rp: replay.Replay, rec, delay: int, window: float):
    """Each window's start state, the servo's acting command and its velocity at every step, and the
    recorded samples with the step each falls after."""
    h, n_steps = rp.timestep, int(round(window / rp.timestep))
    every = int(round(window / np.median(np.diff(rec.state_times))))
    q0, dq0, cmd, vel, meas, idx = [], [], [], [], [], None
    for i in range(0, len(rec.state_times), every):
        t0 = rec.state_times[i]
        if t0 + window > rec.state_times[-1]:
            break
        c, v = rp.acting(t0 + h * np.arange(n_steps), rec.command_times, rec.commands, delay, rec.command_period)
        inside = np.flatnonzero((rec.state_times > t0) & (rec.state_times <= t0 + window - 1e-9))
        at = np.round((rec.state_times[inside] - t0) / h).astype(int) - 1  # the state after step `at`
        if idx is None:
            idx = at
        inside = inside[: len(idx)]
        q0.append(rec.q[i]), dq0.append(rec.dq[i]), cmd.append(c), vel.append(v)
        meas.append(np.concatenate([rec.q[inside], rec.dq[inside]], axis=1))
    return n_steps, idx, *(np.stack(a) for a in (q0, dq0, cmd, vel, meas))


def mjx_residual(model, rp: replay.Replay, idx):
    """residual(theta, q0, dq0, cmd, vel, meas) over every window; theta the 2 x (2 n) log-factors."""
    pc = rp.pc
    mx = model.mjx_model  # jaxsync's solver settings; then the replay's changes: its step, contacts off
    # (the cone pyramidal: no contact is left, and MJX's elliptic solve fails on none)
    flags = mx.opt.disableflags | DisableBit.CONTACT
    mx = mx.replace(opt=mx.opt.replace(timestep=rp.timestep, disableflags=flags, cone=ConeType.PYRAMIDAL))
    for name, where, value in _actuation.model_updates(pc, 1.0):
        mx = mx.replace(**{name: getattr(mx, name).at[where].set(value)})
    base = jnp.asarray(rp.base_qpos)
    limit = jnp.asarray(rp.limit)
    qadr, dofs = jnp.asarray(pc.qpos_adr), jnp.asarray(pc.dof_adr)
    n = len(pc.stiffness)
    sigma = jnp.concatenate([jnp.full(n, SIGMA_Q), jnp.full(n, SIGMA_DQ)])

    def one(theta, q0, dq0, cmd, vel, meas):
        k, b = pc.stiffness * jnp.exp(theta[:n]), pc.damping * jnp.exp(theta[n:])
        m = mx.replace(dof_damping=mx.dof_damping.at[dofs].set(pc.joint_damping + b))
        p = pc._replace(stiffness=k, damping=b)
        d = mjx.make_data(m).replace(qpos=base.at[qadr].set(q0))
        d = d.replace(qvel=d.qvel.at[dofs].set(dq0))

        def body(d, u):
            d = _step.before_control(m, d, passes="tree")
            _, motor = _actuation.servo_torque(p, d.qpos, d.qvel, d.qfrc_bias, u[0], u[1], 1.0, limit)
            d = _step.after_control(m, d, d.ctrl.at[jnp.asarray(pc.actuator_ids)].set(motor))
            return d, jnp.concatenate([d.qpos[qadr], d.qvel[dofs]])

        _, states = jax.lax.scan(body, d, (cmd, vel))
        return ((states[idx] - meas) / sigma).ravel()

    batched = jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0))
    return lambda theta, *w: batched(theta, *w).ravel()


def fit_mjx(res, data, n: int, max_iters: int, say):
    """Levenberg-Marquardt on the log-factors with the Jacobian by ``jax.jacfwd``; the iterates."""
    f = jax.jit(res)
    jac = jax.jit(jax.jacfwd(res))
    theta = jnp.zeros(2 * n)
    start = time.perf_counter()
    r = f(theta, *data).block_until_ready()
    J = jac(theta, *data).block_until_ready()
    compiled = time.perf_counter() - start
    cost, lam, log = float(r @ r), 1e-3, [{"iteration": 0, "cost": float(r @ r), "seconds": 0.0, "theta": theta}]
    start = time.perf_counter()
    for it in range(1, max_iters + 1):
        if it > 1:
            J = jac(theta, *data).block_until_ready()
        JtJ, g = J.T @ J, J.T @ r
        while True:
            step = jnp.linalg.solve(JtJ + lam * jnp.diag(jnp.diag(JtJ)), -g)
            r_new = f(theta + step, *data)
            c_new = float(r_new @ r_new)
            if c_new < cost or lam > 1e8:
                break
            lam *= 10.0
        if c_new >= cost:
            break
        rel = (cost - c_new) / cost
        theta, r, cost, lam = theta + step, r_new, c_new, max(lam / 10.0, 1e-7)
        log.append({"iteration": it, "cost": cost, "seconds": time.perf_counter() - start, "theta": theta})
        say(f"MJX LM iteration {it}: cost {cost:.6g} ({time.perf_counter() - start:.1f} s)")
        if rel < 1e-3:  # at the noise floor: another Jacobian would buy nothing
            break
    return compiled, log


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="mjcf/robots/ur5e_twice.yaml")
    p.add_argument("--delay", type=int, default=2)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--duration", type=float, default=20.0, help="s of the excitation")
    p.add_argument("--max-iters", type=int, default=3, help="MJX's Levenberg-Marquardt iterations at most")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    set_xla_flags()  # before the first JAX computation
    jax.config.update("jax_enable_x64", True)
    enable_compilation_cache()
    model = load_model(args.robot, visual=False)
    ex = excite.excitation(model, duration=args.duration)
    nom = replay.Replay(model).nominal()
    rng = np.random.default_rng(args.seed)
    n = len(nom.stiffness)
    truth = nom.replace(
        stiffness=nom.stiffness * rng.uniform(0.7, 1.3, n), damping=nom.damping * rng.uniform(0.7, 1.3, n)
    )
    t, q, dq = replay.record(model, truth, ex.times, ex.commands, args.delay, timestep=0.0005,
                             integrator="implicitfast", noise_q=1e-5, noise_dq=5e-4, seed=args.seed)  # fmt: skip
    rec = bags.Recording(ex.joints, t, q, dq, ex.times, ex.commands)
    rows = {}

    def errors(stiffness, damping, rms):
        return {"stiffness_error_max_pct": float(100 * np.abs(stiffness / truth.stiffness - 1).max()),
                "damping_error_max_pct": float(100 * np.abs(damping / truth.damping - 1).max()),
                "rms_after_rad": [float(v) for v in rms]}  # fmt: skip

    start = time.perf_counter()
    cal, prob, *_ = calibrate(model, rec, delays=[args.delay], timestep=0.0005, progress=print)
    rows["toolbox"] = {"seconds": time.perf_counter() - start, "windows": cal.windows,
                       **errors(cal.fitted.stiffness, cal.fitted.damping, cal.rms_after)}  # fmt: skip
    print("toolbox", json.dumps(rows["toolbox"]), flush=True)

    rp = replay.Replay(model, timestep=0.0005)
    _, idx, *data = windows(rp, rec, args.delay, 0.5)
    res = mjx_residual(model, rp, idx)
    compiled, log = fit_mjx(res, data, n, args.max_iters, print)
    # each iterate's errors; the tracking error of the last, measured as the toolbox's (the position
    # stack's servo code on MuJoCo C)
    pd = prob.parameters(nom, ("stiffness", "damping"))
    rows["mjx"] = {"compile_and_first_jacobian_s": compiled, "windows": len(data[0]), "iterations": []}
    for entry in log:
        k = nom.stiffness * np.exp(np.asarray(entry["theta"][:n]))
        b = nom.damping * np.exp(np.asarray(entry["theta"][n:]))
        row = {key: v for key, v in entry.items() if key != "theta"} | errors(k, b, [])
        rows["mjx"]["iterations"].append(row)
        print("mjx", json.dumps(row), flush=True)
    for j, name in enumerate(prob.names):
        pd[f"{name} stiffness"].value[0] = k[j] / nom.stiffness[j]
        pd[f"{name} damping"].value[0] = b[j] / nom.damping[j]
    rows["mjx"]["seconds"] = compiled + log[-1]["seconds"]
    rows["mjx"] |= errors(k, b, prob.tracking(pd)[0])
    print("mjx", json.dumps({key: v for key, v in rows["mjx"].items() if key != "iterations"}), flush=True)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "calibrate_mjx.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
