"""The fair study: every controller at its own optimum, compliance held equal (docs/study.md).

Each controller is tuned with the same method, budget, training seeds and
cost, under each compliance bound (a factor of the default classical
controller's mean first-impact peak and apparent normal stiffness), and all
are scored on one held-out set. A run per (controller, bound, seed), each a
``jaxsync tune`` folder under ``runs/``: a lost study costs only the run it
was computing (that run resumes from its last checkpoint).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys
import time

import jax
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import gains as _gains
from jaxsync.control.names import CONTROLLERS
from jaxsync.io import results as _results
from jaxsync.optimize.studies import study_report as _report
from jaxsync.optimize.studies.compare import check_controllers
from jaxsync.optimize.tuning import loss as _loss
from jaxsync.optimize.tuning import pipeline as _pipeline
from jaxsync.optimize.tuning import scenarios as _scenarios
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.optimize.tuning.tune_state import CHECKPOINT
from jaxsync.runtime import interrupt as _interrupt

STUDY_FILE = "study.json"
# what a setting that a study's file does not hold meant when that study ran (before the setting existed)
ABSENT_MEANS = {"grip_spread": 0.0, "scenario": []}
# what a study writes into its folder (--restart removes these, nothing else)
STUDY_PARTS = ("runs", "defaults", "reference.json", STUDY_FILE, *_report.FILES)
REFERENCE_CONTROLLER = "classical"  # the bounds are factors of its default compliance


STUDY_TUNING = TuneConfig(iterations=10, batch=2, heldout_batch=32, validation_batch=8, grip_spread=0.2)
"""The tuning job every run of a study runs, but for its controller, bounds and seed
(``jaxsync study``'s defaults: 10 L-BFGS iterations on batches of 2, 32 held-out
scenarios, the desired grip force +-20 %: 10 N is 8 to 12 N)."""


@dataclasses.dataclass(frozen=True, init=False)
class StudyConfig:
    """How the study runs (defaults: ``jaxsync study``'s): which controllers,
    bounds and training seeds, and the tuning job each run is (``tuning``,
    a :class:`TuneConfig` whose controller, bounds and seed each run sets).

    Built like a TuneConfig: ``tuning``'s fields may be given by name.

    Example:
      >>> cfg = StudyConfig(controllers=("classical", "synchronous"), seeds=(0,), iterations=2).validate()
      >>> cfg.tuning.loop.iterations
      2
    """

    controllers: tuple[str, ...]
    bounds: tuple[float, ...]  # x the default classical controller's compliance figures
    seeds: tuple[int, ...]  # training seeds, one run each
    bootstrap: int  # resamples of the ratios' 95 % intervals
    tuning: TuneConfig

    def __init__(
        self,
        controllers: tuple[str, ...] = CONTROLLERS,
        bounds: tuple[float, ...] = (0.7, 1.0, 1.5),
        seeds: tuple[int, ...] = (0, 1, 2),
        bootstrap: int = 2000,
        tuning: TuneConfig | None = None,
        **fields,
    ):
        for name, value in (("controllers", tuple(controllers)), ("bounds", tuple(bounds)), ("seeds", tuple(seeds))):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "bootstrap", bootstrap)
        object.__setattr__(self, "tuning", (tuning if tuning is not None else STUDY_TUNING).replace(**fields))

    def replace(self, **fields) -> StudyConfig:
        own = {k: fields.pop(k) for k in ("controllers", "bounds", "seeds", "bootstrap", "tuning") if k in fields}
        now = {"controllers": self.controllers, "bounds": self.bounds, "seeds": self.seeds}
        return StudyConfig(**{**now, "bootstrap": self.bootstrap, "tuning": self.tuning, **own}, **fields)

    def validate(self) -> StudyConfig:
        check_controllers(self.controllers, self.tuning.stack())
        if not self.bounds or any(not (b > 0 and np.isfinite(b)) for b in self.bounds):
            raise ConfigError(f"bounds must be positive factors, e.g. 0.7,1,1.5, got {self.bounds}", inputs=("bounds",))
        if len(set(self.bounds)) != len(self.bounds):
            raise ConfigError(f"bounds names a factor twice: {self.bounds}", inputs=("bounds",))
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise ConfigError(f"seeds must be distinct training seeds, got {self.seeds}", inputs=("seeds",))
        d = self.tuning.data
        clash = sorted(set(self.seeds) & {d.heldout_seed, d.validation_seed})
        if clash:
            raise ConfigError(
                f"seeds {clash} equal the held-out ({d.heldout_seed}) or validation ({d.validation_seed}) "
                "seed: held-out scenarios are never trained on",
                inputs=("seeds",),
            )
        if self.bootstrap < 100:
            raise ConfigError(f"bootstrap must be at least 100 resamples, got {self.bootstrap}", inputs=("bootstrap",))
        for c in self.controllers:
            self.tune_config(c, self.seeds[0], None).validate()  # the tuner's own checks
        return self

    def tune_config(self, controller: str, seed: int, bounds: dict | None) -> TuneConfig:
        """One run's TuneConfig: ``tuning`` with its controller (and that
        controller's own tuned parameters), bounds and seed."""
        return self.tuning.replace(
            problem=dataclasses.replace(
                self.tuning.problem,
                controller=controller,
                spec=None,
                max_impact_N=(bounds or {}).get("max_impact_N"),
                max_stiffness_N_per_m=(bounds or {}).get("max_stiffness_N_per_m"),
            ),
            seed=seed,
        )

    def describe(self) -> dict:
        """Plain JSON (tuples as lists, as they come back from a file): the study's
        own settings and every setting of its tuning job, by name."""
        flat = self.tuning.settings()
        own = {"controllers": self.controllers, "bounds": self.bounds, "seeds": self.seeds, "bootstrap": self.bootstrap}
        return json.loads(json.dumps({**own, **flat}))


def bound_name(factor: float) -> str:
    return f"bound_{factor:g}"


def run_dir(out: str, controller: str, factor: float, seed: int) -> str:
    return os.path.join(out, "runs", controller, bound_name(factor), f"seed_{seed}")


def _prepare(out: str, cfg: StudyConfig, model_name: str, resume: bool, restart: bool) -> None:
    path = os.path.join(out, STUDY_FILE)
    if resume and restart:
        raise ConfigError(
            "resume continues the study in out and restart discards it: give one of them", inputs=("resume", "restart")
        )
    want = {"config": cfg.describe(), "model": model_name}
    if os.path.exists(path):
        with open(path) as f:
            saved = json.load(f)
        if restart:
            for name in STUDY_PARTS:
                target = os.path.join(out, name)
                if os.path.isdir(target):
                    shutil.rmtree(target)
                elif os.path.exists(target):
                    os.unlink(target)
        elif not resume:
            raise ConfigError(
                f"output folder {out!r} holds a study: resume to continue it, or restart to discard it",
                inputs=("resume", "restart"),
            )
        elif _differences(saved, cfg, model_name):
            diff = _differences(saved, cfg, model_name)
            raise ConfigError(
                f"the study in {out!r} was run with other settings ({', '.join(diff)} differ): resume it with "
                "those (a resumed study may add controllers, bounds or seeds), or restart it",
                inputs=("resume", "restart"),
            )
    elif resume:
        raise ConfigError(f"no study in {out!r} to resume", inputs=("resume",))
    _results.write_json(path, want)


def model_label(model) -> str:
    """The model as a study folder records it: by name and fingerprint, so that a
    robot file edited since is another robot."""
    return f"{model.name} ({model.path}, fingerprint {model.fingerprint[:12]})"


# the lists of runs a resumed study may extend: every run is tuned and scored
# on its own (the held-out, validation and reference scenarios do not depend
# on them), and the report is drawn from every run on disk
EXTENSIBLE = ("controllers", "bounds", "seeds")
LONGER = ("iterations", "plateau_tol", "plateau_validations")
"""Settings a resumed study may change: how long its runs go, not what they compute. A finished run that
did not converge continues under them (:func:`continues`)."""


def continues(run: dict, tcfg: TuneConfig) -> bool:
    """Whether a finished tuning run (its ``summary.json``) goes on under ``tcfg``: it stopped at its cap
    unconverged, and the cap is now higher or the convergence criterion other (a resumed run checks the
    criterion before its first step)."""
    c = run.get("convergence") or {}
    if c.get("converged") or c.get("reason") == "lost":
        return False
    k = c.get("criterion") or {}
    other = (k.get("plateau_tol"), k.get("plateau_validations")) != (
        tcfg.loop.plateau_tol,
        tcfg.loop.plateau_validations,
    )
    return tcfg.loop.iterations > int(c.get("iterations", run.get("iterations", 0))) or (bool(c) and other)


def _differences(saved: dict, cfg: StudyConfig, model_name: str) -> list[str]:
    """The settings in which a saved study differs from ``cfg``. A setting
    the file does not hold, also one within another (a cost weight added
    since), counts at its default; a list of ``EXTENSIBLE`` that keeps every
    saved entry and adds others does not differ."""
    default = {**StudyConfig().describe(), **ABSENT_MEANS}
    held = {**default, **(saved.get("config") or {})}
    for k, v in default.items():  # a setting added since (a cost weight) counts at its default too
        if isinstance(v, dict) and isinstance(held[k], dict):
            held[k] = {**v, **held[k]}

    def same(k, v):
        if k in EXTENSIBLE and isinstance(held.get(k), list):
            return set(held[k]) <= set(v)
        return held.get(k) == v

    diff = [k for k, v in cfg.describe().items() if k not in LONGER and not same(k, v)]
    return diff + ([f"model: {saved.get('model')} then, {model_name} now"] if saved.get("model") != model_name else [])


def reference_compliance(model, cfg: StudyConfig, out: str, log) -> dict:
    """The default classical controller's compliance figures: its mean
    first-impact peak over the validation scenarios (the set that selects
    each run's iterate; the held-out set only scores) and its apparent
    normal stiffness. Kept on disk."""
    path = os.path.join(out, "reference.json")
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    tcfg = cfg.tune_config(REFERENCE_CONTROLLER, cfg.seeds[0], None)
    base, data = _gains.default_gains(model, tcfg.training.actuation), tcfg.data
    stack = tcfg.stack().rollout_options(model)
    evaluate = _loss.make_evaluator(model, tcfg.training.eval_duration, REFERENCE_CONTROLLER, **stack)
    log(f"compliance reference: default {REFERENCE_CONTROLLER} on {data.validation_batch} validation scenarios...")
    ev = _loss.eval_summary(evaluate(base, _scenarios.validation_scenarios(tcfg)))
    k = jax.jit(_loss.compliance_fn(model, REFERENCE_CONTROLLER))(base)
    ref = {
        "controller": REFERENCE_CONTROLLER,
        "scenarios": f"{data.validation_batch} validation scenarios (seed {data.validation_seed})",
        "first_impact_peak_N": ev["first_impact_peak_N"],
        "apparent_stiffness_normal_N_per_m": float(k),
    }
    _results.write_json(path, ref)
    return ref


def bounds_for(reference: dict, factor: float) -> dict:
    return {
        "max_impact_N": factor * reference["first_impact_peak_N"],
        "max_stiffness_N_per_m": factor * reference["apparent_stiffness_normal_N_per_m"],
    }


def _evaluate_defaults(model, cfg: StudyConfig, out: str, log) -> dict:
    """Every controller (and the reference) at its default gains on the held-out set, kept on disk."""
    held = _scenarios.heldout_scenarios(cfg.tune_config(REFERENCE_CONTROLLER, cfg.seeds[0], None))
    actuation = cfg.tuning.training.actuation
    stack = cfg.tuning.stack().rollout_options(model)
    out_dir = os.path.join(out, "defaults")
    os.makedirs(out_dir, exist_ok=True)
    found = {}
    for name in dict.fromkeys((REFERENCE_CONTROLLER, *cfg.controllers)):
        path = os.path.join(out_dir, f"{name}.json")
        if os.path.exists(path):
            with open(path) as f:
                found[name] = json.load(f)
            continue
        _interrupt.check()
        t0 = time.perf_counter()
        duration = cfg.tuning.training.eval_duration
        n = cfg.tuning.data.heldout_batch
        log(f"defaults: {name} on {n} held-out scenarios ({duration:g} s; compiles first)...")
        evaluate = _loss.make_evaluator(model, duration, name, **stack)
        base = _gains.default_gains(model, actuation, name)  # a controller's own defaults (ros2_synchronous)
        ev = _loss.eval_summary(evaluate(base, held))
        ev.update(_pipeline.stiffness_figures(jax.jit(_loss.compliance_fn(model, name, axis=None))(base)))
        _results.write_json(path, ev)
        found[name] = ev
        log(f"defaults: {name} done in {time.perf_counter() - t0:.0f} s")
    return found


@_interrupt.deferred()  # Ctrl-C stops at a safe point: between runs, or a run between its iterations
def run_study(
    model,
    cfg: StudyConfig,
    out: str,
    *,
    resume: bool = False,
    restart: bool = False,
    report_only: bool = False,
    log=lambda m: print(m, file=sys.stderr, flush=True),
) -> dict:
    """``jaxsync study``'s job on ``model`` (a robot file's object in every
    scenario); returns the report (``report.json``). With
    ``report_only``, the report of the runs finished so far (a bound whose
    runs are not all done is left out; nothing is tuned): a study can be
    looked at while another process runs it, or after it was stopped."""
    scenario = tuple(cfg.tuning.training.scenario) or _scenarios.model_overrides(model)
    cfg = cfg.replace(scenario=scenario).validate()
    cfg.tuning.stack().substeps(model)  # a control rate that does not divide the physics rate: before any folder
    _results.ensure_writable_dir(out)
    model_name = model_label(model)
    t_start = time.perf_counter()
    if report_only:
        if not os.path.exists(os.path.join(out, STUDY_FILE)):
            raise ConfigError(f"no study in {out!r} to report on", inputs=("report_only",))
        return _report_so_far(model, cfg, out, model_name, t_start, log)
    with _results.run_lock(out, "study", log=log):
        _prepare(out, cfg, model_name, resume, restart)
        defaults = _evaluate_defaults(model, cfg, out, log)
        reference = reference_compliance(model, cfg, out, log)
        log(
            f"compliance reference (default {REFERENCE_CONTROLLER}): first-impact peak "
            f"{reference['first_impact_peak_N']:.3g} N, apparent normal stiffness "
            f"{reference['apparent_stiffness_normal_N_per_m']:.4g} N/m; bounds x {', '.join(map(str, cfg.bounds))}"
        )
        actuation = cfg.tuning.training.actuation
        jobs = [(c, b, s) for b in cfg.bounds for c in cfg.controllers for s in cfg.seeds]
        runs, took = {}, []
        for k, (controller, factor, seed) in enumerate(jobs):
            _interrupt.check()  # the runs before are kept whole
            where = run_dir(out, controller, factor, seed)
            label = f"[{k + 1}/{len(jobs)}] {controller}, bound x{factor:g}, seed {seed}"
            summary_path = os.path.join(where, "summary.json")
            tcfg = cfg.tune_config(controller, seed, bounds_for(reference, factor))
            if os.path.exists(summary_path):
                with open(summary_path) as f:
                    done = json.load(f)
                if not continues(done, tcfg):
                    runs[(controller, factor, seed)] = done
                    log(f"{label}: done earlier")
                    continue
                log(f"{label}: not converged in {_report.run_iterations(done)} iterations: continued")
            eta = f", about {np.median(took) * (len(jobs) - k) / 60:.0f} min left" if took else ""
            log(f"{label}: tuning{eta}")
            t0 = time.perf_counter()
            resuming = os.path.exists(os.path.join(where, CHECKPOINT))
            runs[(controller, factor, seed)] = _pipeline.tune_and_evaluate(
                model,
                _gains.default_gains(model, actuation, controller),
                tcfg,
                out=where,
                resume=resuming,
                restart=not resuming,
                mujoco_check=False,
                options={"study": out, "controller": controller, "bound": factor, "seed": seed},
                log=lambda m: None,
                before=_before(defaults[controller], tcfg),
            ).to_dict()
            took.append(time.perf_counter() - t0)
            after = runs[(controller, factor, seed)]["heldout_after"]
            log(
                f"{label}: {took[-1]:.0f} s, held-out settled peak {_num(after['settled_peak_resultant_N'])} N, "
                f"within bounds: {_report.run_within_bounds(runs[(controller, factor, seed)])}, "
                f"converged: {_report.run_converged(runs[(controller, factor, seed)])}"
            )
        report = _report.build(cfg, reference, defaults, runs)
        report["wall_time_s"] = time.perf_counter() - t_start
        _report.write(out, report)
    return report


def _report_so_far(model, cfg: StudyConfig, out: str, model_name: str, t_start: float, log) -> dict:
    """The report of the finished runs, without taking the study's lock (its runs are only read)."""
    with open(os.path.join(out, STUDY_FILE)) as f:
        saved = json.load(f)
    diff = _differences(saved, cfg, model_name)
    if diff:
        raise ConfigError(
            f"the study in {out!r} was run with other settings ({', '.join(diff)} differ); name those to report on it",
            inputs=("report_only",),
        )
    paths = {name: os.path.join(out, "defaults", f"{name}.json") for name in cfg.controllers}
    missing = [n for n, p in paths.items() if not os.path.exists(p)] + (
        [] if os.path.exists(os.path.join(out, "reference.json")) else ["reference"]
    )
    if missing:
        raise ConfigError(
            f"the study in {out!r} has not scored the defaults yet ({', '.join(missing)}): nothing to report",
            inputs=("report_only",),
        )
    defaults = {}
    for name, p in paths.items():
        with open(p) as f:
            defaults[name] = json.load(f)
    with open(os.path.join(out, "reference.json")) as f:
        reference = json.load(f)
    runs = {}
    for c in cfg.controllers:
        for b in cfg.bounds:
            for seed in cfg.seeds:
                p = os.path.join(run_dir(out, c, b, seed), "summary.json")
                if os.path.exists(p):
                    with open(p) as f:
                        runs[(c, b, seed)] = json.load(f)
    report = _report.build(cfg, reference, defaults, runs)
    report["wall_time_s"] = time.perf_counter() - t_start
    n = len(cfg.controllers) * len(cfg.bounds) * len(cfg.seeds)
    log(f"report of {len(runs)} of {n} runs; bounds with every run done: {report['bounds_reported']}")
    _report.write(out, report)
    return report


def _before(default_eval: dict, tcfg: TuneConfig) -> dict:
    """The default gains' held-out evaluation as the tuner records it (with its bounds' verdict)."""
    ev = dict(default_eval)
    ev["within_bounds"] = _pipeline.within_bounds(ev, tcfg)
    return ev


def _num(v) -> str:
    return "n/a" if v is None else f"{v:.5f}"
