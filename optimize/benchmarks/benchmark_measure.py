"""The measurements of ``jaxsync bench`` (``benchmarks.benchmark`` runs them and assembles the results).

Closed-loop MJX environment-steps per second; the same controller stepping
MuJoCo C; bare ``mj_step``; and, for the two gradient paths of ``PATHS`` side
by side (the tuner's implicit path, and the unrolled one kept as a reference),
one forward rollout against its gradient, cold and warm compile times of the
gradient and the peak memory of one tuning step, these two in child processes
(a fresh process, and for the cold compile an empty cache:
``jaxsync.optimize.benchmarks.benchmark_children``). The gradient is
the tuning cost's over the short task (``jaxsync.short_task``, batch 1); the
tuning step is ``jaxsync tune``'s (the full task, its batch).

The imports below start no JAX computation: a child process imports this
module and sets its XLA flags afterwards (XLA reads ``$XLA_FLAGS`` when JAX's
backend starts).
"""

from __future__ import annotations

import os
import platform
import time
from importlib.metadata import PackageNotFoundError, version

import jax
import jax.numpy as jnp
import jaxlib
import mujoco
import numpy as np

from jaxsync.control.gains import default_gains
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.optimize.tuning.loss import make_loss
from jaxsync.optimize.tuning.scenarios import model_overrides, sample_scenarios, training_base
from jaxsync.physics.model import load_model
from jaxsync.physics.sensing import sense
from jaxsync.physics.step import before_control, put_data
from jaxsync.runtime import xla as _xla
from jaxsync.sim.actuation import TORQUE, Stack
from jaxsync.sim.metrics import summarize
from jaxsync.sim.rollout import cpu_vmap_limit, make_rollout, rollout, steps_for
from jaxsync.sim.scenario import default_scenario

# The two gradient paths the benchmark sets side by side: "implicit" is what
# ``jaxsync tune`` runs (MJX's converged solve, the implicit adjoint, the
# exact full-horizon gradient); "unrolled" (three one-iteration Newton solves
# per step, differentiated through, the gradient truncated every 100 steps)
# is a reference to compare against.
PATHS = {
    "implicit": {
        "solver": "accurate",
        "truncate_every": None,
        "label": "converged solve, implicit adjoint, exact gradient",
    },
    "unrolled": {
        "solver": "unrolled",
        "truncate_every": 100,
        "label": "unrolled 1-iteration solves, truncated every 100 steps",
    },
}

# XLA's own default for the CPU emitters, which jaxsync turns off (jaxsync.runtime.xla):
# the benchmark measures the gradient's compile and the tuning step's memory
# with it too, beside jaxsync's setting
XLA_DEFAULT_EMITTERS = f"--{_xla.FUSION_EMITTERS}=true"


def _scenarios(base, n: int):
    """n copies of ``base`` with noise keys 0..n-1 (a batch with a leading axis)."""
    keys = np.stack([np.asarray(jax.random.key_data(jax.random.key(i)), dtype=np.uint32) for i in range(n)])
    tree = jax.tree_util.tree_map(lambda x: np.repeat(np.asarray(x)[None], n, axis=0), base)
    return tree._replace(noise_key=keys)


def _timeit(f, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t0)
    return best


def _on(source: str | None) -> str:
    return f" on {os.path.basename(source)}" if source else ""


def load(path: str, source: str | None = None, visual: bool = True):
    """``path``'s physics (``PATHS``) on ``source``: a robot file or an MJCF in
    jaxsync's convention, the paper model when None."""
    return load_model(source, solver=PATHS[path]["solver"], visual=visual)


# ----------------------------------------------------------------- measurements


def mjx_throughput(model, batch_sizes, duration: float, repeats: int, log) -> dict:
    """Closed-loop env-steps/s of jit(vmap(rollout -> metrics)) at each batch size.

    Batches above :func:`cpu_vmap_limit` run as one call of ``lax.map`` over
    vmapped slices of the limit (the whole batch in one compiled call, at most
    the limit in one vmap).
    """
    fn = make_rollout(model, "synchronous", duration)

    def one(g, s):
        return summarize(fn(g, s), s)

    ev = jax.jit(jax.vmap(one, in_axes=(None, 0)))
    limit = cpu_vmap_limit()
    g = default_gains(model)
    out, compile_s, how = {}, {}, {}
    for b in batch_sizes:
        s = jax.tree_util.tree_map(jnp.asarray, _scenarios(default_scenario(model), b))
        f, how[str(b)] = ev, f"vmap {b}"
        if limit and b > limit:
            f = jax.jit(lambda g, s: jax.lax.map(lambda s1: one(g, s1), s, batch_size=limit))
            how[str(b)] = f"lax.map over vmap {limit} (CPU LAPACK deadlock above {limit})"
        t0 = time.perf_counter()
        jax.block_until_ready(f(g, s))
        compile_s[str(b)] = time.perf_counter() - t0
        dt = _timeit(lambda s=s, f=f: jax.block_until_ready(f(g, s)), repeats)
        out[str(b)] = b * fn.n_steps / dt
        log(
            f"  MJX batch {b:>4}: {out[str(b)]:10.0f} env-steps/s ({dt:.2f} s for {b} x {fn.n_steps} steps; "
            f"first call {compile_s[str(b)]:.1f} s; {how[str(b)]})"
        )
    return {"rates": out, "first_call_s": compile_s, "steps": fn.n_steps, "how": how}


