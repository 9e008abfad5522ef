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
    "grad_s_over_old": ("<=", 1.0),
    "grad_compile_cold_s": ("<=", 45.0),
    "grad_compile_warm_s": ("<=", 5.0),
    "tune_step_peak_rss_gib": ("<=", 2.0),
}

FULL = dict(
    batch_sizes=(1, 16, 64, 256),
    mjx_duration=4.0,
    c_duration=4.0,
    bare_steps=4000,
    grad_duration=2.0,
    tune_batch=4,
    tune_task="full",
    repeats=2,
    grad_repeats=7,
    small=False,
    old_children=True,
)
# --quick checks that the benchmark runs: the gradient parts use a small
# stand-in (kinematics and sensing, no constraint solve) and the former path's
# child processes are skipped; its figures measure nothing about the paths
QUICK = dict(
    batch_sizes=(1,),
    mjx_duration=0.05,
    c_duration=0.05,
    bare_steps=200,
    grad_duration=0.1,
    tune_batch=2,
    tune_task="short",
    repeats=1,
    grad_repeats=1,
    small=True,
    old_children=False,
)


def targets(r: dict, judged: bool = True) -> dict:
    """Each target with its value and whether it was met; ``judged`` False for
    a --quick run (met or missed is still computed and shown, marked as not a
    benchmark)."""
    out = {}
    for key, (op, bound) in TARGETS.items():
        v = r.get(key)
        if v is None:
            continue
        met = v >= bound if op == ">=" else v <= bound
        out[key] = {"value": v, "target": f"{op} {bound:g}", "met": bool(met), "judged": judged}
    return out


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def measure(out: str, *, quick: bool = False, batch_sizes=None, log=_log) -> dict:
    """Every measurement, in one run; writes ``out/bench.json`` and returns its content."""

    from jaxsync.cli._bench_measure import (
        PATHS,
        XLA_DEFAULT_EMITTERS,
        _have_flatbuffers,
        bare_mj_step,
        cold_compile_with_xla_flags,
        compile_times,
        forward_and_gradient,
        machine,
        mjx_throughput,
        mujoco_c_throughput,
        tune_step_memory,
        warm_compile_s,
    )
    from jaxsync.io import results as _results
    from jaxsync.physics.model import load_model

    cfg = dict(QUICK if quick else FULL)
    if batch_sizes:
        cfg["batch_sizes"] = tuple(batch_sizes)
    _results.ensure_writable_dir(out)
    t_start = time.perf_counter()
    info = machine()
    log(
        f"jaxsync bench{' --quick' if quick else ''} on {info['cpu_model']} ({info['cpu_cores']} cores), "
        f"JAX {info['jax']} {info['jax_backend']}"
    )
    small = cfg["small"]
    model = load_model(solver="accurate")
    log("[1/6] MJX closed loop, default scenario")
    mjx = mjx_throughput(model, cfg["batch_sizes"], cfg["mjx_duration"], cfg["repeats"], log)
    log("[2/6] the same controller on MuJoCo C")
    mjc = mujoco_c_throughput(model, cfg["c_duration"], log)
    log("[3/6] bare mj_step")
    bare = bare_mj_step(model, cfg["bare_steps"], log)
    log("[4/6] forward rollout against its gradient, the tuner's path (new) and the former one (old)")
    fg = {p: forward_and_gradient(p, cfg["grad_duration"], cfg["grad_repeats"], log, small) for p in PATHS}
    log("[5/6] gradient compile time, cold (empty cache) and warm (persistent cache), in fresh processes")
    comp = {"new": compile_times("new", cfg["grad_duration"], small, log, exported=not small)}
    if cfg["old_children"]:
        comp["old"] = compile_times("old", cfg["grad_duration"], small, log, exported=False)
        # jaxsync turns XLA's CPU fusion emitters off (jaxsync.runtime.xla); the same compile with XLA's default
        comp["new_xla_default"] = cold_compile_with_xla_flags("new", cfg["grad_duration"], XLA_DEFAULT_EMITTERS, log)
    log("[6/6] peak memory of one tuning step, in fresh processes (cold cache: it compiles; warm: from the cache)")
    tune = {"new": tune_step_memory("new", cfg["tune_batch"], cfg["tune_task"], small, log)}
    if cfg["old_children"]:
        tune["old"] = tune_step_memory("old", cfg["tune_batch"], cfg["tune_task"], small, log, warm=False)
        tune["new_xla_default"] = tune_step_memory(
            "new", cfg["tune_batch"], cfg["tune_task"], small, log, warm=False, xla_flags=XLA_DEFAULT_EMITTERS
        )
    best_b = max(mjx["rates"], key=mjx["rates"].get)

    def path_figures(p: str) -> dict:
        return {
            "label": PATHS[p]["label"],
            "forward_s": fg[p]["forward_s"],
            "grad_s": fg[p]["grad_s"],
            "grad_over_forward": fg[p]["grad_over_forward"],
            "grad_compile_cold_s": comp[p]["cold"]["total_s"] if p in comp else None,
            "grad_compile_warm_s": warm_compile_s(comp[p]) if p in comp else None,
            "tune_step_peak_rss_gib": tune[p]["peak_rss_gib"] if p in tune else None,
        }

    new = path_figures("new")
    result = {
        "mjx_env_steps_per_s": mjx["rates"],
        "mjx_best_batch": int(best_b),
        "mujoco_c_env_steps_per_s": mjc["rate"],
        "mujoco_c_env_steps_per_s_including_setup": mjc["rate_including_setup"],
        "bare_mj_step_per_s": bare,
        "mjx_over_mujoco_c": mjx["rates"][best_b] / mjc["rate"],
        # the tuner's path (new) at the top level, the former one beside it
        "forward_s": new["forward_s"],
        "grad_s": new["grad_s"],
        "grad_over_forward": new["grad_over_forward"],
        "grad_s_over_old": new["grad_s"] / fg["old"]["grad_s"],
        "grad_compile_cold_s": new["grad_compile_cold_s"],
        # what `jaxsync tune` does on a second run: the traced function from disk
        # (jax.export) and the XLA executable from the persistent cache; the
        # persistent cache alone (tracing again) is reported next to it
        "grad_compile_warm_s": new["grad_compile_warm_s"],
        "grad_compile_warm_persistent_cache_only_s": comp["new"]["warm"]["total_s"],
        "tune_step_peak_rss_gib": new["tune_step_peak_rss_gib"],
        "tune_step_peak_rss_warm_gib": tune["new"]["warm"]["peak_rss_gib"],
        # the same with XLA's default CPU emitters (jaxsync turns them off); None in --quick
        "grad_compile_cold_xla_default_s": comp["new_xla_default"]["total_s"] if "new_xla_default" in comp else None,
        "tune_step_peak_rss_xla_default_gib": tune["new_xla_default"]["peak_rss_gib"]
        if "new_xla_default" in tune
        else None,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "paths": {p: path_figures(p) for p in PATHS},
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
    _results.write_json(os.path.join(out, "bench.json"), result)
    return result


def _fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def table(r: dict) -> str:
    """The benchmark as a table: the tuner's path (new) beside the former one
    (old), each figure's target and whether it was met."""
    new, old = r["paths"]["new"], r["paths"]["old"]
    rows = [
        (f"MJX closed loop, env-steps/s, batch {b}", f"{v:,.0f}", "", None) for b, v in r["mjx_env_steps_per_s"].items()
    ]
    rows += [
        ("MuJoCo C + same controller, env-steps/s", f"{r['mujoco_c_env_steps_per_s']:,.0f}", "", None),
        ("bare mj_step, steps/s", f"{r['bare_mj_step_per_s']:,.0f}", "", None),
        (
            f"MJX best (batch {r['mjx_best_batch']}) / MuJoCo C",
            f"{r['mjx_over_mujoco_c']:.2f}",
            "",
            "mjx_over_mujoco_c",
        ),
        ("forward rollout, s", f"{new['forward_s']:.3f}", f"{old['forward_s']:.3f}", None),
        ("value_and_grad, s", f"{new['grad_s']:.3f}", f"{old['grad_s']:.3f}", None),
        (
            "gradient / forward",
            f"{new['grad_over_forward']:.2f}",
            f"{old['grad_over_forward']:.2f}",
            "grad_over_forward",
        ),
        ("gradient s, new / old", f"{r['grad_s_over_old']:.2f}", "", "grad_s_over_old"),
        (
            "gradient compile cold, s",
            _fmt(new["grad_compile_cold_s"], ".1f"),
            _fmt(old["grad_compile_cold_s"], ".1f"),
            "grad_compile_cold_s",
        ),
        (
            "gradient compile warm (as the CLI), s",
            _fmt(new["grad_compile_warm_s"], ".1f"),
            _fmt(old["grad_compile_warm_s"], ".1f"),
            "grad_compile_warm_s",
        ),
        (
            "gradient compile warm, persistent cache only, s",
            f"{r['grad_compile_warm_persistent_cache_only_s']:.1f}",
            "",
            None,
        ),
        (
            "tuning step peak RSS (compiling it), GiB",
            _fmt(new["tune_step_peak_rss_gib"], ".2f"),
            _fmt(old["tune_step_peak_rss_gib"], ".2f"),
            "tune_step_peak_rss_gib",
        ),
        ("tuning step peak RSS (from the cache), GiB", f"{r['tune_step_peak_rss_warm_gib']:.2f}", "", None),
        (
            "with XLA's default CPU emitters: gradient compile cold, s",
            _fmt(r.get("grad_compile_cold_xla_default_s"), ".1f"),
            "",
            None,
        ),
        (
            "with XLA's default CPU emitters: tuning step peak RSS (compiling), GiB",
            _fmt(r.get("tune_step_peak_rss_xla_default_gib"), ".2f"),
            "",
            None,
        ),
    ]
    tg = r.get("targets", {})
    w = max(len(a) for a, *_ in rows)
    lines = [f"{'measure':<{w}}  {'new':>12}  {'old':>8}  target"]
    for name, val, val_old, key in rows:
        t = tg.get(key)
        mark = ""
        if t:
            verdict = "met" if t["met"] else "MISSED"
            mark = f"{t['target']:<8} {verdict}" + ("" if t["judged"] else " (--quick: not a benchmark)")
        lines.append(f"{name:<{w}}  {val:>12}  {val_old:>8}  {mark}".rstrip())
    lines.append(f"new: {new['label']}; old: {old['label']}; XLA_FLAGS: {r.get('xla_flags') or '(none)'}")
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
