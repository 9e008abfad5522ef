"""How fast the simulator, its gradient and its compilation are: ``jaxsync bench`` as a library.

:func:`run` measures, in one run on one machine, closed-loop MJX
environment-steps per second at several batch sizes; the same controller
stepping MuJoCo C (one environment); bare ``mj_step``; one forward rollout
against its gradient; cold and warm (persistent-cache) compile times of the
gradient; the peak memory of one tuning step (the measurements are in
``jaxsync.optimize.benchmarks.benchmark_measure`` and ``benchmark_children``). It writes ``bench.json`` and returns
its content; :func:`table` formats it. A benchmark reports, it never fails:
the targets of docs/performance.md are recorded next to the numbers.

With a robot (``source``), every measurement is taken on the robot's
composed scene at its default gains and object, and a last section measures
the paper model's forward rollout and gradient in the same rounds as the
robot's, alternated in one process, and its cold compile in a fresh process,
so that the robot's figures are given as ratios to the paper model's.

The gradient figures are taken for both paths of ``PATHS``: ``implicit``
(the converged solve, the implicit adjoint, the exact gradient: what
``jaxsync tune`` runs) and ``unrolled`` (one-iteration solves unrolled and
truncated every 100 steps, a reference). The top-level figures are the
implicit path's.

Example:
  >>> from jaxsync.optimize.benchmarks import benchmark
  >>> r = benchmark.run("/tmp/bench", quick=True)  # doctest: +SKIP
  >>> print(benchmark.table(r))  # doctest: +SKIP
"""

from __future__ import annotations

import numbers
import os
import sys
import time
from collections.abc import Callable, Sequence

from jaxsync._errors import ConfigError
from jaxsync.control import gains as _gains
from jaxsync.io import results as _results
from jaxsync.optimize.benchmarks.benchmark_children import (
    cold_compile_with_xla_flags,
    compile_times,
    tune_step_memory,
    warm_compile_s,
)
from jaxsync.optimize.benchmarks.benchmark_measure import (
    PATHS,
    XLA_DEFAULT_EMITTERS,
    bare_mj_step,
    forward_and_gradient,
    have_flatbuffers,
    machine,
    mjx_throughput,
    mujoco_c_throughput,
    paired_forward_and_gradient,
    paired_stacks,
)
from jaxsync.physics.model import identity, load_model
from jaxsync.sim import scenario as _scenario
from jaxsync.sim.actuation import TORQUE, Stack

TARGETS = {
    "mjx_over_mujoco_c": (">=", 3.0),
    "grad_over_forward": ("<=", 4.0),
    "grad_s_over_unrolled": ("<=", 1.0),
    "grad_compile_cold_s": ("<=", 45.0),
    "grad_compile_warm_s": ("<=", 5.0),
    "tune_step_peak_rss_gib": ("<=", 2.0),
    # with a robot: its gradient's cost (in forward rollouts) and its cold
    # compile against the paper model's, measured in the same run
    "grad_over_forward_over_paper": ("<=", 1.3),
    "grad_compile_cold_over_paper": ("<=", 1.3),
    # with a position stack: its gradient's cost (in forward rollouts) against the torque stack's
    "position_grad_over_forward_over_torque": ("<=", 1.3),
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
    pair_rounds=21,
    small=False,
    reference_children=True,
)
# quick checks that the benchmark runs: the gradient parts use a small
# stand-in (kinematics and sensing, no constraint solve) and the reference
# child processes (the unrolled path's, XLA's default emitters) are skipped;
# its figures measure nothing about the paths
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
    pair_rounds=1,
    small=True,
    reference_children=False,
)


def targets(r: dict, judged: bool = True) -> dict:
    """Each target with its value and whether it was met; ``judged`` False for
    a quick run (met or missed is still computed and shown, marked as not a
    benchmark)."""
    out = {}
    for key, (op, bound) in TARGETS.items():
        v = r.get(key)
        if v is None:
            continue
        met = v >= bound if op == ">=" else v <= bound
        out[key] = {"value": v, "target": f"{op} {bound:g}", "met": bool(met), "judged": judged}
    return out