def mujoco_c_throughput(model, duration: float, log) -> dict:
    """The same jitted control law stepping MuJoCo C (``backend="mujoco"``), one environment.

    Each call re-jits its per-call control function (cached on disk after the
    first), so the steady rate is taken from the difference of a short and a
    long rollout; the raw rate of the long call is reported too.
    """
    g, s = default_gains(model), default_scenario(model)
    short = min(0.02, duration / 2)
    jax.block_until_ready(rollout(model, g, s, backend="mujoco", duration=short))  # compile, warm the cache
    t0 = time.perf_counter()
    jax.block_until_ready(rollout(model, g, s, backend="mujoco", duration=short))
    t_short = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(rollout(model, g, s, backend="mujoco", duration=duration))
    t_long = time.perf_counter() - t0
    n_short, n_long = steps_for(short, model), steps_for(duration, model)
    steady = (n_long - n_short) / max(t_long - t_short, 1e-9)
    raw = n_long / t_long
    log(
        f"  MuJoCo C + controller: {steady:10.0f} env-steps/s steady ({raw:.0f} including the per-call "
        f"set-up of {t_short:.2f} s)"
    )
    return {"rate": steady, "rate_including_setup": raw, "setup_s": t_short, "steps": n_long}


def bare_mj_step(model, n: int, log) -> float:
    m = model.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = model.keyframe_qpos("grasp")
    mujoco.mj_forward(m, d)
    for _ in range(50):
        mujoco.mj_step(m, d)
    t0 = time.perf_counter()
    for _ in range(n):
        mujoco.mj_step(m, d)
    rate = n / (time.perf_counter() - t0)
    log(f"  bare mj_step: {rate:10.0f} steps/s")
    return rate


def tuning_loss(
    path: str,
    task: str,
    batch: int,
    duration: float | None = None,
    source: str | None = None,
    visual: bool = True,
    stack: Stack = TORQUE,
):
    """The tuner's own loss on ``path``'s physics: ``(loss, args, n_steps)``.

    ``loss(theta, scenarios) -> (cost, terms)`` is ``optimize.loss.make_loss``
    with ``jaxsync tune``'s defaults except the task (``"short"``: the 2 s
    short task, or ``"full"``: the 4 s task), the batch and the path's solver
    and truncation; ``args`` are the default gains' parameters and a seeded
    batch of randomised scenarios. ``source``: the model (:func:`load`), its
    default gains and its object, as ``jaxsync tune --robot`` takes them.
    ``stack``: the arms' stack (its defaults and its one delay in every scenario).
    """
    p = PATHS[path]
    over = {"train_duration": duration} if (duration is not None and task == "short") else {}
    model = load(path, source, visual)
    over["scenario"] = model_overrides(model)
    over.update(actuation=stack.actuation, control_rate=stack.control_rate)
    cfg = TuneConfig(task=task, batch=batch, truncate_every=p["truncate_every"], **over)
    base, spec = default_gains(model, stack.actuation, cfg.problem.controller), cfg.problem.tuned
    loss = make_loss(model, base, cfg)
    scen_base, dur = training_base(cfg.training)
    scen = sample_scenarios(jax.random.key(0), batch, scen_base, delay=(stack.scenario_delay(),) * 2)
    return loss, (spec.init(base), scen), steps_for(dur, model)


def small_gradient(path: str = "implicit", source: str | None = None, visual: bool = True):
    """A small stand-in for ``--quick``: the pad position through one
    kinematics stage and the sensing (compiles in seconds, not minutes), on
    ``path``'s model. It does not reach the constraint solve, so the two paths
    do the same work here: ``--quick`` checks the benchmark runs, it measures
    nothing about the paths."""
    model = load(path, source, visual)
    mx, index = model.mjx_model, model.index
    d = put_data(model.mj_model, mujoco.MjData(model.mj_model))
    q0 = jnp.asarray(model.keyframe_qpos("grasp"))

    def f(q):
        v = jnp.sum(sense(mx, before_control(mx, d.replace(qpos=q)), index).right.pad_pos)
        return v, v

    return f, (q0,), 1


