"""The whole tuning job, as ``jaxsync tune`` runs it, for a Python caller.

:func:`tune_and_evaluate` scores the starting gains on the held-out
scenarios, tunes (:func:`jaxsync.optimize.tuning.tune.tune`, validation picking the
iterate), scores the selected gains on the same held-out scenarios, checks
them on MuJoCo C, and writes the run's folder: ``gains.json`` (selected),
``gains_last.json``, ``history.csv``, ``loss.png``, ``heldout_before.json``,
``summary.json`` (and the loop's checkpoint). It returns a
:class:`TuneSummary`, what ``summary.json`` holds.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import time
from collections.abc import Callable

import jax

from jaxsync._errors import DroppedObjectError
from jaxsync.control import gains as _gains
from jaxsync.control import schedule as _schedule
from jaxsync.io import gains_file
from jaxsync.io import results as _results
from jaxsync.io.export_gains import export_check
from jaxsync.optimize.tuning import loss as _loss
from jaxsync.optimize.tuning import scenarios as _scenarios
from jaxsync.optimize.tuning import tune as _tune
from jaxsync.optimize.tuning.params import check_tuned
from jaxsync.optimize.tuning.tune_report import plot_loss
from jaxsync.optimize.tuning.tune_state import CHECKPOINT, prepare_out
from jaxsync.physics.model import DualArmModel, as_model, identity
from jaxsync.runtime import distributed as _distributed
from jaxsync.runtime import interrupt as _interrupt
from jaxsync.sim import crosscheck as _crosscheck
from jaxsync.sim import scenario as _scenario

HELDOUT_BEFORE = "heldout_before.json"
MUJOCO_CHECK_SCENARIOS = 4
"""Held-out scenarios the MuJoCo C check rolls out (before and after)."""

# history.csv's leading columns, then the cost terms (term_*) by name: a fixed
# order, whatever order a row's keys came in (a resumed run's rows come back
# from the checkpoint in another order)
HISTORY_COLUMNS = ("iteration", "cost", "grad_norm", "skipped", "seconds")


def history_columns(history: list[dict]) -> list[str]:
    """history.csv's header: HISTORY_COLUMNS, then any other keys sorted."""
    keys = {k for r in history for k in r}
    return [k for k in HISTORY_COLUMNS if k in keys] + sorted(keys - set(HISTORY_COLUMNS))


def stiffness_figures(k: dict) -> dict:
    """{"apparent_stiffness_normal_N_per_m": .., "apparent_stiffness_tangential_N_per_m": ..} as floats."""
    return {f"apparent_stiffness_{axis}_N_per_m": float(v) for axis, v in k.items()}


BOUND_MARGIN = 1e-3
"""Relative margin of the compliance bounds: a figure up to bound x (1 + this)
counts as within. The gains a run starts from come back from the tuner's
parametrisation with both arms' impedance shared (their mean: a stiffness
moved by 5e-5 relative was seen), so without it the gains that define a
bound (the study's reference at x1) were counted outside their own bound."""


def bound_excess(evaluation: dict, cfg) -> float:
    """How far an evaluation's compliance figures exceed ``cfg``'s bounds: the
    largest of (mean first-impact peak / its bound, apparent normal
    stiffness / its bound) less one; 0 or below when within (or unbounded)."""
    ratios = [-1.0]
    p = cfg.problem
    for bound, key in ((p.max_impact_N, "first_impact_peak_N"), (p.max_stiffness_N_per_m, STIFF)):
        if bound:
            value = evaluation.get(key)
            ratios.append(float("inf") if value is None else value / bound - 1.0)
    return max(ratios)


def within_bounds(evaluation: dict, cfg) -> bool:
    """Whether an evaluation's mean first-impact peak and apparent normal
    stiffness are within ``cfg``'s compliance bounds, up to the relative
    ``BOUND_MARGIN`` (True when unbounded)."""
    return bound_excess(evaluation, cfg) <= BOUND_MARGIN


STIFF = "apparent_stiffness_normal_N_per_m"
WORSE_BY = 1.005  # a held-out mean this many times the start's counts as worse (0.5 %: past rounding)


