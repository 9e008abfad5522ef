"""The measurements of ``jaxsync bench`` (``jaxsync.cli.bench`` runs them and reports).

Closed-loop MJX environment-steps per second; the same controller stepping
MuJoCo C; bare ``mj_step``; one forward rollout against its gradient; cold and
warm compile times of the gradient and the peak memory of one tuning step,
these two in child processes (a fresh process, and for the cold compile an
empty cache). The gradient's horizon is the short task (``jaxsync.short_task``).
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

import numpy as np


def _scenarios(base, n: int):
    """n copies of ``base`` with noise keys 0..n-1 (a batch with a leading axis)."""
    import jax

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
    import jax

    from jaxsync._gains import default_gains
    from jaxsync._metrics import summarize
    from jaxsync._rollout import make_rollout
    from jaxsync._scenario import default_scenario

    fn = make_rollout(model, "synchronous", duration)

    def one(g, s):
        return summarize(fn(g, s), s)

    ev = jax.jit(jax.vmap(one, in_axes=(None, 0)))
    from jaxsync._rollout import cpu_vmap_limit

    limit = cpu_vmap_limit()
    g = default_gains()
    out, compile_s, how = {}, {}, {}
    for b in batch_sizes:
        s = jax.tree_util.tree_map(jax.numpy.asarray, _scenarios(default_scenario(), b))
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
    import jax

    from jaxsync._gains import default_gains
    from jaxsync._rollout import rollout, steps_for
    from jaxsync._scenario import default_scenario

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
    import mujoco

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


def gradient_functions(duration: float, remat: bool = True):
    """jit(cost) and jit(value_and_grad(cost)), cost = the rms resultant of one
    rollout of the short task on the differentiable solver setting."""
    import jax

    from jaxsync._metrics import summarize
    from jaxsync._model import load_model
    from jaxsync._rollout import make_rollout

    fn = make_rollout(load_model(solver="unrolled"), "synchronous", duration, remat=remat)

    def cost(g, s):
        return summarize(fn(g, s), s).rms_resultant_N

    return jax.jit(cost), jax.jit(jax.value_and_grad(cost)), fn.n_steps


def forward_and_gradient(duration: float, repeats: int, log) -> dict:
    import jax

    from jaxsync._gains import default_gains
    from jaxsync._scenario import short_task

    fwd, grad, n_steps = gradient_functions(duration)
    g, s = default_gains(), short_task()
    t0 = time.perf_counter()
    jax.block_until_ready(fwd(g, s))
    t_fc = time.perf_counter() - t0
    t0 = time.perf_counter()
    value, gr = jax.block_until_ready(grad(g, s))
    t_gc = time.perf_counter() - t0
    # alternated, so that a change in the machine's load hits both alike; the
    # best of each (the medians are kept in the details)
    tf_all, tg_all = [], []
    for _ in range(repeats):
        tf_all.append(_timeit(lambda: jax.block_until_ready(fwd(g, s)), 1))
        tg_all.append(_timeit(lambda: jax.block_until_ready(grad(g, s)), 1))
    t_f, t_g = min(tf_all), min(tg_all)
    finite = bool(all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(gr)))
    log(
        f"  forward {t_f:.3f} s, value_and_grad {t_g:.3f} s over {n_steps} steps: ratio {t_g / t_f:.2f} "
        f"(gradient finite: {finite})"
    )
    return {
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


def small_gradient():
    """A small stand-in for ``--quick``: the gradient of the pad position through
    one kinematics stage and the sensing (compiles in seconds, not minutes)."""
    import jax
    import jax.numpy as jnp
    import mujoco

    from jaxsync._model import load_model
    from jaxsync._physics import before_control, put_data
    from jaxsync._sensing import sense

    model = load_model(solver="unrolled")
    mx, index = model.mjx_model, model.index
    d = put_data(model.mj_model, mujoco.MjData(model.mj_model))
    q0 = jnp.asarray(model.keyframe_qpos("grasp"))

    def f(q):
        return jnp.sum(sense(mx, before_control(mx, d.replace(qpos=q)), index).right.pad_pos)

    return jax.jit(jax.grad(f)), (q0,)


def _have_flatbuffers() -> bool:
    try:
        import flatbuffers  # noqa: F401
    except ImportError:
        return False
    return True


# ----------------------------------------------------------------- child processes


def _child_setup():
    import jax

    from jaxsync._cache import enable_compilation_cache

    jax.config.update("jax_enable_x64", True)
    return enable_compilation_cache()


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


def child(mode: str, cfg: dict) -> dict:
    """Run in a fresh process: ``compile`` (trace + XLA-compile the gradient) or ``tune_step``."""
    _child_setup()
    import jax

    from jaxsync._gains import default_gains
    from jaxsync._scenario import short_task

    if mode == "compile":
        t0 = time.perf_counter()
        if cfg.get("small"):
            grad, args = small_gradient()
        else:
            grad = gradient_functions(cfg["duration"])[1]
            args = (default_gains(), short_task())
        if cfg.get("exported"):  # what the CLI does: the traced function from disk (jax.export)
            from jaxsync._cache import traced_on_disk

            grad = traced_on_disk(grad, args, "bench.gradient")
        t1 = time.perf_counter()
        lowered = grad.lower(*args)
        t2 = time.perf_counter()
        lowered.compile()
        t3 = time.perf_counter()
        return {"setup_s": t1 - t0, "trace_s": t2 - t1, "xla_compile_s": t3 - t2, "total_s": t3 - t1}
    if mode == "tune_step":
        import optax

        from jaxsync._metrics import summarize
        from jaxsync._model import load_model
        from jaxsync._rollout import make_rollout
        from jaxsync.optimize.loop import apply_update

        rss0 = _maxrss_gib()
        fn = make_rollout(load_model(solver="unrolled"), "synchronous", cfg["duration"], remat=True)
        opt = optax.adam(1e-3)

        def loss(g, s):
            return jax.vmap(lambda s1: summarize(fn(g, s1), s1).rms_resultant_N)(s).mean()

        @jax.jit
        def step(g, state, s):
            value, grad = jax.value_and_grad(loss)(g, s)
            u = apply_update(opt, g, state, value, grad)
            return u.params, u.opt_state, value

        g = default_gains()
        state = opt.init(g)
        s = jax.tree_util.tree_map(jax.numpy.asarray, _scenarios(short_task(), cfg["batch"]))
        t0 = time.perf_counter()
        compiled = step.lower(g, state, s).compile()
        t_compile = time.perf_counter() - t0
        rss_compiled = _maxrss_gib()
        mem = compiled.memory_analysis()
        t0 = time.perf_counter()
        g2, state, value = jax.block_until_ready(compiled(g, state, s))
        t_step = time.perf_counter() - t0
        return {
            "peak_rss_gib": _maxrss_gib(),
            "peak_rss_after_compile_gib": rss_compiled,
            "rss_before_gib": rss0,
            "xla_temp_gib": (mem.temp_size_in_bytes / 1024**3) if mem is not None else None,
            "compile_s": t_compile,
            "step_s": t_step,
            "loss": float(value),
        }
    raise ValueError(mode)


def _run_child(mode: str, cfg: dict, cache_dir: str | None) -> dict:
    env = dict(os.environ)
    env["JAXSYNC_CACHE_DIR"] = cache_dir or "off"
    code = (
        "import json, sys; from jaxsync.cli._bench_measure import child; "
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


def compile_times(duration: float, small: bool, log) -> dict:
    """Cold: a fresh process and an empty persistent cache. Warm: a second fresh
    process on the same cache (what a user's second run sees). With the
    ``flatbuffers`` package, also warm with the traced function kept on disk
    (``jax.export``), which skips the tracing the persistent cache cannot save."""
    cfg = {"duration": duration, "small": small}
    out = {"function": "small stand-in (--quick)" if small else f"value_and_grad of a {duration:g} s rollout"}
    with tempfile.TemporaryDirectory(prefix="jaxsync-bench-cache-") as cache:
        out["cold"] = cold = _run_child("compile", cfg, cache)
        out["warm"] = warm = _run_child("compile", cfg, cache)
        if _have_flatbuffers():
            exported = {**cfg, "exported": True}
            _run_child("compile", exported, cache)  # trace, export, compile the wrapper
            out["warm_exported"] = _run_child("compile", exported, cache)
    log(
        f"  gradient compile cold {cold['total_s']:.1f} s (trace {cold['trace_s']:.1f} + XLA "
        f"{cold['xla_compile_s']:.1f}), warm {warm['total_s']:.1f} s (trace {warm['trace_s']:.1f} + "
        f"cache {warm['xla_compile_s']:.1f})" + (" [small stand-in]" if small else "")
    )
    if "warm_exported" in out:
        log(f"  warm with the traced function on disk (jax.export): {out['warm_exported']['total_s']:.1f} s")
    return out


def tune_step_memory(batch: int, duration: float, cache_dir: str | None, log) -> dict:
    r = _run_child("tune_step", {"batch": batch, "duration": duration}, cache_dir)
    log(
        f"  tuning step (batch {batch}, {duration:g} s): peak RSS {r['peak_rss_gib']:.2f} GiB "
        f"(after compiling {r['peak_rss_after_compile_gib']:.2f} GiB; XLA temporaries "
        f"{r['xla_temp_gib'] or float('nan'):.3f} GiB), step {r['step_s']:.1f} s"
    )
    return r


# ----------------------------------------------------------------- machine


def machine() -> dict:
    import jax
    import jaxlib
    import mujoco

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
        from importlib.metadata import version

        mjx_version = version("mujoco-mjx")
    except Exception:  # noqa: BLE001
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
