"""The measurements of ``jaxsync bench`` (``jaxsync.optimize.benchmark`` runs them and assembles the results).

Closed-loop MJX environment-steps per second; the same controller stepping
MuJoCo C; bare ``mj_step``; and, for the two gradient paths of ``PATHS`` side
by side (the tuner's implicit path, and the unrolled one kept as a reference),
one forward rollout against its gradient, cold and warm compile times of the
gradient and the peak memory of one tuning step, these two in child processes
(a fresh process, and for the cold compile an empty cache). The gradient is
the tuning cost's over the short task (``jaxsync.short_task``, batch 1); the
tuning step is ``jaxsync tune``'s (the full task, its batch).

The child processes import this module and set their XLA flags afterwards
(:func:`child`): XLA reads ``$XLA_FLAGS`` when JAX's backend starts, and the
imports below start no JAX computation.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from importlib.metadata import PackageNotFoundError, version

import jax
import jax.numpy as jnp
import jaxlib
import mujoco
import numpy as np

from jaxsync.control.gains import default_gains
from jaxsync.optimize.config import TuneConfig
from jaxsync.optimize.cost import CostWeights
from jaxsync.optimize.loop import apply_update
from jaxsync.optimize.loss import make_loss
from jaxsync.optimize.params import TuneSpec
from jaxsync.optimize.scenarios import sample_scenarios, training_base
from jaxsync.physics.model import load_model
from jaxsync.physics.sensing import sense
from jaxsync.physics.step import before_control, put_data
from jaxsync.runtime import xla as _xla
from jaxsync.runtime.cache import enable_compilation_cache, traced_on_disk
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
    g = default_gains()
    out, compile_s, how = {}, {}, {}
    for b in batch_sizes:
        s = jax.tree_util.tree_map(jnp.asarray, _scenarios(default_scenario(), b))
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
    g, s = default_gains(), default_scenario()
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


def tuning_loss(path: str, task: str, batch: int, duration: float | None = None):
    """The tuner's own loss on ``path``'s physics: ``(loss, args, n_steps)``.

    ``loss(theta, scenarios) -> (cost, terms)`` is ``optimize.loss.make_loss``
    with ``jaxsync tune``'s defaults except the task (``"short"``: the 2 s
    short task, or ``"full"``: the 4 s task), the batch and the path's solver
    and truncation; ``args`` are the default gains' parameters and a seeded
    batch of randomised scenarios.
    """
    p = PATHS[path]
    over = {"train_duration": duration} if (duration is not None and task == "short") else {}
    cfg = TuneConfig(task=task, batch=batch, truncate_every=p["truncate_every"], **over)
    model = load_model(solver=p["solver"])
    base, spec = default_gains(), TuneSpec()
    loss = make_loss(model, spec, base, cfg, CostWeights())
    scen_base, dur = training_base(cfg)
    scen = sample_scenarios(jax.random.key(0), batch, scen_base)
    return loss, (spec.init(base), scen), steps_for(dur, model)


def small_gradient(path: str = "implicit"):
    """A small stand-in for ``--quick``: the pad position through one
    kinematics stage and the sensing (compiles in seconds, not minutes), on
    ``path``'s model. It does not reach the constraint solve, so the two paths
    do the same work here: ``--quick`` checks the benchmark runs, it measures
    nothing about the paths."""
    model = load_model(solver=PATHS[path]["solver"])
    mx, index = model.mjx_model, model.index
    d = put_data(model.mj_model, mujoco.MjData(model.mj_model))
    q0 = jnp.asarray(model.keyframe_qpos("grasp"))

    def f(q):
        v = jnp.sum(sense(mx, before_control(mx, d.replace(qpos=q)), index).right.pad_pos)
        return v, v

    return f, (q0,), 1


def gradient_functions(path: str, duration: float, small: bool = False):
    """``(jit(forward), jit(value_and_grad), args, n_steps)`` of the tuning
    cost of one rollout of the short task (batch 1) on ``path``'s physics."""
    loss, args, n = small_gradient(path) if small else tuning_loss(path, "short", 1, duration)
    return jax.jit(lambda *a: loss(*a)[0]), jax.jit(jax.value_and_grad(loss, has_aux=True)), args, n


def forward_and_gradient(path: str, duration: float, repeats: int, log, small: bool = False) -> dict:
    """Forward against value_and_grad of the same physics, alternated, best of ``repeats``."""
    fwd, grad, args, n_steps = gradient_functions(path, duration, small)
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
        f"  {path} ({PATHS[path]['label']}{'; small stand-in' if small else ''}): forward {t_f:.3f} s, "
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