def worse_than_start(before: dict, after: dict) -> list[str]:
    """What the kept gains score worse on than the starting gains, on the same
    held-out scenarios (``optimize.loss.eval_summary``'s dicts): the mean
    settled peak resultant and grip-force error (by more than ``WORSE_BY``),
    and the scenarios dropped, diverged or chattering (any more); [] when
    none. Each entry "what: start -> kept"."""
    out = []
    for key, what, fmt, unit in (
        ("settled_peak_resultant_N", "settled peak resultant", ".5f", " N"),
        ("grip_force_error_rel", "grip-force error", ".4f", ""),
    ):
        b, a = before.get(key), after.get(key)
        if b is not None and a is not None and a > WORSE_BY * b:
            out.append(f"{what} {b:{fmt}} -> {a:{fmt}}{unit} ({a / b:.2f}x)" if b > 0 else f"{what} 0 -> {a:{fmt}}")
    for key, what in (
        ("dropped", "scenarios dropped"),
        ("nonfinite", "scenarios diverged"),
        ("chattering", "chattering"),
    ):
        b, a = before.get(key) or 0, after.get(key) or 0
        if a > b:
            out.append(f"{what} {b} -> {a}")
    return out


@dataclasses.dataclass(frozen=True)
class TuneSummary:
    """What a tuning job gives: the kept gains and every figure ``summary.json`` records.

    ``heldout_before`` and ``heldout_after`` are the held-out evaluations
    (``optimize.loss.eval_summary``) of the starting and the kept gains on
    the same scenarios, each with its compliance figures and bounds' verdict.
    """

    gains: object  # the kept gains (the selected iterate's), as gains.json holds them
    last_gains: object  # the last iterate's (gains_last.json)
    config: dict  # TuneConfig.to_dict() of the job
    controller: str
    model: dict  # jaxsync.physics.model.identity
    gains_start: dict
    scenario_base: dict
    bounds: dict
    initial_cost: float | None
    final_cost: float | None
    heldout_before: dict
    heldout_after: dict
    wall_time_s: float
    iterations: int
    skipped_steps: int
    selected_iteration: int
    kept_worse_than_start: list  # worse_than_start: on the held-out scenarios, [] when none
    validation: list
    options: dict
    weights: dict
    tune: dict
    start_moved_into_bands: list
    mujoco_check: dict | None
    stack: dict  # the arms' stack the job ran (jaxsync.sim.actuation.Stack.to_dict, with the servo)
    starts: list = dataclasses.field(default_factory=list)  # a multi-start run's starts (optimize.tuning.starts)
    convergence: dict | None = None  # converged or not, why, at what cost (tune_state.convergence_record)
    deployment: dict | None = None  # position stack: whether the kept gains export (export_gains.export_check)

    @property
    def peak_before(self) -> float | None:
        """Held-out mean settled peak resultant of the starting gains, N (None: all dropped)."""
        return self.heldout_before["settled_peak_resultant_N"]

    @property
    def peak_after(self) -> float | None:
        """Held-out mean settled peak resultant of the kept gains, N."""
        return self.heldout_after["settled_peak_resultant_N"]

    @property
    def grip_error_before(self) -> float | None:
        return self.heldout_before["grip_force_error_rel"]

    @property
    def grip_error_after(self) -> float | None:
        return self.heldout_after["grip_force_error_rel"]

    def to_dict(self) -> dict:
        """``summary.json``'s dict (the gains objects left out: gains.json holds them)."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in ("gains", "last_gains")}
        d["heldout_settled_peak_resultant_N_before"] = self.peak_before
        d["heldout_settled_peak_resultant_N_after"] = self.peak_after
        d["heldout_grip_force_error_rel_before"] = self.grip_error_before
        d["heldout_grip_force_error_rel_after"] = self.grip_error_after
        return d


def job_config(model: DualArmModel, cfg: _tune.TuneConfig) -> tuple[_tune.TuneConfig, list[str]]:
    """``cfg`` as a job on ``model`` runs it (what ``summary.json``'s ``config`` records), checked: the
    model's own object as every scenario's base where none is given, and the parameters the model's
    stack adds to the tuned ones (returned by name: the loop gain where a servo limits it)."""
    if not cfg.training.scenario:  # the model's own object (a robot file's): every scenario's base
        cfg = cfg.replace(scenario=_scenarios.model_overrides(model))
    cfg.validate()
    given = cfg.problem.tuned  # a new TuneSpec on each read where the problem names none: read once
    spec = given.for_model(cfg.problem.controller, model, cfg.training.actuation, cfg.training.control_rate)
    if spec is given:
        return cfg, []
    added = [n for n in spec.tuned if n not in given.tuned]
    return cfg.replace(problem=dataclasses.replace(cfg.problem, spec=spec)), added


@_interrupt.deferred()  # Ctrl-C stops at a safe point (between iterations, after tuning)
def tune_and_evaluate(
    model: DualArmModel,
    base: _gains.Gains,
    cfg: _tune.TuneConfig,
    *,
    out: str,
    resume: bool = False,
    restart: bool = False,
    mujoco_check: bool = True,
    options: dict | None = None,
    fingerprint: dict | None = None,
    log: Callable[[str], None] = print,
    before: dict | None = None,
) -> TuneSummary | None:
    """Tune ``base`` on ``model`` as ``cfg`` says and score it before and after.

    ``out`` is checked before anything is computed: a folder holding a run is
    continued (``resume``) or discarded (``restart``), never overwritten.
    ``options`` (recorded in the summary) and ``fingerprint`` (the options a
    resumed run must share) describe the caller's settings. In a multi-process
    run every process tunes (data-parallel); process 0 alone scores, writes
    and gets the summary, the others get None. ``before``: the held-out
    evaluation of ``base`` (``optimize.loss.eval_summary`` of the same
    held-out scenarios), when the caller already has it.

    Example:
      >>> summary = tune_and_evaluate(jaxsync.load_model(), jaxsync.default_gains(),
      ...                             TuneConfig(iterations=2, task="short"), out="results/tune")  # doctest: +SKIP
      >>> summary.peak_after  # doctest: +SKIP
    """
    cfg, added = job_config(model, cfg)
    main = _distributed.is_main()
    say = log if main else (lambda *a, **k: None)
    spec = cfg.problem.tuned
    if added:
        loop = _gains.default_gains(model, "position")
        say(
            f"{', '.join(added)} {'is' if len(added) == 1 else 'are'} tuned too: this robot's slowest servo holds "
            f"its joint-command loop at lambda = {2 * float(loop.kp_pos) / float(loop.kd_pos):.3g} 1/s by default, "
            "a trade of speed against the delay, and lags an accelerating command by I/k, which the plan's "
            f"acceleration fed forward (ff_acc, 0 by default) cancels (--freeze {','.join(added)} keeps the starting "
            "gains')"
        )
    check_tuned(spec.tuned, cfg.problem.controller)
    spec.init(base)  # a schedule needs a per-phase spec: say so before any folder is touched
    run_args = (model, base, cfg, out, resume, mujoco_check, options, fingerprint, say, main)
    if not main:
        _distributed.barrier("tune: output folder ready")
        return _run(*run_args, before)
    _results.ensure_writable_dir(out)
    with _results.run_lock(out, "tune", log=say):
        prepare_out(out, resume=resume, restart=restart)
        _distributed.barrier("tune: output folder ready")
        before_path = os.path.join(out, HELDOUT_BEFORE)
        wrote_before = not (resume and os.path.exists(before_path))
        try:
            return _run(*run_args, before)
        except Exception:
            # a run that failed before its first checkpoint leaves nothing of value: not even the
            # held-out scores it wrote, which would make the corrected command ask for --restart
            if wrote_before and not os.path.exists(os.path.join(out, CHECKPOINT)):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(before_path)
            raise


def _run(model, base, cfg, out, resume, mujoco_check, options, fingerprint, say, main, given=None):
    t_start = time.perf_counter()
    spec, weights, controller = cfg.problem.tuned, cfg.problem.weights, cfg.problem.controller
    data, eval_duration = cfg.data, cfg.training.eval_duration
    stack = cfg.stack()
    # one physics and one stack: training, validation, held out
    evaluate = _loss.make_evaluator(model, eval_duration, controller, **stack.rollout_options(model))
    held = _scenarios.heldout_scenarios(cfg)
    before_path = os.path.join(out, HELDOUT_BEFORE)
    before = dict(given) if given is not None else None
    if not main:
        before = {}
    elif resume and os.path.exists(before_path):
        with open(before_path) as f:
            before = json.load(f)
    elif before is not None:
        _results.write_json(before_path, before)  # given: the folder holds what a run scoring them would
    if before is None:
        say(f"held-out evaluation before tuning ({data.heldout_batch} scenarios, {eval_duration:g} s)...")
        before = _loss.eval_summary(evaluate(base, held))
        if before["settled_peak_resultant_N"] is None:  # every held-out scenario dropped (or diverged)
            raise DroppedObjectError(
                f"the starting gains drop the object (or diverge) in all {data.heldout_batch} held-out scenarios "
                f"({before['dropped']} dropped, {before['nonfinite']} non-finite): there is no grasp to tune; "
                "start from gains that hold it (the model's defaults, or other gains)",
                inputs=("gains",),
            )
        _results.write_json(before_path, before)
    moved = spec.moved(base)
    if moved:
        raised = spec.deploy_dt is not None and any(m.startswith("imp_mass:") for m in moved)
        say(
            "the starting gains were moved into the tuning bands: "
            + "; ".join(moved)
            + (
                f" (masses raised to the exported rule's stability margin at {spec.deploy_dt:g} s: "
                "jaxsync export refuses the rule beyond it)"
                if raised
                else ""
            )
        )

    say(
        f"tuning {', '.join(spec.tuned)} ({spec.size()} parameters"
        + (", per task phase" if spec.schedule else "")
        + f") with {cfg.method.name}: {cfg.loop.iterations} iterations, batch {cfg.training.batch} "
        + (
            "(the first iteration traces and compiles the gradient: a minute or two on a 2-core CPU, seconds when "
            "the compilation cache holds it; the ETA leaves it out)"
            if cfg.method.name != "cmaes"
            else "(the first iteration compiles the population's rollouts; the ETA leaves it out)"
        )
    )
    valid = _scenarios.validation_scenarios(cfg)

    stiffness = jax.jit(_loss.compliance_fn(model, controller, axis=None))

    def validate(g):
        out = _loss.eval_summary(evaluate(g, valid))
        out.update(stiffness_figures(stiffness(g)))
        out["within_bounds"], out["bound_excess"] = within_bounds(out, cfg), bound_excess(out, cfg)
        return out

    if cfg.loop.validate_every:
        say(
            f"validation: {data.validation_batch} full-task scenarios (seed {data.validation_seed}) every "
            f"{cfg.loop.validate_every} iterations pick the iterate (lowest settled peak with a grip error not "
            "worse than the start's)"
        )
    result = _tune.tune(
        model,
        base,
        cfg,
        out=out,
        resume=resume,
        fingerprint=_fingerprint(model, base, cfg, fingerprint),
        validate=validate if cfg.loop.validate_every else None,
    )
    _interrupt.check()  # the loop's last checkpoint is written: stop before the held-out scoring
    gains, history, selected = result.gains, result.history, result.selected
    if not main:  # process 0 scores and writes; wait until it has
        _distributed.barrier("tune: results written")
        return None
    if selected is not None:
        say(f"selected iterate: {selected['iteration']} of {len(history)} (by validation)")

    say("held-out evaluation after tuning...")
    after = _loss.eval_summary(evaluate(gains, held))
    for which, g in ((before, base), (after, gains)):
        which.update(stiffness_figures(stiffness(g)))
        which["within_bounds"] = within_bounds(which, cfg)
    worse = worse_than_start(before, after)
    deployment = (  # what jaxsync export --format ros2-admittance would say of the kept gains
        export_check(gains, controller, spec.deploy_dt) if cfg.training.actuation == "position" else None
    )
    described = spec.describe()
    for name, g in (("gains.json", gains), ("gains_last.json", result.last_gains)):
        doc = {"gains": _schedule.to_file_dict(g), "controller": controller, "model": identity(model)}
        doc["tune"] = described
        _results.write_json(os.path.join(out, name), doc)
    check = None
    if mujoco_check:
        n = MUJOCO_CHECK_SCENARIOS
        say(f"the same gains on MuJoCo C ({min(n, data.heldout_batch)} held-out scenarios, the same control law)...")
        # MJX's side is the held-out scoring above (the same scenarios and duration), not run again
        mjx_rows = {"before": before.get("per_scenario"), "after": after.get("per_scenario")}
        check = _crosscheck.sim_to_sim(
            model,
            gains,
            base,
            held,
            eval_duration,
            n=n,
            mjx_rows=mjx_rows,
            log=lambda m: None,
            controller=controller,
            stack=stack,
        )
    cols = {k: [r[k] for r in history] for k in history_columns(history)}
    if cols:
        _results.write_csv(os.path.join(out, "history.csv"), cols)
        plot_loss(history, os.path.join(out, "loss.png"), result.validation, selected)
    summary = TuneSummary(
        gains=gains,
        last_gains=result.last_gains,
        config=cfg.to_dict(),
        controller=controller,
        model=identity(model),
        gains_start=_schedule.to_file_dict(base),
        scenario_base=_scenario.to_dict(_scenario.default_scenario(**dict(cfg.training.scenario))),
        bounds={
            "max_impact_N": cfg.problem.max_impact_N,
            "max_stiffness_N_per_m": cfg.problem.max_stiffness_N_per_m,
            "margin_rel": BOUND_MARGIN,
        },
        initial_cost=history[0]["cost"] if history else None,
        final_cost=history[-1]["cost"] if history else None,
        heldout_before=before,
        heldout_after=after,
        wall_time_s=time.perf_counter() - t_start,
        iterations=len(history),
        skipped_steps=int(sum(r["skipped"] for r in history)),
        selected_iteration=selected["iteration"] if selected is not None else len(history),
        kept_worse_than_start=worse,
        validation=[dict(r) for r in result.validation],
        options=options if options is not None else {},
        weights=weights._asdict(),
        tune=described,
        start_moved_into_bands=moved,
        mujoco_check=check,
        stack=stack.to_dict(model),
        convergence=result.convergence,
        deployment=deployment,
    )
    _results.write_json(os.path.join(out, "summary.json"), summary.to_dict())
    _distributed.barrier("tune: results written")
    return summary


_EXTENDABLE = ("iterations", "plateau_tol", "plateau_validations", "grip_floor")
"""The settings a resumed run may change: how long it runs, not what it computes."""


def _fingerprint(model, base, cfg, given: dict | None) -> dict:
    """What a resumed run must share with the checkpoint it continues: every
    setting but the run's length, the starting gains and the model (an edited
    robot file is another robot), with the caller's ``given``."""
    settings = {k: v for k, v in cfg.settings().items() if k not in _EXTENDABLE}
    own = {**settings, "gains_start": _schedule.to_file_dict(base), "model": _identity_text(model)}
    return json.loads(json.dumps({**own, **(given or {})}))


