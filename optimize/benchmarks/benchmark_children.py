"""The measurements of ``jaxsync bench`` that run in fresh processes: the
cold and warm compile of the gradient and the peak memory of one tuning step.

:func:`child` runs in the child (started by :func:`_run_child` with
``python -c``); it sets the XLA flags before the first JAX computation: XLA
reads ``$XLA_FLAGS`` when JAX's backend starts, and no import here starts one.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import jax

from jaxsync.optimize.benchmarks.benchmark_measure import (
    _on,
    gradient_functions,
    have_flatbuffers,
    small_gradient,
    tuning_loss,
)
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.optimize.tuning.loop import apply_update
from jaxsync.runtime import xla as _xla
from jaxsync.runtime.cache import enable_compilation_cache, traced_on_disk

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
    source, visual = cfg.get("source"), cfg.get("visual", True)
    _, grad, args, _ = gradient_functions(cfg["path"], cfg["duration"], cfg.get("small", False), source, visual)
    if cfg.get("exported"):  # what the CLI does: the traced function from disk (jax.export)
        name = f"bench.gradient.{cfg['path']}.{cfg['duration']}.{cfg.get('small')}.{source}.{visual}"
        grad = traced_on_disk(grad, args, name)
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
    source, visual = cfg.get("source"), cfg.get("visual", True)
    if cfg.get("small"):
        loss, args, _ = small_gradient(cfg["path"], source, visual)
    else:
        loss, args, _ = tuning_loss(cfg["path"], cfg["task"], cfg["batch"], None, source, visual)
    opt = TuneConfig(method="adam").optimizer_transform()
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
        "import json, sys; from jaxsync.optimize.benchmarks.benchmark_children import child; "
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


def compile_times(
    path: str,
    duration: float,
    small: bool,
    log,
    exported: bool = True,
    source: str | None = None,
    visual: bool = True,
    warm: bool = True,
) -> dict:
    """Cold: a fresh process and an empty persistent cache. Warm: a second fresh
    process on the same cache (what a user's second run sees). With the
    ``flatbuffers`` package (and ``exported``), also warm with the traced
    function kept on disk (``jax.export``), which skips the tracing the
    persistent cache cannot save: what ``jaxsync tune`` does. ``source``: the
    model (:func:`load`); ``warm`` False: the cold compile only."""
    cfg = {"path": path, "duration": duration, "small": small, "source": source, "visual": visual}
    what = "small stand-in (--quick)" if small else f"value_and_grad of the tuning cost, {duration:g} s rollout"
    out = {"path": path, "function": what}
    with tempfile.TemporaryDirectory(prefix="jaxsync-bench-cache-") as cache:
        out["cold"] = cold = _run_child("compile", cfg, cache)
        if not warm:
            log(
                f"  {path}{_on(source)}: gradient compile cold {cold['total_s']:.1f} s (trace {cold['trace_s']:.1f} "
                f"+ XLA {cold['xla_compile_s']:.1f})" + (" [small stand-in]" if small else "")
            )
            return out
        out["warm"] = warm = _run_child("compile", cfg, cache)
        if exported and have_flatbuffers():
            exp = {**cfg, "exported": True}
            _run_child("compile", exp, cache)  # trace, export, compile the wrapper
            out["warm_exported"] = _run_child("compile", exp, cache)
    log(
        f"  {path}{_on(source)}: gradient compile cold {cold['total_s']:.1f} s (trace {cold['trace_s']:.1f} + XLA "
        f"{cold['xla_compile_s']:.1f}), warm {warm['total_s']:.1f} s (trace {warm['trace_s']:.1f} + "
        f"cache {warm['xla_compile_s']:.1f})" + (" [small stand-in]" if small else "")
    )
    if "warm_exported" in out:
        log(f"  {path}: warm with the traced function on disk (jax.export): {out['warm_exported']['total_s']:.1f} s")
    return out


def cold_compile_with_xla_flags(
    path: str, duration: float, xla_flags: str, log, source: str | None = None, visual: bool = True
) -> dict:
    """The cold compile of ``path``'s gradient (fresh process, empty cache) under ``xla_flags``."""
    cfg = {"path": path, "duration": duration, "small": False, "source": source, "visual": visual}
    with tempfile.TemporaryDirectory(prefix="jaxsync-bench-cache-") as cache:
        r = _run_child("compile", cfg, cache, xla_flags=xla_flags)
    log(
        f"  {path}{_on(source)} with {xla_flags}: gradient compile cold {r['total_s']:.1f} s "
        f"(trace {r['trace_s']:.1f} + XLA {r['xla_compile_s']:.1f})"
    )
    return r


def warm_compile_s(comp: dict) -> float:
    """The warm compile time as ``jaxsync tune`` sees it (traced on disk where measured)."""
    return (comp["warm_exported"] if "warm_exported" in comp else comp["warm"])["total_s"]


def tune_step_memory(
    path: str,
    batch: int,
    task: str,
    small: bool,
    log,
    warm: bool = True,
    xla_flags: str | None = None,
    source: str | None = None,
    visual: bool = True,
) -> dict:
    """Peak memory of a fresh process taking one tuning step: cold (an empty
    persistent cache, so the process compiles the step: a first ``jaxsync
    tune``) and, with ``warm``, again on the filled cache (a later run).
    ``xla_flags`` replaces the children's ``$XLA_FLAGS``."""
    cfg = {"path": path, "batch": batch, "task": task, "small": small, "source": source, "visual": visual}
    what = "small stand-in" if small else f"batch {batch}, {task} task"
    what += f", {xla_flags}" if xla_flags is not None else ""
    out = {}
    with tempfile.TemporaryDirectory(prefix="jaxsync-bench-cache-") as cache:
        for kind in ("cold", "warm") if warm else ("cold",):
            out[kind] = r = _run_child("tune_step", cfg, cache, xla_flags=xla_flags)
            log(
                f"  {path}{_on(source)}: tuning step ({what}), {kind} cache: peak RSS {r['peak_rss_gib']:.2f} GiB "
                f"(after compiling {r['peak_rss_after_compile_gib']:.2f} GiB; XLA temporaries "
                f"{r['xla_temp_gib'] or float('nan'):.3f} GiB), compile {r['compile_s']:.1f} s, "
                f"step {r['step_s']:.1f} s"
            )
    out["peak_rss_gib"] = max(r["peak_rss_gib"] for r in out.values())
    return out
