"""Test configuration: float64, the persistent compilation cache, shared models.

Every jitted function is compiled once per session through the fixtures here.
"""

from __future__ import annotations

import collections
import gc
import hashlib
import inspect
import json
import os
import signal
import subprocess
import sys
import time
import types

import jax
import numpy as np
import pytest

import jaxsync
from jaxsync.control.gains import classical_equivalent, default_gains
from jaxsync.optimize.tuning import loss as loss_mod
from jaxsync.optimize.tuning import pipeline as pipeline_mod
from jaxsync.optimize.tuning import tune as tune_mod
from jaxsync.optimize.tuning.scenarios import sample_scenarios, training_base
from jaxsync.runtime import programs
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags
from jaxsync.sim import rollout as _rollout
from jaxsync.sim.metrics import Metrics
from jaxsync.sim.rollout import rollout
from jaxsync.sim.scenario import min_duration, short_task

# isort: split
# after jaxsync, whose import keeps MJX's warp message out of the output and
# defers MUJOCO_GL's OpenGL backend to the first Renderer (jaxsync.runtime.gl)
from mujoco import mjx

set_xla_flags()  # as the command line does (half the memory of compiling); before any JAX computation
jax.config.update("jax_enable_x64", True)
# every program, also the small ones of eager operations (about 600 of them in
# three test files, 24 s of compiling that a warm run reads back)
enable_compilation_cache(min_compile_time_s=0.0)


# Python's own Ctrl-C handler, whatever the shell started the tests with (a
# background job of a non-interactive shell inherits SIGINT ignored): the
# interrupt tests raise SIGINT and expect a KeyboardInterrupt.
signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_collection_modifyitems(config, items):
    """The default run (the README's test command, .ci/run) leaves out the
    tests marked slow: deep checks that compile for minutes on a small CPU.
    ``-m`` decides instead when given (``-m slow``: only those), and a test
    named on the command line (``path::name``) runs whatever its mark; the
    other slow tests of the same run stay out."""
    if config.option.markexpr:
        return
    named = [str(a).split("::", 1)[1] for a in config.args if "::" in str(a)]

    def asked_for(item):  # named on the command line, alone or by its parametrised name
        return any(item.name == n or item.name.startswith(n + "[") for n in named)

    slow = [item for item in items if item.get_closest_marker("slow") and not asked_for(item)]
    if slow:
        config.hook.pytest_deselected(items=slow)
        dropped = set(map(id, slow))
        items[:] = [item for item in items if id(item) not in dropped]


# Above this resident size the programs a test module compiled are dropped
# after it; below, they stay for the next modules (measured, warm suite, one
# run each in a row: 3 min 55 s and 4 min 8 s dropping after every module
# against 3 min 29 s never dropping, peak 1.72 GiB against 2.75 GiB).
KEEP_PROGRAMS_BELOW_GIB = 2.0


def _resident_gib() -> float:
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 2**20
    except (OSError, StopIteration):
        return float("inf")  # not Linux: always drop


@pytest.fixture(scope="module", autouse=True)
def _free_compiled_programs():
    """After a test module, when the process holds more than
    ``KEEP_PROGRAMS_BELOW_GIB``, drop the compiled programs it holds (JAX's
    caches and jaxsync's own), so that the process does not hold every program
    of the session at once (the suite's peak memory). Programs a later module
    needs again come back from the persistent compilation cache; below the
    limit they stay, and a later module does not trace and look them up again."""
    yield
    if _resident_gib() < KEEP_PROGRAMS_BELOW_GIB:
        return
    programs.clear()
    gc.collect()


# The suite's time is mostly XLA compiling big programs, one at a time on one
# core. A test module may define ``compile_ahead()``: it builds and runs, with
# the test's own code, the programs its tests compile. At the session's start a
# second process runs those of the selected modules, in the order the tests
# come, and writes them to the persistent compilation cache; when a test comes
# to one, it reads it back instead of compiling. The first module's are left
# out (its tests would be compiling them at the same time). When a module starts
# while the process is still on it, its tests wait for the process to finish it
# (they would compile the same programs from the start); while the process is
# on an earlier one, it is stopped and started again on the modules after it
# (compiling what the tests compile anyway gains nothing). Nothing
# depends on it: a program not in the cache yet is compiled by the test as
# before; the process runs at a lower priority, so that a busy machine runs the
# tests first. Measured cold, the default run on 2 cores: 9 min 15 s without,
# 6 min 46 s with; with another job holding a core, eight of the modules gained
# about 10 s.
_COMPILE_AHEAD = """
import os, sys, time, traceback
os.nice(10)
import conftest  # the tests' settings: XLA flags, float64, the compilation cache
for name in sys.argv[1:]:
    print(f"start {name} {time.time():.1f}", flush=True)  # the wall clock: when, beside the tests
    t = time.perf_counter()
    try:
        __import__(name).compile_ahead()
        print(f"{name}: {time.perf_counter() - t:.1f} s, ended {time.time():.1f}", flush=True)
    except Exception:
        traceback.print_exc()
"""