def run_tune(
    model=None,
    cfg: _tune.TuneConfig | None = None,
    *,
    gains=None,
    any_model: bool = False,
    visual: bool = True,
    out: str = "results/tune",
    resume: bool = False,
    restart: bool = False,
    mujoco_check: bool = True,
    options: dict | None = None,
    log: Callable[[str], None] = print,
) -> TuneSummary | None:
    """``jaxsync tune``'s job: ``model`` (a model, an MJCF or robot file, or
    None: the paper model), starting from ``gains`` (a gains file, refused
    when tuned on another model unless ``any_model``; gains; None: the
    model's own defaults on ``cfg``'s stack), tuned as ``cfg`` says (None:
    ``TuneConfig()``), then :func:`tune_and_evaluate` (several runs, the best
    by validation: :func:`jaxsync.optimize.tuning.starts.run_tune`).

    Example:
      >>> cfg = TuneConfig(iterations=2)
      >>> summary = run_tune("mjcf/robots/iiwa14_twice.yaml", cfg, out="results/tune")  # doctest: +SKIP
    """
    model, base, cfg = job_inputs(model, cfg, gains, any_model, visual)
    return tune_and_evaluate(
        model, base, cfg, out=out, resume=resume, restart=restart, mujoco_check=mujoco_check, options=options, log=log
    )


def job_inputs(model, cfg, gains, any_model: bool, visual: bool):
    """:func:`run_tune`'s model, starting gains and config from what it was given,
    checked before any folder is touched."""
    cfg = (cfg if cfg is not None else _tune.TuneConfig()).validate()  # checked before the model compiles
    model = as_model(model, visual=visual)
    base = gains_file.load_or_default(gains, model, any_model, cfg.training.actuation, cfg.problem.controller)
    cfg.stack().substeps(model)  # a control rate that does not divide the physics rate: before any folder
    return model, base, cfg


def _identity_text(model) -> str:
    """A model as a resumed run's fingerprint names it: its name and fingerprint."""
    return f"{model.name} ({model.path}, fingerprint {model.fingerprint[:12]})"