def have_flatbuffers() -> bool:
    """Whether ``jax.export`` can serialise (the warm start with the traced function on disk)."""
    try:
        import flatbuffers  # noqa: F401  (inside: an optional dependency of jax.export)
    except ImportError:
        return False
    return True


# ----------------------------------------------------------------- child processes


def _maxrss_gib() -> float:
    """Peak resident memory of this process. On Linux from ``VmHWM``: the
    ``ru_maxrss`` of a process started by fork and exec keeps the parent's
    peak (measured: a child of the 1.7 GiB bench process reported 1.74 GiB
    before it had done anything)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024**2  # kB
    except OSError:
        pass
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return kib * (1 if sys.platform != "darwin" else 1 / 1024) / 1024**2


def _child_compile(cfg: dict) -> dict:
    """Trace and XLA-compile the gradient of ``cfg["path"]`` (as the benchmark times it)."""
    t0 = time.perf_counter()
    _, grad, args, _ = gradient_functions(cfg["path"], cfg["duration"], cfg.get("small", False))
    if cfg.get("exported"):  # what the CLI does: the traced function from disk (jax.export)
        grad = traced_on_disk(grad, args, f"bench.gradient.{cfg['path']}.{cfg['duration']}.{cfg.get('small')}")
    t1 = time.perf_counter()
    lowered = grad.lower(*args)
    t2 = time.perf_counter()
    lowered.compile()
    t3 = time.perf_counter()
    return {"setup_s": t1 - t0, "trace_s": t2 - t1, "xla_compile_s": t3 - t2, "total_s": t3 - t1}


def _child_tune_step(cfg: dict) -> dict:
    """One tuning step as ``jaxsync tune`` takes it on ``cfg["path"]``: the
    gradient of the tuning loss over a batch of randomised scenarios of the
    task, then one optax update; the process's peak memory."""
    rss0 = _maxrss_gib()
    if cfg.get("small"):
        loss, args, _ = small_gradient(cfg["path"])
    else:
        loss, args, _ = tuning_loss(cfg["path"], cfg["task"], cfg["batch"])
    opt = TuneConfig().optimizer_transform()
    value_and_grad = jax.jit(jax.value_and_grad(loss, has_aux=True))
    theta = args[0]
    state = opt.init(theta)
    t0 = time.perf_counter()
    compiled = value_and_grad.lower(*args).compile()
    t_compile = time.perf_counter() - t0
    rss_compiled = _maxrss_gib()
    mem = compiled.memory_analysis()
    t0 = time.perf_counter()
    (value, _), grad = jax.block_until_ready(compiled(*args))
    u = jax.block_until_ready(apply_update(opt, theta, state, value, grad))
    t_step = time.perf_counter() - t0
    return {
        "peak_rss_gib": _maxrss_gib(),
        "peak_rss_after_compile_gib": rss_compiled,
        "rss_before_gib": rss0,
        "xla_temp_gib": (mem.temp_size_in_bytes / 1024**3) if mem is not None else None,
        "compile_s": t_compile,
        "step_s": t_step,
        "loss": float(value),
        "update_finite": bool(u.finite),
    }


def child(mode: str, cfg: dict) -> dict:
    """Run in a fresh process: ``compile`` (trace + XLA-compile the gradient) or ``tune_step``."""
    # before the first JAX computation, which starts the backend and reads $XLA_FLAGS
    _xla.set_xla_flags()
    jax.config.update("jax_enable_x64", True)
    enable_compilation_cache()
    if mode == "compile":
        return _child_compile(cfg)
    if mode == "tune_step":
        return _child_tune_step(cfg)
    raise ValueError(mode)


def _run_child(mode: str, cfg: dict, cache_dir: str | None, xla_flags: str | None = None) -> dict:
    env = dict(os.environ)
    env["JAXSYNC_CACHE_DIR"] = cache_dir or "off"
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    code = (
        "import json, sys; from jaxsync.optimize.benchmark_measure import child; "
        "print('JAXSYNC_BENCH ' + json.dumps(child(sys.argv[1], json.loads(sys.argv[2]))))"
    )
    # cwd away from any source checkout: ``python -c`` puts the cwd first on sys.path
    proc = subprocess.run(
        [sys.executable, "-c", code, mode, json.dumps(cfg)],
        capture_output=True,
        text=True,
        env=env,
        timeout=3600,
        cwd=tempfile.gettempdir(),
    )
    for line in proc.stdout.splitlines()[::-1]:
        if line.startswith("JAXSYNC_BENCH "):
            return json.loads(line[len("JAXSYNC_BENCH ") :])
    raise RuntimeError(f"benchmark child '{mode}' failed (exit {proc.returncode}): {proc.stderr[-2000:]}")