class _AheadProcess:
    """The compile-ahead process (above): started on the modules still to come,
    restarted past the tests when they catch up with it. Its log is one file."""

    def __init__(self, names: list[str], cache: str, log_path):
        self.names, self.cache, self.log_path, self.proc = names, cache, log_path, None
        self.start(names)

    def start(self, names: list[str]) -> None:
        if not names:
            return
        with open(self.log_path, "a") as log:
            self.offset = log.tell()  # where this process's lines begin
            self.proc = subprocess.Popen(
                [sys.executable, "-c", _COMPILE_AHEAD, *names],
                cwd=os.path.dirname(os.path.abspath(__file__)),  # python -c imports from here: conftest, the modules
                env=dict(os.environ, JAXSYNC_CACHE_DIR=self.cache),
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        self.running = names

    def current(self) -> str | None:
        """The module the process is compiling, None when it has ended."""
        if self.proc is None or self.proc.poll() is not None:
            return None
        with open(self.log_path) as log:
            log.seek(self.offset)
            started = [line.split()[1] for line in log if line.startswith("start ")]
        return started[-1] if started else self.running[0]

    def reached(self, name: str) -> None:
        """The tests start module ``name``: wait while the process compiles that module's programs (the
        tests would compile the same from the start), restart past it if the process is behind."""
        if name not in self.names:
            return
        at = self.current()
        if at == name:
            t = time.perf_counter()
            while self.current() == name and time.perf_counter() - t < WAIT_FOR_AHEAD_S:
                time.sleep(0.1)
            with open(self.log_path, "a") as log:
                log.write(f"the tests waited {time.perf_counter() - t:.1f} s for {name}'s programs\n")
            at = self.current()
        if at is None or self.names.index(at) > self.names.index(name):
            return
        self.stop()
        with open(self.log_path, "a") as log:
            log.write(f"the tests reached {name} while this process compiled {at}: restarted past it\n")
        self.start(self.names[self.names.index(name) + 1 :])

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
        if self.proc is not None:
            self.proc.wait()


_AHEAD: _AheadProcess | None = None
WAIT_FOR_AHEAD_S = 180.0  # at most, for the module the tests reached (the longest compiles for about 120 s)


@pytest.fixture(scope="session", autouse=True)
def _compile_ahead(request, tmp_path_factory):
    """Start the process that compiles the selected modules' programs ahead
    (above); stop it, if still running, when the session ends. Only with a
    compilation cache to share, at least two cores and no pytest-xdist workers."""
    global _AHEAD
    cache = jax.config.jax_compilation_cache_dir
    if os.environ.get("PYTEST_XDIST_WORKER"):
        # under pytest-xdist the workers already keep both cores busy
        yield
        return
    if all(item.get_closest_marker("slow") for item in request.session.items):
        # the slow tier alone (.ci/run runs it in two processes): the modules'
        # compile_ahead builds their default tests' programs, none of these
        yield
        return
    modules = [getattr(item, "module", None) for item in request.session.items]
    names = list(dict.fromkeys(m.__name__ for m in modules if m is not None and hasattr(m, "compile_ahead")))
    if names and modules and modules[0] is not None and modules[0].__name__ == names[0]:
        names = names[1:]
    if not cache or not names or (os.cpu_count() or 1) < 2:
        yield
        return
    _AHEAD = _AheadProcess(names, cache, tmp_path_factory.getbasetemp() / "compile_ahead.log")
    yield
    _AHEAD.stop()
    _AHEAD = None


@pytest.fixture(scope="module", autouse=True)
def _ahead_of_the_tests(request, _compile_ahead):
    """Each module, as it starts, tells the compile-ahead process (above)."""
    if _AHEAD is not None and request.module is not None:
        _AHEAD.reached(request.module.__name__)


def paper_model():
    """The paper model with the accurate solver, one per process: the session's ``model``."""
    global _PAPER_MODEL
    if _PAPER_MODEL is None:
        _PAPER_MODEL = jaxsync.load_model(solver="accurate")
    return _PAPER_MODEL


_PAPER_MODEL = None


@pytest.fixture(scope="session")
def model():
    return paper_model()


@pytest.fixture(scope="session")
def unrolled_model():
    """The unrolled solver (one Newton iteration per solve), kept as a reference."""
    return jaxsync.load_model(solver="unrolled")


def make_forward_sense(model):
    """jit(mjx.forward, then sense)."""
    index = model.index

    @jax.jit
    def fn(mx, d):
        d = mjx.forward(mx, d)
        return d, jaxsync.sense(mx, d, index)

    return fn


@pytest.fixture(scope="session")
def forward_sense(model):
    """``make_forward_sense``: one compile for the session."""
    return make_forward_sense(model)


# The tests' task is jaxsync.short_task() (the tuner's and the benchmark's too),
# rolled out for its shortest horizon with a settled window: every phase, hold
# from 1.2 s, settled from 1.5 s.
TEST_DURATION = 1.7


def fake_heldout_metrics():
    """What a stand-in for the held-out evaluator returns: two held scenarios'
    metrics, those the tuner's scoring reads (``optimize.loss.eval_summary``)."""
    fields = ("settled_peak_resultant_N", "grip_force_error_rel", "dropped", "nonfinite", "chattering")
    fields += ("first_impact_peak_N",)
    return collections.namedtuple("FakeMetrics", fields)(
        settled_peak_resultant_N=np.array([0.01, 0.02]),
        grip_force_error_rel=np.array([0.004, 0.006]),
        dropped=np.zeros(2, bool),
        nonfinite=np.zeros(2, bool),
        chattering=np.zeros(2, bool),
        first_impact_peak_N=np.array([6.0, 7.0]),
    )


def ctrl_c_in_a_gc_callback() -> None:
    """A Ctrl-C that lands inside a garbage-collection callback (JAX frees
    buffers from one): CPython reports an exception raised there as
    "Exception ignored in ..." and goes on."""

    def callback(phase, info):
        gc.callbacks.remove(callback)
        signal.raise_signal(signal.SIGINT)  # the handler runs here, before raise_signal returns

    gc.callbacks.append(callback)
    gc.collect()


def fast_scenario(**overrides):
    return short_task(**overrides)


@pytest.fixture(scope="session")
def rollouts(model):
    """Rollouts of the fast scenario, computed once per session and shared."""
    assert min_duration(fast_scenario()) == TEST_DURATION

    g = default_gains()
    s = fast_scenario()
    run = lambda gains, **kw: jax.block_until_ready(rollout(model, gains, s, duration=TEST_DURATION, **kw))  # noqa: E731
    return {
        "scenario": s,
        "gains": g,
        "classical": run(g, controller="classical"),
        "synchronous": run(g, controller="synchronous"),
        "neutral": run(classical_equivalent(g), controller="synchronous", cross_term="none"),
        "object_impedance": run(g, controller="object_impedance"),
        "task_space": run(g, controller="task_space"),
    }


@pytest.fixture(scope="session")
def shared_rollout():
    """``jaxsync.sim.rollout.rollout`` with the same signature, memoised for the
    session on the values of its arguments: the MuJoCo C rollouts (about a
    second each, a Python loop over the steps) and the MJX ones that several
    tests need (the backends' agreement, both sim-to-sim checks) run once.
    Tests pass it where ``rollout`` is called, or put it in place of
    ``jaxsync.sim.crosscheck.rollout``."""

    def digest(tree):
        h = hashlib.sha256()
        for x in jax.tree_util.tree_leaves(tree):
            if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
                x = jax.random.key_data(x)
            x = np.asarray(x)
            h.update(str((x.dtype, x.shape)).encode() + x.tobytes())
        return h.hexdigest()

    memo, signature = {}, inspect.signature(_rollout.rollout)

    def fn(model, gains, scenario, **kw):
        bound = signature.bind(model, gains, scenario, **kw)
        bound.apply_defaults()  # the same call, whichever defaults it spelled out
        kw = {k: v for k, v in bound.arguments.items() if k not in ("model", "gains", "scenario")}
        key = (id(model), digest(gains), digest(scenario), tuple(sorted(kw.items())))
        if key not in memo:
            memo[key] = jax.block_until_ready(_rollout.rollout(model, gains, scenario, **kw))
        return memo[key]

    return fn


@pytest.fixture(scope="session")
def tuning_program(model):
    """``build_tuning_program``, once for the session."""
    return build_tuning_program(model)


def build_tuning_program(model):
    """``jaxsync tune``'s own gradient program:
    its defaults (the full 4 s task, 2000 steps, the exact full-horizon
    gradient), batch 2, through ``traced_value_and_grad`` as ``tune()`` builds
    it, so that a ``tune()`` call in a test with the same configuration gets the
    same program back (traced form from disk, executable from the persistent
    cache). Used by the full-task gradient check (test_gradient) and the
    resumed-run test (test_tune)."""
    cfg = tune_mod.TuneConfig(batch=2)
    spec, base, weights = cfg.problem.tuned, default_gains(), cfg.problem.weights
    loss = loss_mod.make_loss(model, base, cfg)
    scen = sample_scenarios(jax.random.key(7), cfg.training.batch, training_base(cfg.training)[0])
    theta0 = spec.init(base)
    value_and_grad = loss_mod.traced_value_and_grad(loss, model, base, cfg, (theta0, scen), None)
    return {
        "cfg": cfg,
        "spec": spec,
        "base": base,
        "weights": weights,
        "loss": loss,
        "theta0": theta0,
        "scenarios": scen,
        "value_and_grad": value_and_grad,
    }


def fake_study_parts(monkeypatch):
    """A study's tuning runs and held-out rollouts replaced by stand-ins: each
    controller's settled peaks are a fixed multiple of the classical one's.
    Returns the runs tuned, (controller, first-impact bound, seed, resumed),
    and a dict of what the stand-ins were given (``tuned``: each run's
    controller, starting gains and scenario settings; ``evaluated``: each
    controller, gains and scenarios scored), in which a test may also set
    ``at`` (the run that raises KeyboardInterrupt) or ``ctrl_c_lost_at``."""
    scale = {"classical": 1.0, "synchronous": 0.25, "object_impedance": 0.9, "task_space": 0.5, "ros2_synchronous": 0.3}
    calls = []
    n = 4

    def fake_evaluator(model, duration, controller="synchronous", **stack):
        seen.setdefault("stacks", []).append(stack)

        def evaluate(g, scenarios):
            seen.setdefault("evaluated_k_rk", {})[controller] = float(g.k_rk)
            seen.setdefault("evaluated", []).append((controller, g, scenarios))
            peaks = np.linspace(0.05, 0.08, n) * scale[controller]
            fields = {f: np.full(n, 0.01) for f in Metrics._fields}
            fields.update(
                settled_peak_resultant_N=peaks,
                dropped=np.zeros(n, bool),
                nonfinite=np.zeros(n, bool),
                chattering=np.zeros(n, bool),
                first_impact_peak_N=np.full(n, 6.0),
                drop_time_s=np.full(n, np.nan),
            )
            return Metrics(**fields)

        return evaluate

    def fake_tune(model, base, cfg, *, out, resume, restart, before, **kw):
        calls.append((cfg.problem.controller, cfg.problem.max_impact_N, cfg.data.seed, resume))
        seen.setdefault("tuned_from_k_rk", {})[cfg.problem.controller] = float(base.k_rk)
        seen.setdefault("tuned", []).append((cfg.problem.controller, base, dict(cfg.training.scenario)))
        seen.setdefault("tune_stacks", []).append((cfg.stack(), cfg.data.servo_spread))
        if len(calls) == seen.get("at"):
            raise KeyboardInterrupt
        if len(calls) == seen.get("ctrl_c_lost_at"):
            ctrl_c_in_a_gc_callback()  # Python's own handler: lost, and the run goes on
        after = dict(before)
        after["metrics"] = dict(before["metrics"])
        after["metrics"]["settled_peak_resultant_N"] = [0.5 * x for x in before["metrics"]["settled_peak_resultant_N"]]
        after["within_bounds"] = True
        summary = {"heldout_before": before, "heldout_after": after, "controller": cfg.problem.controller, "bounds": {}}
        # converged unless a test sets ``unconverged``: then stopped at its cap
        stopped = seen.get("unconverged", False)
        summary["iterations"] = cfg.loop.iterations
        summary["convergence"] = {
            "converged": not stopped,
            "reason": "cap" if stopped else "plateau",
            "iterations": cfg.loop.iterations,
            "criterion": {"plateau_tol": cfg.loop.plateau_tol, "plateau_validations": cfg.loop.plateau_validations},
        }
        os.makedirs(out, exist_ok=True)
        with open(os.path.join(out, "summary.json"), "w") as f:
            json.dump(summary, f)
        open(os.path.join(out, "checkpoint.npz"), "wb").close()  # a finished run's, which a continued run resumes
        return types.SimpleNamespace(to_dict=lambda: summary)

    seen = {}
    monkeypatch.setattr(loss_mod, "make_evaluator", fake_evaluator)
    monkeypatch.setattr(pipeline_mod, "tune_and_evaluate", fake_tune)
    return calls, seen
