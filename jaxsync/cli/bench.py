"""``jaxsync bench``: how fast the simulator, its gradient and its compilation are.

Measured in one run on one machine and written to ``bench.json`` (and printed
as a table): closed-loop MJX environment-steps per second at several batch
sizes; the same controller stepping MuJoCo C (one environment); bare
``mj_step``; one forward rollout against its gradient; cold and warm
(persistent-cache) compile times of the gradient; the peak memory of one
tuning step (``jaxsync.cli._bench_measure``). A benchmark reports, it never
fails: the targets of docs/performance.md are printed next to the numbers.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from jaxsync._errors import ConfigError

TARGETS = {
    "mjx_over_mujoco_c": (">=", 3.0),
    "grad_over_forward": ("<=", 4.0),
    "grad_compile_cold_s": ("<=", 45.0),
    "grad_compile_warm_s": ("<=", 5.0),
    "tune_step_peak_rss_gib": ("<=", 6.0),
}

FULL = dict(
    batch_sizes=(1, 16, 64, 256),
    mjx_duration=4.0,
    c_duration=4.0,
    bare_steps=4000,
    grad_duration=2.0,
    tune_batch=8,
    tune_duration=2.0,
    repeats=2,
    grad_repeats=7,
)
QUICK = dict(
    batch_sizes=(1, 2),
    mjx_duration=0.05,
    c_duration=0.05,
    bare_steps=200,
    grad_duration=0.1,
    tune_batch=2,
    tune_duration=0.1,
    repeats=1,
    grad_repeats=1,
)


def targets(r: dict, judged: bool = True) -> dict:
    """Each target with its value and whether it was met (None: a --quick run, not judged)."""
    out = {}
    for key, (op, bound) in TARGETS.items():
        v = r.get(key)
        if v is None:
            continue
        met = v >= bound if op == ">=" else v <= bound
        out[key] = {"value": v, "target": f"{op} {bound:g}", "met": bool(met) if judged else None}
    return out


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def measure(out: str, *, quick: bool = False, batch_sizes=None, log=_log) -> dict:
    """Every measurement, in one run; writes ``out/bench.json`` and returns its content."""
    import jax

    from jaxsync import _io
    from jaxsync._model import load_model
    from jaxsync.cli._bench_measure import (
        _have_flatbuffers,
        bare_mj_step,
        compile_times,
        forward_and_gradient,
        machine,
        mjx_throughput,
        mujoco_c_throughput,
        tune_step_memory,
    )

    cfg = dict(QUICK if quick else FULL)
    if batch_sizes:
        cfg["batch_sizes"] = tuple(batch_sizes)
    _io.ensure_writable_dir(out)
    t_start = time.perf_counter()
    info = machine()
    log(
        f"jaxsync bench{' --quick' if quick else ''} on {info['cpu_model']} ({info['cpu_cores']} cores), "
        f"JAX {info['jax']} {info['jax_backend']}"
    )
    cache_dir = jax.config.jax_compilation_cache_dir
    model = load_model(solver="accurate")
    log("[1/6] MJX closed loop, default scenario")
    mjx = mjx_throughput(model, cfg["batch_sizes"], cfg["mjx_duration"], cfg["repeats"], log)
    log("[2/6] the same controller on MuJoCo C")
    mjc = mujoco_c_throughput(model, cfg["c_duration"], log)
    log("[3/6] bare mj_step")
    bare = bare_mj_step(model, cfg["bare_steps"], log)
    log("[4/6] forward rollout and its gradient (differentiable solver, rematerialised scan)")
    fg = forward_and_gradient(cfg["grad_duration"], cfg["grad_repeats"], log)
    log("[5/6] gradient compile time, cold (empty cache) and warm (persistent cache), in fresh processes")
    comp = compile_times(cfg["grad_duration"], quick, log)
    log("[6/6] peak memory of one tuning step, in a fresh process")
    tune = tune_step_memory(cfg["tune_batch"], cfg["tune_duration"], cache_dir, log)
    best_b = max(mjx["rates"], key=mjx["rates"].get)
    result = {
        "mjx_env_steps_per_s": mjx["rates"],
        "mjx_best_batch": int(best_b),
        "mujoco_c_env_steps_per_s": mjc["rate"],
        "mujoco_c_env_steps_per_s_including_setup": mjc["rate_including_setup"],
        "bare_mj_step_per_s": bare,
        "mjx_over_mujoco_c": mjx["rates"][best_b] / mjc["rate"],
        "forward_s": fg["forward_s"],
        "grad_s": fg["grad_s"],
        "grad_over_forward": fg["grad_over_forward"],
        "grad_compile_cold_s": comp["cold"]["total_s"],
        # what `jaxsync tune` does on a second run: the traced function from disk
        # (jax.export) and the XLA executable from the persistent cache; the
        # persistent cache alone (tracing again) is reported next to it
        "grad_compile_warm_s": (comp["warm_exported"] if "warm_exported" in comp else comp["warm"])["total_s"],
        "grad_compile_warm_persistent_cache_only_s": comp["warm"]["total_s"],
        "tune_step_peak_rss_gib": tune["peak_rss_gib"],
        "details": {
            "mjx": mjx,
            "mujoco_c": mjc,
            "forward_and_gradient": fg,
            "compile": comp,
            "tune_step": tune,
            "config": {**cfg, "quick": quick, "flatbuffers": _have_flatbuffers()},
        },
        "machine": info,
    }
    result["targets"] = targets(result, judged=not quick)
    result["wall_time_s"] = time.perf_counter() - t_start
    _io.write_json(os.path.join(out, "bench.json"), result)
    return result


def table(r: dict) -> str:
    rates = r["mjx_env_steps_per_s"]
    rows = [(f"MJX closed loop, env-steps/s, batch {b}", f"{v:,.0f}") for b, v in rates.items()]
    rows += [
        ("MuJoCo C + same controller, env-steps/s", f"{r['mujoco_c_env_steps_per_s']:,.0f}"),
        ("bare mj_step, steps/s", f"{r['bare_mj_step_per_s']:,.0f}"),
        (f"MJX best (batch {r['mjx_best_batch']}) / MuJoCo C", f"{r['mjx_over_mujoco_c']:.2f}"),
        ("forward rollout, s", f"{r['forward_s']:.3f}"),
        ("value_and_grad, s", f"{r['grad_s']:.3f}"),
        ("gradient / forward", f"{r['grad_over_forward']:.2f}"),
        ("gradient compile cold, s", f"{r['grad_compile_cold_s']:.1f}"),
        ("gradient compile warm (as the CLI: traced on disk + cache), s", f"{r['grad_compile_warm_s']:.1f}"),
        ("gradient compile warm, persistent cache only, s", f"{r['grad_compile_warm_persistent_cache_only_s']:.1f}"),
        ("tuning step peak RSS, GiB", f"{r['tune_step_peak_rss_gib']:.2f}"),
    ]
    tg = r.get("targets", {})
    keymap = {
        "MJX best": "mjx_over_mujoco_c",
        "gradient / forward": "grad_over_forward",
        "gradient compile cold": "grad_compile_cold_s",
        "gradient compile warm (as": "grad_compile_warm_s",
        "tuning step peak": "tune_step_peak_rss_gib",
    }
    w = max(len(a) for a, _ in rows)
    lines = [f"{'measure':<{w}}  {'value':>12}  target"]
    for name, val in rows:
        key = next((k for p, k in keymap.items() if name.startswith(p)), None)
        t = tg.get(key)
        verdict = "(--quick)" if t and t["met"] is None else "met" if t and t["met"] else "MISSED"
        mark = f"{t['target']:<8} {verdict}" if t else ""
        lines.append(f"{name:<{w}}  {val:>12}  {mark}")
    return "\n".join(lines)


def _batch_list(text: str):
    try:
        sizes = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--batch-sizes must be comma-separated whole numbers, got {text!r}") from None
    if not sizes or any(b < 1 for b in sizes):
        raise ConfigError(f"--batch-sizes must be positive whole numbers, got {text!r}")
    return sizes


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "bench",
        help="measure simulation throughput, gradient cost, compile times and memory",
        description="Benchmark MJX against MuJoCo C, the gradient against the forward rollout, compile times "
        "and the memory of a tuning step, in one run; writes bench.json and prints a table. "
        "See docs/performance.md.",
    )
    p.add_argument("--out", default="results/bench", help="output folder (results/bench)")
    p.add_argument("--quick", action="store_true", help="tiny horizons and batches: a smoke test, not a benchmark")
    p.add_argument("--batch-sizes", default=None, help="MJX batch sizes, comma-separated (1,16,64,256)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    sizes = _batch_list(args.batch_sizes) if args.batch_sizes is not None else None
    r = measure(args.out, quick=args.quick, batch_sizes=sizes)
    print(table(r))
    print(f"bench.json in {args.out} ({r['wall_time_s']:.0f} s)")
    return 0