def _log_stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run(
    out: str,
    *,
    quick: bool = False,
    batch_sizes: Sequence[int] | None = None,
    log: Callable[[str], None] = _log_stderr,
    source: str | None = None,
    visual: bool = True,
    stack: Stack = TORQUE,
) -> dict:
    """Every measurement, in one run; writes ``out/bench.json`` and returns its content.

    ``quick``: tiny horizons and batches and a small stand-in for the
    gradient (a smoke test, not a benchmark); ``batch_sizes`` replaces the
    MJX batch sizes; ``log`` receives the progress lines (standard error by
    default); ``source`` a robot file (or an MJCF in jaxsync's convention) to
    benchmark instead of the paper model, against the paper model's gradient
    figures; ``visual`` False loads it without its meshes. ``stack`` a
    position stack (one delay): its gradient's cost against the torque
    stack's, timed in the same rounds (the other figures are the torque
    stack's).
    """
    cfg = dict(QUICK if quick else FULL)
    if batch_sizes:
        sizes = tuple(batch_sizes)
        if any(not isinstance(b, numbers.Integral) or b < 1 for b in sizes):
            raise ConfigError(f"batch sizes must be positive whole numbers, got {list(sizes)}")
        cfg["batch_sizes"] = tuple(int(b) for b in sizes)
    # the children run away from the working directory: an absolute path
    source = os.path.abspath(source) if source is not None else None
    model = load_model(source, solver="accurate", visual=visual)
    position = stack.actuation == "position"
    if position:
        stack.scenario_delay(), stack.substeps(model)  # one delay, a rate that divides: before any folder
    _results.ensure_writable_dir(out)
    model_kw = {"source": source, "visual": visual}
    t_start = time.perf_counter()
    info = machine()
    log(
        f"jaxsync bench{' --quick' if quick else ''} on {info['cpu_model']} ({info['cpu_cores']} cores), "
        f"JAX {info['jax']} {info['jax_backend']}"
    )
    small = cfg["small"]
    n = 6 + bool(source) + position
    log(f"[1/{n}] MJX closed loop, default scenario" + (f", {source}" if source else ""))
    mjx = mjx_throughput(model, cfg["batch_sizes"], cfg["mjx_duration"], cfg["repeats"], log)
    log(f"[2/{n}] the same controller on MuJoCo C")
    mjc = mujoco_c_throughput(model, cfg["c_duration"], log)
    log(f"[3/{n}] bare mj_step")
    bare = bare_mj_step(model, cfg["bare_steps"], log)
    log(f"[4/{n}] forward rollout against its gradient, the tuner's path (implicit) and the reference (unrolled)")
    dur, reps = cfg["grad_duration"], cfg["grad_repeats"]
    fg = {p: forward_and_gradient(p, dur, reps, log, small, **model_kw) for p in PATHS}
    log(f"[5/{n}] gradient compile time, cold (empty cache) and warm (persistent cache), in fresh processes")
    comp = {"implicit": compile_times("implicit", dur, small, log, exported=not small, **model_kw)}
    if cfg["reference_children"]:
        comp["unrolled"] = compile_times("unrolled", dur, small, log, exported=False, **model_kw)
        # jaxsync turns XLA's CPU fusion emitters off (jaxsync.runtime.xla); the same compile with XLA's default
        flags = XLA_DEFAULT_EMITTERS
        comp["implicit_xla_default"] = cold_compile_with_xla_flags("implicit", dur, flags, log, **model_kw)
    log(f"[6/{n}] peak memory of one tuning step, in fresh processes (cold cache: it compiles; warm: from the cache)")
    batch, task = cfg["tune_batch"], cfg["tune_task"]
    tune = {"implicit": tune_step_memory("implicit", batch, task, small, log, **model_kw)}
    if cfg["reference_children"]:
        tune["unrolled"] = tune_step_memory("unrolled", batch, task, small, log, warm=False, **model_kw)
        tune["implicit_xla_default"] = tune_step_memory(
            "implicit", batch, task, small, log, warm=False, xla_flags=XLA_DEFAULT_EMITTERS, **model_kw
        )
    paper = None
    if source:
        log(
            f"[7/{n}] the paper model against the robot: forward rollout and gradient in alternating rounds "
            "(this process), cold compile (a fresh process)"
        )
        pair = paired_forward_and_gradient(dur, cfg["pair_rounds"], log, small, **model_kw)
        paper_cold = compile_times("implicit", dur, small, log, exported=False, warm=False)["cold"]
        paper_fg = pair["models"]["paper"]
        paper = {
            "forward_s": paper_fg["forward_s"],
            "grad_s": paper_fg["grad_s"],
            "grad_over_forward": paper_fg["grad_over_forward"],
            "grad_compile_cold_s": paper_cold["total_s"],
            # the robot's figures of the same rounds: the ratio's numerator
            "robot_in_the_same_rounds": pair["models"]["robot"],
            "ratio_of_ratios": pair["ratio_of_ratios"],
            "details": {"paired_forward_and_gradient": pair, "compile_cold": paper_cold},
        }
    on_position = None
    if position:
        log(
            f"[{n}/{n}] the position stack against the torque stack: forward rollout and gradient in alternating "
            "rounds (this process)"
        )
        on_position = paired_stacks(dur, cfg["pair_rounds"], log, stack, small, **model_kw)
        on_position["stack"] = stack.to_dict(model)
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

    implicit = path_figures("implicit")
    result = {
        "model": source or "paper model",
        # what ran: the model's identity, its default gains and scenario (a robot file's raised gains and object)
        "model_identity": identity(model),
        "gains": _gains.to_dict(_gains.default_gains(model)),
        "scenario_base": _scenario.to_dict(_scenario.default_scenario(model)),
        "mjx_env_steps_per_s": mjx["rates"],
        "mjx_best_batch": int(best_b),
        "mujoco_c_env_steps_per_s": mjc["rate"],
        "mujoco_c_env_steps_per_s_including_setup": mjc["rate_including_setup"],
        "bare_mj_step_per_s": bare,
        "mjx_over_mujoco_c": mjx["rates"][best_b] / mjc["rate"],
        # the tuner's path (implicit) at the top level, the unrolled reference beside it
        "forward_s": implicit["forward_s"],
        "grad_s": implicit["grad_s"],
        "grad_over_forward": implicit["grad_over_forward"],
        "grad_s_over_unrolled": implicit["grad_s"] / fg["unrolled"]["grad_s"],
        "grad_compile_cold_s": implicit["grad_compile_cold_s"],
        # what `jaxsync tune` does on a second run: the traced function from disk
        # (jax.export) and the XLA executable from the persistent cache; the
        # persistent cache alone (tracing again) is reported next to it
        "grad_compile_warm_s": implicit["grad_compile_warm_s"],
        "grad_compile_warm_persistent_cache_only_s": comp["implicit"]["warm"]["total_s"],
        "tune_step_peak_rss_gib": implicit["tune_step_peak_rss_gib"],
        "tune_step_peak_rss_warm_gib": tune["implicit"]["warm"]["peak_rss_gib"],
        # the same with XLA's default CPU emitters (jaxsync turns them off); None in a quick run
        "grad_compile_cold_xla_default_s": comp["implicit_xla_default"]["total_s"]
        if "implicit_xla_default" in comp
        else None,
        "tune_step_peak_rss_xla_default_gib": tune["implicit_xla_default"]["peak_rss_gib"]
        if "implicit_xla_default" in tune
        else None,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "paths": {p: path_figures(p) for p in PATHS},
        # with a robot: the paper model's figures and the robot's ratios to them
        "paper_model": paper,
        # timed in the same rounds as the paper model (paired_forward_and_gradient)
        "grad_over_forward_over_paper": paper["ratio_of_ratios"]["per_round_median"] if paper else None,
        "grad_compile_cold_over_paper": implicit["grad_compile_cold_s"] / paper["grad_compile_cold_s"]
        if paper
        else None,
        # with a position stack: its figures and the gradient's cost over the torque stack's, in the same rounds
        "position_stack": on_position,
        "position_grad_over_forward_over_torque": on_position["ratio_of_ratios"]["per_round_median"]
        if on_position
        else None,
        "details": {
            "mjx": mjx,
            "mujoco_c": mjc,
            "forward_and_gradient": fg,
            "compile": comp,
            "tune_step": tune,
            "config": {**cfg, "quick": quick, "flatbuffers": have_flatbuffers()},
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
    """The benchmark as a table: the tuner's path (implicit) beside the
    reference (unrolled), each figure's target and whether it was met."""
    implicit, unrolled = r["paths"]["implicit"], r["paths"]["unrolled"]
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
        ("forward rollout, s", f"{implicit['forward_s']:.3f}", f"{unrolled['forward_s']:.3f}", None),
        ("value_and_grad, s", f"{implicit['grad_s']:.3f}", f"{unrolled['grad_s']:.3f}", None),
        (
            "gradient / forward",
            f"{implicit['grad_over_forward']:.2f}",
            f"{unrolled['grad_over_forward']:.2f}",
            "grad_over_forward",
        ),
        ("gradient s, implicit / unrolled", f"{r['grad_s_over_unrolled']:.2f}", "", "grad_s_over_unrolled"),
        (
            "gradient compile cold, s",
            _fmt(implicit["grad_compile_cold_s"], ".1f"),
            _fmt(unrolled["grad_compile_cold_s"], ".1f"),
            "grad_compile_cold_s",
        ),
        (
            "gradient compile warm (as the CLI), s",
            _fmt(implicit["grad_compile_warm_s"], ".1f"),
            _fmt(unrolled["grad_compile_warm_s"], ".1f"),
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
            _fmt(implicit["tune_step_peak_rss_gib"], ".2f"),
            _fmt(unrolled["tune_step_peak_rss_gib"], ".2f"),
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
    paper = r.get("paper_model")
    if paper:
        rows += [
            ("the paper model: gradient / forward", f"{paper['grad_over_forward']:.2f}", "", None),
            ("the paper model: gradient compile cold, s", f"{paper['grad_compile_cold_s']:.1f}", "", None),
            (
                "this model's gradient / forward, in the same rounds",
                f"{paper['robot_in_the_same_rounds']['grad_over_forward']:.2f}",
                "",
                None,
            ),
            (
                "this model's gradient / forward over the paper model's, median of the rounds",
                f"{r['grad_over_forward_over_paper']:.2f}",
                "",
                "grad_over_forward_over_paper",
            ),
            (
                "the same: quartiles over the rounds; ratio of the best times",
                "{:.2f}-{:.2f}".format(*paper["ratio_of_ratios"]["per_round_quartiles"]),
                f"{paper['ratio_of_ratios']['of_best']:.2f}",
                None,
            ),
            (
                "this model's cold compile over the paper model's",
                f"{r['grad_compile_cold_over_paper']:.2f}",
                "",
                "grad_compile_cold_over_paper",
            ),
        ]
    pos = r.get("position_stack")
    if pos:
        st = pos["stacks"]
        rows += [
            (
                "position stack: gradient / forward, in the same rounds",
                f"{st['position']['grad_over_forward']:.2f}",
                "",
                None,
            ),
            (
                "torque stack: gradient / forward, in the same rounds",
                f"{st['torque']['grad_over_forward']:.2f}",
                "",
                None,
            ),
            (
                "position stack's gradient / forward over the torque stack's, median of the rounds",
                f"{r['position_grad_over_forward_over_torque']:.2f}",
                "",
                "position_grad_over_forward_over_torque",
            ),
        ]
    tg = r.get("targets", {})
    w = max(len(a) for a, *_ in rows)
    lines = [f"model: {r.get('model', 'paper model')}", f"{'measure':<{w}}  {'implicit':>12}  {'unrolled':>8}  target"]
    for name, val, val_unrolled, key in rows:
        t = tg.get(key)
        mark = ""
        if t:
            verdict = "met" if t["met"] else "MISSED"
            mark = f"{t['target']:<8} {verdict}" + ("" if t["judged"] else " (--quick: not a benchmark)")
        lines.append(f"{name:<{w}}  {val:>12}  {val_unrolled:>8}  {mark}".rstrip())
    lines.append(
        f"implicit: {implicit['label']}; unrolled: {unrolled['label']}; XLA_FLAGS: {r.get('xla_flags') or '(none)'}"
    )
    return "\n".join(lines)