def compile_times(path: str, duration: float, small: bool, log, exported: bool = True) -> dict:
    """Cold: a fresh process and an empty persistent cache. Warm: a second fresh
    process on the same cache (what a user's second run sees). With the
    ``flatbuffers`` package (and ``exported``), also warm with the traced
    function kept on disk (``jax.export``), which skips the tracing the
    persistent cache cannot save: what ``jaxsync tune`` does."""
    cfg = {"path": path, "duration": duration, "small": small}
    what = "small stand-in (--quick)" if small else f"value_and_grad of the tuning cost, {duration:g} s rollout"
    out = {"path": path, "function": what}
    with tempfile.TemporaryDirectory(prefix="jaxsync-bench-cache-") as cache:
        out["cold"] = cold = _run_child("compile", cfg, cache)
        out["warm"] = warm = _run_child("compile", cfg, cache)
        if exported and have_flatbuffers():
            exp = {**cfg, "exported": True}
            _run_child("compile", exp, cache)  # trace, export, compile the wrapper
            out["warm_exported"] = _run_child("compile", exp, cache)
    log(
        f"  {path}: gradient compile cold {cold['total_s']:.1f} s (trace {cold['trace_s']:.1f} + XLA "
        f"{cold['xla_compile_s']:.1f}), warm {warm['total_s']:.1f} s (trace {warm['trace_s']:.1f} + "
        f"cache {warm['xla_compile_s']:.1f})" + (" [small stand-in]" if small else "")
    )
    if "warm_exported" in out:
        log(f"  {path}: warm with the traced function on disk (jax.export): {out['warm_exported']['total_s']:.1f} s")
    return out


def cold_compile_with_xla_flags(path: str, duration: float, xla_flags: str, log) -> dict:
    """The cold compile of ``path``'s gradient (fresh process, empty cache) under ``xla_flags``."""
    cfg = {"path": path, "duration": duration, "small": False}
    with tempfile.TemporaryDirectory(prefix="jaxsync-bench-cache-") as cache:
        r = _run_child("compile", cfg, cache, xla_flags=xla_flags)
    log(
        f"  {path} with {xla_flags}: gradient compile cold {r['total_s']:.1f} s "
        f"(trace {r['trace_s']:.1f} + XLA {r['xla_compile_s']:.1f})"
    )
    return r


def warm_compile_s(comp: dict) -> float:
    """The warm compile time as ``jaxsync tune`` sees it (traced on disk where measured)."""
    return (comp["warm_exported"] if "warm_exported" in comp else comp["warm"])["total_s"]


def tune_step_memory(
    path: str, batch: int, task: str, small: bool, log, warm: bool = True, xla_flags: str | None = None
) -> dict:
    """Peak memory of a fresh process taking one tuning step: cold (an empty
    persistent cache, so the process compiles the step: a first ``jaxsync
    tune``) and, with ``warm``, again on the filled cache (a later run).
    ``xla_flags`` replaces the children's ``$XLA_FLAGS``."""
    cfg = {"path": path, "batch": batch, "task": task, "small": small}
    what = "small stand-in" if small else f"batch {batch}, {task} task"
    what += f", {xla_flags}" if xla_flags is not None else ""
    out = {}
    with tempfile.TemporaryDirectory(prefix="jaxsync-bench-cache-") as cache:
        for kind in ("cold", "warm") if warm else ("cold",):
            out[kind] = r = _run_child("tune_step", cfg, cache, xla_flags=xla_flags)
            log(
                f"  {path}: tuning step ({what}), {kind} cache: peak RSS {r['peak_rss_gib']:.2f} GiB "
                f"(after compiling {r['peak_rss_after_compile_gib']:.2f} GiB; XLA temporaries "
                f"{r['xla_temp_gib'] or float('nan'):.3f} GiB), compile {r['compile_s']:.1f} s, "
                f"step {r['step_s']:.1f} s"
            )
    out["peak_rss_gib"] = max(r["peak_rss_gib"] for r in out.values())
    return out


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