def gradient_functions(
    path: str,
    duration: float,
    small: bool = False,
    source: str | None = None,
    visual: bool = True,
    stack: Stack = TORQUE,
):
    """``(jit(forward), jit(value_and_grad), args, n_steps)`` of the tuning
    cost of one rollout of the short task (batch 1) on ``path``'s physics,
    ``source``'s model (:func:`load`) and ``stack``."""
    if small:
        loss, args, n = small_gradient(path, source, visual)
    else:
        loss, args, n = tuning_loss(path, "short", 1, duration, source, visual, stack)
    return jax.jit(lambda *a: loss(*a)[0]), jax.jit(jax.value_and_grad(loss, has_aux=True)), args, n


def forward_and_gradient(
    path: str, duration: float, repeats: int, log, small: bool = False, source: str | None = None, visual: bool = True
) -> dict:
    """Forward against value_and_grad of the same physics, alternated, best of ``repeats``."""
    fwd, grad, args, n_steps = gradient_functions(path, duration, small, source, visual)
    t0 = time.perf_counter()
    jax.block_until_ready(fwd(*args))
    t_fc = time.perf_counter() - t0
    t0 = time.perf_counter()
    (value, _), gr = jax.block_until_ready(grad(*args))
    t_gc = time.perf_counter() - t0
    # alternated, so that a change in the machine's load hits both alike; the
    # best of each (the medians are kept in the details)
    tf_all, tg_all = [], []
    for _ in range(repeats):
        tf_all.append(_timeit(lambda: jax.block_until_ready(fwd(*args)), 1))
        tg_all.append(_timeit(lambda: jax.block_until_ready(grad(*args)), 1))
    t_f, t_g = min(tf_all), min(tg_all)
    finite = bool(all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(gr)))
    log(
        f"  {path} ({PATHS[path]['label']}{'; small stand-in' if small else ''}{_on(source)}): forward {t_f:.3f} s, "
        f"value_and_grad {t_g:.3f} s over {n_steps} steps: ratio {t_g / t_f:.2f} (first calls "
        f"{t_fc:.1f} s and {t_gc:.1f} s; gradient finite: {finite})"
    )
    return {
        "path": path,
        "label": PATHS[path]["label"],
        "forward_s": t_f,
        "grad_s": t_g,
        "grad_over_forward": t_g / t_f,
        "steps": n_steps,
        "forward_first_call_s": t_fc,
        "grad_first_call_s": t_gc,
        "forward_median_s": float(np.median(tf_all)),
        "grad_median_s": float(np.median(tg_all)),
        "repeats": repeats,
        "grad_finite": finite,
        "cost_value": float(value),
    }


def ratio_of_ratios(times: dict, num: str = "robot", den: str = "paper") -> dict:
    """The robot's gradient/forward over the paper model's, from timings taken
    in rounds (``times[side][program]``: one time per round; sides ``num``
    and ``den``, by default ``"robot"``/``"paper"``, programs
    ``"forward"``/``"grad"``).

    ``per_round``: the ratio within each round, four calls a few seconds
    apart; ``per_round_median`` is the figure the target is judged on, with
    its quartiles. ``of_best``: the ratio of each program's best time, kept
    beside it. On this project's 2-core machine, the same files in three
    processes of 15 rounds gave per-round medians of 1.07-1.14 and ratios of
    the best times of 1.03-1.31: a forward call lasts 0.15-0.3 s, and one
    lucky call of one program moves a ratio of bests by a fifth."""
    t = {m: {k: np.asarray(v, float) for k, v in progs.items()} for m, progs in times.items()}
    n = {len(v) for progs in t.values() for v in progs.values()}
    if len(n) != 1 or 0 in n:
        raise ValueError(f"every program needs the same number of rounds (at least one), got {sorted(n)}")
    best = {m: float(p["grad"].min() / p["forward"].min()) for m, p in t.items()}
    per = (t[num]["grad"] / t[num]["forward"]) / (t[den]["grad"] / t[den]["forward"])
    q25, q50, q75 = np.percentile(per, [25, 50, 75])
    return {
        "of_best": best[num] / best[den],
        f"{num}_grad_over_forward": best[num],
        f"{den}_grad_over_forward": best[den],
        "per_round": per.tolist(),
        "per_round_median": float(q50),
        "per_round_quartiles": [float(q25), float(q75)],
    }


