"""Batched parameter studies: ``jaxsync sweep`` (docs/sweep.md).

The study in four rooms: the parameter grammar (``sweep_spec``), the plan
(``sweep_plan``), the sharded evaluator (``sweep_eval``), the chunk store
(``sweep_store``) and the report (``sweep_report``); :func:`run` ties them
together. The names a user needs are re-exported here.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time

import jax
import numpy as np
from tqdm import tqdm

from jaxsync._errors import ConfigError
from jaxsync.io import results as _results
from jaxsync.optimize.studies.sweep_eval import (
    DEFAULT_BUDGET_GIB,
    DEFAULT_CHUNK_PER_DEVICE,
    GIB,
    choose_chunk,
    evaluator,
    gather,
    to_device,
)
from jaxsync.optimize.studies.sweep_plan import Plan, make_plan
from jaxsync.optimize.studies.sweep_report import DEFAULT_PLOT_METRICS, plot, summarize_sweep, write_csv
from jaxsync.optimize.studies.sweep_spec import (
    Param,
    Target,
    build_batch,
    known_names,
    make_points,
    parse_param,
    resolve_name,
)
from jaxsync.optimize.studies.sweep_store import load_chunk, prepare_out, read_plan, save_chunk
from jaxsync.runtime import distributed as _distributed
from jaxsync.runtime import interrupt as _interrupt
from jaxsync.sim import metrics as _metrics

__all__ = [
    "DEFAULT_BUDGET_GIB",
    "DEFAULT_CHUNK_PER_DEVICE",
    "DEFAULT_PLOT_METRICS",
    "Param",
    "Plan",
    "Target",
    "build_batch",
    "choose_chunk",
    "known_names",
    "make_plan",
    "make_points",
    "parse_param",
    "resolve_name",
    "run",
]


def _check(chunk, budget_gib, plot_metrics, n_dev) -> None:
    if chunk is not None and chunk < 1:
        raise ConfigError(f"--chunk must be a positive number of points, got {chunk}")
    if not budget_gib > 0:
        raise ConfigError(f"--memory-budget-gib must be positive, got {budget_gib}")
    for k in plot_metrics:
        if k not in _metrics.Metrics._fields:
            raise ConfigError(f"--plot-metric {k!r} is not a metric; known: {list(_metrics.Metrics._fields)}")
    if chunk is not None and chunk % n_dev:
        raise ConfigError(f"--chunk {chunk} must be a multiple of the {n_dev} devices the sweep is sharded over")


def _bounds(i: int, c: int, n: int) -> tuple[int, int]:
    return i * c, min(n, (i + 1) * c)


def _read_back(out: str, stored: dict | None, n: int, n_dev: int, chunk, main_proc: bool, log):
    """(the stored chunk size or None, {chunk index: metrics}) of the chunks already on disk
    (read by process 0 only: it alone assembles the results)."""
    c_stored = int(stored["chunk"]) if stored and stored.get("n_devices") == n_dev else None
    results: dict[int, dict] = {}
    if c_stored and main_proc:
        if chunk is not None and chunk != c_stored:
            log(f"resuming with the stored chunk size {c_stored} (not --chunk {chunk})")
        for i in range(-(-n // c_stored)):
            got = load_chunk(out, i, *_bounds(i, c_stored, n), _metrics.Metrics._fields)
            if got is not None:
                results[i] = got
    elif stored and main_proc:  # another device count: the stored chunks do not apply
        shutil.rmtree(os.path.join(out, "chunks"), ignore_errors=True)
        os.makedirs(os.path.join(out, "chunks"), exist_ok=True)
    return c_stored, results


def _compile(plan: Plan, c_stored, chunk, budget_gib: float, devices, log):
    """(chunk size, compiled chunk function, bytes per device, seconds); the stored size must still fit."""
    t0 = time.perf_counter()
    kw = dict(budget_gib=budget_gib, n_devices=len(devices), platform=devices[0].platform, log=log)
    c, compiled, used = choose_chunk(plan, chunk=c_stored or chunk, **kw)
    if c_stored and c != c_stored:
        raise ConfigError(
            f"the stored chunk size {c_stored} no longer fits --memory-budget-gib {budget_gib:g}; pass --restart"
        )
    return c, compiled, used, time.perf_counter() - t0


def _log_computed(out: str, i: int, process: int) -> None:
    """One line per chunk this process computed and saved (``chunks/computed_pK.jsonl``):
    what a resumed or multi-process run did, chunk by chunk."""
    with open(os.path.join(out, "chunks", f"computed_p{process}.jsonl"), "a") as f:
        f.write(json.dumps({"chunk": i, "process": process, "time": time.time()}) + "\n")


def _evaluate(plan: Plan, out: str, todo, c: int, compiled, n_dev: int, results: dict, bar, process: int):
    """Evaluate the chunks in ``todo`` into ``results`` and on disk; returns how many were computed."""
    n = len(plan.points)
    computed = 0
    for i in todo:
        start, stop = _bounds(i, c, n)
        idx = np.minimum(np.arange(start, start + c), stop - 1)  # pad the last chunk with its last point
        g, s = build_batch(plan.params, plan.points[idx], plan.base_gains, plan.base_scenario)
        m = gather(compiled(to_device(g, n_dev), to_device(s, n_dev)))
        got = {k: v[: stop - start] for k, v in _metrics.to_arrays(m).items()}
        save_chunk(out, i, start, stop, got)
        _log_computed(out, i, process)
        results[i] = got
        computed += 1
        if bar is not None:
            bar.update(stop - start)
        _interrupt.check()  # a safe point: every chunk so far is on disk
    return computed


def _progress_bar(progress: bool, total: int, initial: int, nproc: int):
    if not progress:
        return None

    desc = "sweep" if nproc == 1 else f"sweep, process 0 of {nproc}"
    return tqdm(total=total, initial=initial, unit="pt", desc=desc, file=sys.stderr, dynamic_ncols=True)


@_interrupt.deferred()  # Ctrl-C stops between chunks, those finished kept
def run(
    plan: Plan,
    out: str,
    *,
    chunk: int | None = None,
    budget_gib: float = DEFAULT_BUDGET_GIB,
    restart: bool = False,
    resume: bool = False,
    progress: bool = True,
    max_chunks: int | None = None,
    plot_metrics=DEFAULT_PLOT_METRICS,
    log=lambda m: print(m, file=sys.stderr, flush=True),
) -> dict:
    """Evaluate the plan into ``out``; returns summary.json's content (``complete`` False
    when ``max_chunks`` stopped it early). A sweep already in ``out`` is
    continued with ``resume`` (the same plan's finished chunks are read back),
    discarded with ``restart``, and an error with neither.

    In a multi-process run (``jaxsync.runtime.distributed.initialize``; ``out`` on a
    file system every process sees) process 0 checks the folder and decides
    which chunks are left; process k computes every P-th of them on its own
    devices and writes each as it finishes; process 0 then assembles
    ``results.csv``, the summary and the plots. A chunk on disk is never
    computed again: after a lost process, ``resume`` computes only the missing
    ones.

    Example:
      >>> plan = make_plan(["k_rk=-0.5:0.5:3", "object_mass=0.5,0.7"], duration=4.0)
      >>> summary = run(plan, "results/sweep", progress=False)  # doctest: +SKIP
      >>> summary["best_ok_point"]["settled_peak_resultant_N"]  # doctest: +SKIP
    """
    _check(chunk, budget_gib, plot_metrics, len(jax.local_devices()))  # the options, before any folder
    if jax.process_index() != 0:  # process 0 holds the folder for the whole run
        return _run(plan, out, chunk, budget_gib, restart, resume, progress, max_chunks, plot_metrics, log)
    _results.ensure_writable_dir(out)
    with _results.run_lock(out, "sweep", log=log):
        return _run(plan, out, chunk, budget_gib, restart, resume, progress, max_chunks, plot_metrics, log)


def _run(plan, out, chunk, budget_gib, restart, resume, progress, max_chunks, plot_metrics, log) -> dict:
    devices = jax.local_devices()
    n_dev = len(devices)
    t_start = time.perf_counter()
    nproc, me = jax.process_count(), jax.process_index()
    main_proc = me == 0
    log = log if main_proc else (lambda m: None)
    stored = prepare_out(out, plan, restart, resume) if main_proc else None
    if nproc > 1:  # every process reads the same folder (a shared --out)
        _distributed.barrier("sweep: output folder ready")
        if not main_proc:
            stored = read_plan(out, plan)
    n = len(plan.points)
    c_stored, results = _read_back(out, stored, n, n_dev, chunk, main_proc, log)
    loaded = len(results)
    need = _distributed.share("sweep: compile", c_stored is None or len(results) < -(-n // c_stored))
    compile_s, used, compiled, c = 0.0, None, None, c_stored
    if need:
        c, compiled, used, compile_s = _compile(plan, c_stored, chunk, budget_gib, devices, log)
    c_main = _distributed.share("sweep: chunk size", c)
    if c_main != c:
        raise ConfigError(
            f"process {me} chose chunks of {c} points and process 0 of {c_main} (their memory analyses "
            "differ): pass --chunk"
        )
    n_chunks = -(-n // c)
    if main_proc:
        doc = {"fingerprint": plan.fingerprint, "chunk": c, "n_chunks": n_chunks, "n_devices": n_dev}
        _results.write_json(os.path.join(out, "plan.json"), {**doc, "spec": plan.spec, "process_count": nproc})
        todo = [i for i in range(n_chunks) if i not in results]
        if loaded:
            log(f"resuming: {loaded} of {n_chunks} chunks read back from {os.path.join(out, 'chunks')}")
        if max_chunks is not None:
            todo = todo[:max_chunks]
    todo = _distributed.share("sweep: todo", todo if main_proc else None)
    mine = todo[me::nproc]
    n_steps = evaluator(
        plan.solver, plan.controller, plan.duration, n_dev, plan.model, plan.visual, *plan.stack_options
    )[1]
    size = lambda chunks: sum(stop - start for start, stop in (_bounds(i, c, n) for i in chunks))  # noqa: E731
    bar = _progress_bar(progress and main_proc, size(mine) + size(results), size(results), nproc)
    t_eval = time.perf_counter()
    try:
        computed = _evaluate(plan, out, mine, c, compiled, n_dev, results, bar, me)
    finally:
        if bar is not None:
            bar.close()
    eval_s = time.perf_counter() - t_eval
    per_process = [{"process": me, "chunks": computed, "points": size(mine), "eval_s": eval_s}]
    if nproc > 1:
        per_process = _distributed.gather("sweep: computed", per_process[0])
        _distributed.barrier("sweep: chunks written")
    if main_proc:
        for i in todo:  # the other processes' chunks, from disk
            if i not in results:
                got = load_chunk(out, i, *_bounds(i, c, n), _metrics.Metrics._fields)
                if got is None:
                    raise RuntimeError(f"chunk {i} was computed by another process but is not in {out}/chunks")
                results[i] = got
    computed = sum(p["chunks"] for p in per_process)
    points = sum(p["points"] for p in per_process)
    eval_s = max(p["eval_s"] for p in per_process)  # the evaluation ends with the slowest process
    rate = computed and eval_s > 0
    timing = {
        "wall_s": time.perf_counter() - t_start,
        "compile_s": compile_s,
        "eval_s": eval_s,
        "chunks_computed": computed,
        "chunks_loaded": loaded,
        "points_per_s": points / eval_s if rate else None,
        "env_steps_per_s": points * n_steps / eval_s if rate else None,
        "per_process": per_process,
    }
    if not main_proc:  # process 0 assembles the results: wait until it has
        _distributed.barrier("sweep: results written")
        return {"complete": True, "process_index": me, "timing": timing}
    try:
        return _assemble(
            plan, out, results, n_chunks, c, n_steps, devices, nproc, budget_gib, used, timing, plot_metrics, log
        )
    finally:
        _distributed.barrier("sweep: results written")


def _assemble(plan, out, results, n_chunks, c, n_steps, devices, nproc, budget_gib, used, timing, plot_metrics, log):
    """Process 0: results.csv, the plots and summary.json from every chunk (or the note that some are left)."""
    computed = timing["chunks_computed"]
    if len(results) < n_chunks:
        log(
            f"stopped after {computed} new chunk(s) (--max-chunks): {len(results)} of {n_chunks} done; "
            "run the same command again with --resume to finish"
        )
        return {"complete": False, "chunks_done": len(results), "n_chunks": n_chunks, "timing": timing}
    metrics = {k: np.concatenate([results[i][k] for i in range(n_chunks)]) for k in _metrics.Metrics._fields}
    summary = {"complete": True, **summarize_sweep(plan, metrics)}
    write_csv(os.path.join(out, "results.csv"), plan, metrics)
    fig = plot(out, plan, metrics, plot_metrics)
    summary.update(
        {
            "sweep": plan.spec,
            "fingerprint": plan.fingerprint,
            "chunk": c,
            "n_chunks": n_chunks,
            "n_steps_per_rollout": n_steps,
            "devices": [str(d) for d in devices],
            "process_count": nproc,
            "memory": {
                "budget_gib_per_device": budget_gib,
                "chunk_gib_per_device": used / GIB if used is not None else None,
            },
            "timing": timing,
            "plot": fig,
            "files": ["results.csv", "summary.json", "plan.json", "chunks/"] + ([fig] if fig else []),
        }
    )
    _results.write_json(os.path.join(out, "summary.json"), summary)
    return summary
