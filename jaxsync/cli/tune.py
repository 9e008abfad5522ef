"""``jaxsync tune``: gradient-based gain tuning, evaluated on held-out scenarios before and after."""

from __future__ import annotations

import math

from jaxsync._errors import ConfigError
from jaxsync.cli._common import (
    add_controller_argument,
    add_distributed_arguments,
    add_gains_argument,
    add_model_argument,
    model_options,
    model_source,
    positive,
)
from jaxsync.optimize.tuning.cost import CostWeights
from jaxsync.optimize.tuning.methods import METHODS
from jaxsync.optimize.tuning.params import DEFAULT_TUNED_FOR, TUNABLE, TuneSpec


def _weights(items: list[str] | None) -> CostWeights:
    """``--weight NAME=VALUE`` (repeatable) over the defaults of CostWeights."""
    w = CostWeights()
    for item in items or []:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in CostWeights._fields:
            raise ConfigError(f"--weight must be NAME=VALUE with NAME one of {list(CostWeights._fields)}, got {item!r}")
        try:
            v = float(value)
        except ValueError:
            raise ConfigError(f"--weight {name}: not a number: {value!r}") from None
        if not math.isfinite(v) or v < 0 or (name == "peak_temperature" and v <= 0):
            raise ConfigError(f"--weight {name} must be a finite number >= 0 (temperature > 0), got {v}")
        w = w._replace(**{name: v})
    return w


def _names(text: str | None) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()] if text else []


def run(args) -> int:
    # the library is imported here, not at the top: `jaxsync --help` stays fast
    from jaxsync.control import gains as _gains
    from jaxsync.io import gains_file
    from jaxsync.optimize.tuning import pipeline
    from jaxsync.optimize.tuning import tune as tuning
    from jaxsync.physics.model import load_model

    tuned = _names(args.tune) or list(DEFAULT_TUNED_FOR[args.controller])
    frozen = _names(args.freeze)
    unknown = sorted(set(frozen) - set(TUNABLE))
    if unknown:
        raise ConfigError(f"--freeze: unknown parameter(s) {unknown}; tunable: {list(TUNABLE)}")
    spec = TuneSpec(
        tuned=tuple(n for n in tuned if n not in frozen),
        per_arm=args.per_arm,
        isotropic=args.isotropic,
        schedule=args.per_phase,
    )
    cfg = tuning.TuneConfig(
        iterations=args.iterations,
        batch=args.batch,
        learning_rate=args.lr,
        optimizer=args.optimizer,
        schedule=args.schedule,
        clip_norm=args.clip,
        seed=args.seed,
        heldout_seed=args.heldout_seed,
        heldout_batch=args.heldout_batch,
        checkpoint_every=args.checkpoint_every,
        truncate_every=args.truncate_every or None,
        validate_every=args.validate_every,
        validation_seed=args.validation_seed,
        validation_batch=args.validation_batch,
        task=args.task,
        method=args.method,
        popsize=args.popsize,
        sampling=args.sampling,
        controller=args.controller,
        max_impact_N=args.max_impact,
        max_stiffness_N_per_m=args.max_stiffness,
    ).validate()
    weights = _weights(args.weight)
    options = {k: v for k, v in vars(args).items() if k not in ("func", "interrupted_hint")}
    skip = ("resume", "restart", "iterations", "out", "cache_dir", "mujoco_check", "coordinator", "process_id")
    model = load_model(model_source(args), **model_options(args))
    base = gains_file.load_for(args.gains, model, args.any_model) if args.gains else _gains.default_gains(model)
    summary = pipeline.tune_and_evaluate(
        model,
        spec,
        base,
        cfg,
        weights,
        out=args.out,
        resume=args.resume,
        restart=args.restart,
        mujoco_check=args.mujoco_check,
        options=options,
        fingerprint={k: v for k, v in options.items() if k not in skip},
        log=lambda m: print(m, flush=True),
    )
    if summary is None:  # another process than the first of a multi-process run: it wrote nothing
        return 0
    b, a = summary["heldout_settled_peak_resultant_N_before"], summary["heldout_settled_peak_resultant_N_after"]
    gb, ga = summary["heldout_grip_force_error_rel_before"], summary["heldout_grip_force_error_rel_after"]
    print(f"held-out settled peak resultant: {_num(b, '.5f')} N -> {_num(a, '.5f')} N" + change_text(b, a))
    print(f"held-out grip-force error: {_num(gb, '.4f')} -> {_num(ga, '.4f')}")
    if summary["kept_worse_than_start"]:
        print(worse_text(summary))
    if summary["mujoco_check"] is not None:
        print(mujoco_text(summary["mujoco_check"]))
    print(f"results in {args.out}: gains.json (selected), gains_last.json, history.csv, loss.png, summary.json")
    return 0