def paired_forward_and_gradient(
    duration: float, rounds: int, log, small: bool = False, source: str | None = None, visual: bool = True
) -> dict:
    """The robot's (``source``) and the paper model's forward rollout and
    gradient (the implicit path), timed in the same rounds of one process.

    Each round times all four programs, the robot's first in even rounds and
    the paper model's first in odd ones, so that a change in the machine's
    speed (this machine's call-to-call spread is larger than a 1.3x target's
    margin) reaches both models alike; timing the two models minutes apart,
    each best of a few calls, moved the ratio of ratios between 1.21 and 1.49
    on the same files. Returns each model's best and median times and
    :func:`ratio_of_ratios`."""
    sides = {"robot": {"source": source, "visual": visual}, "paper": {"source": None, "visual": visual}}
    names = {"robot": os.path.basename(source or "robot"), "paper": "paper"}
    times, rr, n_steps = _paired_rounds(duration, rounds, small, sides)
    models = _side_figures(times, rr, n_steps, rounds, log, names, "over the paper model's")
    return {"rounds": rounds, "steps": n_steps, "models": models, "ratio_of_ratios": rr, "times": times}


def _side_figures(times: dict, rr: dict, n_steps: int, rounds: int, log, names: dict, over: str) -> dict:
    """Each side's best and median times from :func:`_paired_rounds`, logged with the ratio."""
    figures = {
        m: {
            "forward_s": min(t["forward"]),
            "grad_s": min(t["grad"]),
            "grad_over_forward": min(t["grad"]) / min(t["forward"]),
            "forward_median_s": float(np.median(t["forward"])),
            "grad_median_s": float(np.median(t["grad"])),
        }
        for m, t in times.items()
    }
    for m, f in figures.items():
        log(
            f"  {names[m]}: forward {f['forward_s']:.3f} s, value_and_grad {f['grad_s']:.3f} s over {n_steps} "
            f"steps (best of {rounds} rounds): ratio {f['grad_over_forward']:.2f}"
        )
    q25, q75 = rr["per_round_quartiles"]
    log(
        f"  gradient/forward {over}: {rr['of_best']:.2f} of the best times; "
        f"round by round median {rr['per_round_median']:.2f} (quartiles {q25:.2f}-{q75:.2f})"
    )
    return figures


def _paired_rounds(duration: float, rounds: int, small: bool, sides: dict):
    """Forward and gradient of two sides (``{name: gradient_functions kwargs}``,
    numerator first), every program timed once per round, the sides in turn
    first: ``(times, ratio_of_ratios, n_steps)``."""
    progs = {}
    for name, kw in sides.items():
        fwd, grad, args, n_steps = gradient_functions("implicit", duration, small, **kw)
        jax.block_until_ready(fwd(*args))
        jax.block_until_ready(grad(*args))
        progs[name] = (fwd, grad, args)
    num, den = list(sides)
    times = {m: {"forward": [], "grad": []} for m in progs}
    for r in range(rounds):
        for m in (num, den) if r % 2 == 0 else (den, num):
            fwd, grad, args = progs[m]
            for kind, f in (("forward", fwd), ("grad", grad)):
                times[m][kind].append(_timeit(lambda f=f, args=args: jax.block_until_ready(f(*args)), 1))
    return times, ratio_of_ratios(times, num, den), n_steps


def paired_stacks(
    duration: float, rounds: int, log, stack: Stack, small: bool = False, source: str | None = None, visual: bool = True
) -> dict:
    """The tuner's gradient on ``stack`` (position-controlled arms) against
    the torque stack's, forward rollout and gradient timed in the same rounds
    of one process (as :func:`paired_forward_and_gradient`): the gradient's
    cost in forward rollouts on each stack, and their ratio."""
    sides = {
        "position": {"source": source, "visual": visual, "stack": stack},
        "torque": {"source": source, "visual": visual, "stack": TORQUE},
    }
    times, rr, n_steps = _paired_rounds(duration, rounds, small, sides)
    names = {"position": "position stack", "torque": "torque stack"}
    stacks = _side_figures(times, rr, n_steps, rounds, log, names, "position over torque")
    return {"rounds": rounds, "steps": n_steps, "stacks": stacks, "ratio_of_ratios": rr, "times": times}


def have_flatbuffers() -> bool:
    """Whether ``jax.export`` can serialise (the warm start with the traced function on disk)."""
    try:
        import flatbuffers  # noqa: F401  (inside: an optional dependency of jax.export)
    except ImportError:
        return False
    return True


# ----------------------------------------------------------------- machine


def machine() -> dict:
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        mjx_version = version("mujoco-mjx")
    except PackageNotFoundError:
        mjx_version = None
    mem = None
    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1024**3
    except (ValueError, OSError, AttributeError):
        pass
    return {
        "cpu_model": cpu,
        "cpu_cores": os.cpu_count(),
        "memory_gib": mem,
        "load_average_at_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "mujoco": mujoco.__version__,
        "mujoco_mjx": mjx_version,
        "numpy": np.__version__,
        "x64": bool(jax.config.jax_enable_x64),
        "compilation_cache": jax.config.jax_compilation_cache_dir,
    }