def worse_text(summary: dict) -> str:
    """The warning that the kept gains score worse than the start (summary["kept_worse_than_start"])."""
    if summary["validation"]:
        kept = f"iteration {summary['selected_iteration']}, selected by validation"
    else:
        kept = "the last iterate: --validate-every 0 selects none"
    return (
        f"WARNING: the kept gains ({kept}) score worse than the starting gains on the held-out scenarios: "
        + "; ".join(summary["kept_worse_than_start"])
        + ". gains.json holds them; the starting gains may be the better choice"
        + ("" if summary["validation"] else " (--validate-every N keeps the best validated iterate)")
    )


def mujoco_text(c: dict) -> str:
    """The MuJoCo C check's line (jaxsync.sim.crosscheck.sim_to_sim's result): both
    improvement factors, flagged when they disagree or an object was dropped."""

    def f(v, fmt):
        return "n/a" if v is None else format(v, fmt)

    head = (
        f"on {c['scenarios']} held-out scenarios, settled peak before -> after: MJX {f(c['mjx_before_N'], '.5f')} -> "
        f"{f(c['mjx_after_N'], '.5f')} N ({f(c['factor_mjx'], '.2f')}x), MuJoCo C {f(c['mujoco_before_N'], '.5f')} -> "
        f"{f(c['mujoco_after_N'], '.5f')} N ({f(c['factor_mujoco'], '.2f')}x): "
    )
    if c["agree"]:
        return head + f"agree within {100 * c['tolerance']:.0f} %"
    why = "; ".join(c.get("problems") or [f"they differ by more than {100 * c['tolerance']:.0f} %"])
    return head + f"WARNING: MuJoCo C and MJX disagree: {why} (docs/export.md)"


def _num(v: float | None, fmt: str) -> str:
    """``v`` formatted, or 'n/a' (every scenario dropped)."""
    return "n/a" if v is None else format(v, fmt)


def change_text(before: float | None, after: float | None) -> str:
    """' (2.73x lower)', ' (8.66x higher)' or ' (unchanged)': the factor always
    above 1 as printed, the direction in words."""
    if not before or not after:
        return ""
    if f"{before / after:.2f}" == "1.00":
        return " (unchanged)"
    if after <= before:
        return f" ({before / after:.2f}x lower)"
    return f" ({after / before:.2f}x higher)"


def add_parser(sub) -> None:
    p = sub.add_parser(
        "tune",
        help="tune the synchronisation and impedance gains by gradient through MJX rollouts",
        description="Gradient-based gain tuning (optax) on batches of randomised scenarios, "
        "evaluated on held-out scenarios before and after.",
    )
    add_controller_argument(p)
    p.add_argument(
        "--max-impact",
        type=positive(float),
        default=None,
        metavar="N",
        help="bound the mean first-impact peak pad force, N (docs/metrics.md; default unbounded)",
    )
    p.add_argument(
        "--max-stiffness",
        type=positive(float),
        default=None,
        metavar="N_PER_M",
        help="bound the apparent stiffness along the pad normal, N/m (docs/metrics.md; default unbounded)",
    )
    p.add_argument("--iterations", type=int, default=60, help="optimisation steps (60)")
    p.add_argument(
        "--batch",
        type=int,
        default=4,
        help="randomised scenarios per step (4); per process in a multi-process run, which trains on all of them",
    )
    p.add_argument("--lr", type=float, default=0.05, help="learning rate (0.05)")
    p.add_argument("--optimizer", default="adam", help="an optax optimiser by name (adam)")
    p.add_argument("--schedule", default="cosine", choices=["cosine", "constant"])
    p.add_argument("--clip", type=float, default=1.0, help="global-norm gradient clipping (1.0)")
    p.add_argument(
        "--tune",
        default=None,
        help="comma-separated parameters to tune (default: the controller's own; synchronous "
        f"{','.join(DEFAULT_TUNED_FOR['synchronous'])}; any of {','.join(TUNABLE)})",
    )
    p.add_argument("--freeze", default=None, help="comma-separated parameters to keep fixed")
    p.add_argument("--per-arm", action="store_true", help="separate impedance parameters per arm")
    p.add_argument(
        "--per-phase",
        action="store_true",
        help="a gain schedule: every tuned parameter per task phase (close, squeeze, carry, hold), blended "
        "across the boundaries; with --per-arm, 160 parameters",
    )
    p.add_argument(
        "--method",
        default="lbfgs",
        choices=list(METHODS),
        help="lbfgs (quasi-Newton with a line search; measured fastest to a target, docs/tuning.md), adam "
        "(optax, a fresh batch every iteration; --lr, --optimizer, --schedule and --clip steer it), cmaes, "
        "cmaes-lbfgs (CMA-ES, then L-BFGS); all but adam optimise one fixed batch (lbfgs)",
    )
    p.add_argument("--popsize", type=int, default=16, help="CMA-ES population (16)")
    p.add_argument(
        "--no-mujoco-check",
        dest="mujoco_check",
        action="store_false",
        help="skip rolling the gains before and after out on MuJoCo C (4 held-out scenarios; about a minute)",
    )
    p.add_argument("--isotropic", action="store_true", help="one impedance value for translations, one for rotations")
    p.add_argument(
        "--truncate-every",
        type=int,
        default=0,
        help="truncate backpropagation into windows of this many steps (0, the default: the exact full-horizon "
        "gradient; truncation changed its direction, docs/tuning.md)",
    )
    p.add_argument("--seed", type=int, default=0, help="training scenarios seed (0)")
    p.add_argument("--heldout-seed", type=int, default=1000, help="held-out scenarios seed (1000)")
    p.add_argument("--heldout-batch", type=int, default=16, help="held-out scenarios (16)")
    p.add_argument("--checkpoint-every", type=int, default=5, help="checkpoint period, iterations (5)")
    p.add_argument(
        "--validate-every",
        type=int,
        default=5,
        help="evaluate the iterate on validation scenarios every N iterations and keep the best one "
        "whose grip error is not worse than the start's (5; 0: keep the last iterate)",
    )
    p.add_argument("--validation-seed", type=int, default=500, help="validation scenarios seed (500)")
    p.add_argument("--validation-batch", type=int, default=16, help="validation scenarios (16)")
    p.add_argument(
        "--task",
        default="full",
        choices=["full", "short"],
        help="training task: 'short' (2 s, compressed phases) or 'full' (the 4 s default task the held-out "
        "scenarios use; twice the cost per step of 'short') (full)",
    )
    p.add_argument(
        "--sampling",
        default="stratified",
        choices=["stratified", "iid"],
        help="training batches: 'stratified' holds each scenario range's ends (a batch of 2: the softest and "
        "the stiffest contact, the lightest and the heaviest object, ...), 'iid' draws each scenario "
        "independently (stratified)",
    )
    p.add_argument(
        "--weight",
        action="append",
        default=None,
        metavar="NAME=VALUE",
        help="a cost weight (repeatable): resultant_ms, resultant_peak, grip, sync, effort, peak_temperature "
        "(defaults in docs/tuning.md)",
    )
    add_gains_argument(p, "start from this gains file (default: the model's own)")
    add_model_argument(p)
    add_distributed_arguments(p)
    p.add_argument("--out", default="results/tune", help="output folder (results/tune)")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint in --out")
    p.add_argument(
        "--restart",
        action="store_true",
        help="discard the tuning run in --out (checkpoint and results) and start over; without --resume or "
        "--restart, a folder holding a run is an error",
    )
    p.set_defaults(func=run)
