"""Gradient-based gain tuning through MJX rollouts (``jaxsync tune``).

Each iteration: sample a batch of randomised scenarios (seeded by the
iteration, so a resumed run sees the same batches), take ``jax.value_and_grad``
of the mean cost through the batched closed-loop rollouts on the
differentiable solver setting, skip non-finite gradients, and apply an optax
update to the unconstrained parameters (optimize/params.py). Held-out
scenarios from another seed, on the accurate solver and the full task, are
evaluated before and after.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pickle
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxsync.optimize.cost import CostWeights, cost, cost_terms
from jaxsync.optimize.params import TuneSpec

from jaxsync import _gains, _io, _metrics, _scenario
from jaxsync._cache import traced_on_disk
from jaxsync._errors import ConfigError, JaxsyncError
from jaxsync._rollout import make_rollout

# TuneConfig fields the training loss's program depends on (the rest steer the loop)
_PROGRAM_FIELDS = ("train_duration", "eval_duration", "truncate_every", "train_start", "train_task", "task", "batch")


class TuneError(JaxsyncError):
    """Tuning cannot go on (e.g. gradients kept being non-finite)."""


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    iterations: int = 60
    batch: int = 4
    learning_rate: float = 0.05
    optimizer: str = "adam"
    schedule: str = "cosine"  # or "constant"
    clip_norm: float = 1.0
    seed: int = 0
    heldout_seed: int = 1000
    heldout_batch: int = 16
    train_duration: float = 2.0  # of the "short" task; the "full" task runs eval_duration
    eval_duration: float = 4.0
    truncate_every: int | None = 100
    checkpoint_every: int = 5
    max_bad_steps: int = 3
    train_start: str = "approach"  # keyframe the training rollouts start from
    train_task: tuple = ()  # (field, value) overrides of the training task
    task: str = "full"  # "full": the default task, as held out; "short": training_task() (2 s)
    validate_every: int = 5  # iterations between validation evaluations (0: none, keep the last iterate)
    validation_seed: int = 500
    validation_batch: int = 16

    def validate(self) -> TuneConfig:
        if self.learning_rate <= 0 or not math.isfinite(self.learning_rate):
            raise ConfigError(f"learning rate must be positive, got {self.learning_rate}")
        for name in ("iterations", "batch", "heldout_batch", "checkpoint_every", "max_bad_steps", "validation_batch"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name.replace('_', ' ')} must be a positive integer, got {getattr(self, name)}")
        if self.validate_every < 0:
            raise ConfigError(f"validate every must be 0 (off) or a positive integer, got {self.validate_every}")
        if len({self.seed, self.heldout_seed, self.validation_seed}) < 3:
            raise ConfigError(
                f"the training, validation and held-out seeds must differ (got {self.seed}, "
                f"{self.validation_seed}, {self.heldout_seed}): held-out scenarios are never trained on or selected on"
            )
        if not hasattr(optax, self.optimizer) or self.optimizer.startswith("_"):
            raise ConfigError(
                f"optimizer must name an optax optimiser (adam, adamw, sgd, lion, ...), got {self.optimizer!r}"
            )
        if self.task not in ("short", "full"):
            raise ConfigError(f"training task must be 'short' or 'full', got {self.task!r}")
        if self.schedule not in ("cosine", "constant"):
            raise ConfigError(f"schedule must be 'cosine' or 'constant', got {self.schedule!r}")
        return self


# ---------------------------------------------------------------- scenarios


def training_task(**overrides) -> _scenario.Scenario:
    """The short task tuning rolls out (2 s: close 0.3, squeeze 0.4, lift 0.5,
    hold; metrics from 1.5 s). The squeeze is long enough for the grip force to
    settle: with a 0.2 s squeeze the unsettled grip error dominated the cost
    and its gradient pushed k_rl, k_ll up, the opposite of what lowers the
    resultant on the full task (measured)."""
    values = dict(t_close=0.3, t_squeeze=0.4, t_carry=0.5, settle_time=0.3, lift=[0.02, 0.0, 0.05])
    values.update(overrides)
    return _scenario.default_scenario(**values)


def training_base(cfg: TuneConfig) -> tuple[_scenario.Scenario, float]:
    """The training scenario family's base and its rollout duration."""
    if cfg.task == "full":
        return _scenario.default_scenario(**dict(cfg.train_task)), cfg.eval_duration
    return training_task(**dict(cfg.train_task)), cfg.train_duration


def sample_scenarios(key: jax.Array, n: int, base: _scenario.Scenario) -> _scenario.Scenario:
    """A batch of randomised scenarios around ``base``: object mass +-30 % (the
    controller keeps the nominal estimate), offset along the clamping axis
    +-5 mm, contact time constant 15-30 ms, friction 0.8-1.2, wrist force
    noise 0.05-0.15 N, fresh noise keys."""
    ks = jax.random.split(key, 7)
    u = lambda k, lo, hi: jax.random.uniform(k, (n,), minval=lo, maxval=hi, dtype=jnp.float64)  # noqa: E731
    rep = lambda x: jnp.broadcast_to(x, (n, *jnp.shape(x)))  # noqa: E731
    batch = jax.tree_util.tree_map(rep, base)
    offset = jnp.zeros((n, 3)).at[:, 1].set(u(ks[1], -0.005, 0.005))
    noise_keys = jax.vmap(lambda k: jax.random.key_data(k))(jax.random.split(ks[6], n)).astype(jnp.uint32)
    return batch._replace(
        object_mass=base.object_mass * u(ks[0], 0.7, 1.3),
        object_offset=offset,
        contact_timeconst=u(ks[2], 0.015, 0.03),
        friction=u(ks[3], 0.8, 1.2),
        force_noise=u(ks[4], 0.05, 0.15),
        noise_key=noise_keys,
    )


# ------------------------------------------------------------------- pieces


def make_loss(diff_model, spec: TuneSpec, base: _gains.Gains, cfg: TuneConfig, weights: CostWeights):
    """loss(theta, scenarios) -> (mean cost, mean cost terms), jit- and grad-ready."""
    fn = make_rollout(
        diff_model,
        "synchronous",
        training_base(cfg)[1],
        remat=True,
        truncate_every=cfg.truncate_every,
        start=cfg.train_start,
    )

    def one(gains, s):
        traj = fn(gains, s)
        return cost(traj, s, weights), cost_terms(traj, s, weights)

    def loss(theta, scenarios):
        gains = spec.to_gains(theta, base)
        c, terms = jax.vmap(one, in_axes=(None, 0))(gains, scenarios)
        return c.mean(), jax.tree_util.tree_map(jnp.mean, terms)

    return loss


def make_evaluator(model, duration: float):
    """evaluate(gains, scenarios) -> batched Metrics on the full task (accurate solver)."""
    fn = make_rollout(model, "synchronous", duration)
    return jax.jit(jax.vmap(lambda g, s: _metrics.summarize(fn(g, s), s), in_axes=(None, 0)))


def make_optimizer(cfg: TuneConfig) -> optax.GradientTransformation:
    lr = (
        optax.cosine_decay_schedule(cfg.learning_rate, cfg.iterations, alpha=0.1)
        if cfg.schedule == "cosine"
        else cfg.learning_rate
    )
    return optax.chain(optax.clip_by_global_norm(cfg.clip_norm), getattr(optax, cfg.optimizer)(lr))


def heldout_scenarios(cfg: TuneConfig) -> _scenario.Scenario:
    """Full-task scenarios from the held-out seed (never used for training or selection)."""
    return sample_scenarios(jax.random.key(cfg.heldout_seed), cfg.heldout_batch, _scenario.default_scenario())


def validation_scenarios(cfg: TuneConfig) -> _scenario.Scenario:
    """Full-task scenarios from the validation seed: they pick the iterate, the
    held-out ones only score it."""
    return sample_scenarios(jax.random.key(cfg.validation_seed), cfg.validation_batch, _scenario.default_scenario())


def select_iterate(validation: list[dict]) -> dict | None:
    """The validated iterate with the lowest settled peak resultant whose grip
    error is not worse than the start's (the first entry, which therefore always
    qualifies). Entries: {"iteration", "settled_peak_resultant_N",
    "grip_force_error_rel", "dropped", "nonfinite", ...}."""
    if not validation:
        return None
    grip0 = validation[0]["grip_force_error_rel"]
    ok = [
        v
        for v in validation
        if v["settled_peak_resultant_N"] is not None
        and not v["dropped"]
        and not v["nonfinite"]
        and (v is validation[0] or v["grip_force_error_rel"] <= grip0)
    ]
    return min(ok, key=lambda v: v["settled_peak_resultant_N"]) if ok else validation[0]


def _eval_summary(m) -> dict:
    m = jax.tree_util.tree_map(np.asarray, m)
    kept = ~(m.dropped | m.nonfinite)
    mean = lambda x: float(np.mean(x[kept])) if kept.any() else None  # noqa: E731
    return {
        "settled_peak_resultant_N": mean(m.settled_peak_resultant_N),
        "grip_force_error_rel": mean(m.grip_force_error_rel),
        "dropped": int(m.dropped.sum()),
        "nonfinite": int(m.nonfinite.sum()),
        "per_scenario_peak_N": m.settled_peak_resultant_N.tolist(),
    }


# -------------------------------------------------------------- checkpoints


def _save_checkpoint(path: str, state: dict) -> None:
    _io.atomic_write_bytes(path, pickle.dumps(jax.tree_util.tree_map(np.asarray, state)))


def _load_checkpoint(path: str) -> dict:
    try:
        with open(path, "rb") as f:
            return pickle.load(f)
    except FileNotFoundError:
        raise ConfigError(f"--resume: no checkpoint at {path}") from None
    except (OSError, pickle.UnpicklingError, EOFError) as err:
        raise ConfigError(f"--resume: cannot read checkpoint {path}: {err}") from None


# ---------------------------------------------------------------- the loop


def tune(
    diff_model,
    spec: TuneSpec,
    base: _gains.Gains,
    cfg: TuneConfig,
    weights: CostWeights | None = None,
    *,
    out: str | None = None,
    resume: bool = False,
    fingerprint: dict | None = None,
    progress: bool = True,
    on_iteration: Callable | None = None,
    validate: Callable | None = None,
):
    """Run the optimisation loop; returns (tuned gains, history rows, state).

    With ``validate`` (gains -> an evaluation dict, see :func:`select_iterate`)
    the start and every ``cfg.validate_every`` iterations (and the last) are
    evaluated, and the returned gains are the selected iterate's; without it,
    the last iterate's. ``state["validation"]`` lists the evaluations,
    ``state["selected"]`` the chosen one.

    Checkpoints (``out/checkpoint.pkl``) every ``cfg.checkpoint_every``
    iterations and on Ctrl-C; ``resume`` continues from the last one and ends
    where an uninterrupted run with the same seed ends.
    """
    from tqdm import tqdm

    cfg.validate()
    weights = weights if weights is not None else CostWeights()
    loss = make_loss(diff_model, spec, base, cfg, weights)
    value_and_grad = None  # built at the first step, from its arguments

    def build_value_and_grad(theta, scen):
        """jit(value_and_grad(loss)), its traced form kept on disk between runs
        (``jaxsync._cache.traced_on_disk``), keyed by everything the loss closes over."""
        import hashlib

        with open(diff_model.path, "rb") as f:
            model_hash = hashlib.sha256(f.read()).hexdigest()
        program = {k: v for k, v in dataclasses.asdict(cfg).items() if k in _PROGRAM_FIELDS}
        key = repr(
            (
                "tune.value_and_grad",
                spec.describe(),
                _gains.to_dict(base),
                program,
                tuple(weights),
                diff_model.path,
                model_hash,
                diff_model.solver,
            )
        )
        return traced_on_disk(jax.value_and_grad(loss, has_aux=True), (theta, scen), key, log=bar.write)

    opt = make_optimizer(cfg)
    train_base = training_base(cfg)[0]
    ckpt = os.path.join(_io.ensure_writable_dir(out), "checkpoint.pkl") if out else None

    if resume:
        state = _load_checkpoint(ckpt)
        if fingerprint is not None and state.get("fingerprint") != fingerprint:
            raise ConfigError(
                f"--resume: {ckpt} was written by a run with other options; its options: {state.get('fingerprint')}"
            )
        theta = jax.tree_util.tree_map(jnp.asarray, state["theta"])
        opt_state = jax.tree_util.tree_map(jnp.asarray, state["opt_state"])
        opt_state = jax.tree_util.tree_unflatten(
            jax.tree_util.tree_structure(opt.init(theta)), jax.tree_util.tree_leaves(opt_state)
        )
        history, start, bad = list(state["history"]), int(state["iteration"]), int(state["bad"])
        validation = list(state.get("validation", []))
        kept = {int(k): jax.tree_util.tree_map(jnp.asarray, v) for k, v in state.get("kept", {}).items()}
    else:
        theta = spec.init(base)
        opt_state = opt.init(theta)
        history, start, bad = [], 0, 0
        validation, kept = [], {}

    every = cfg.validate_every if validate is not None else 0

    def run_validation(i):
        """Evaluate the iterate after i steps; keep its parameters while it may be selected."""
        r = {"iteration": i, **validate(spec.to_gains(theta, base))}
        validation.append(r)
        kept[i] = theta
        best = select_iterate(validation)["iteration"]
        for k in [k for k in kept if k != best]:
            del kept[k]
        peak, grip = r["settled_peak_resultant_N"], r["grip_force_error_rel"]
        bar.write(
            f"validation after {i} iterations: settled peak "
            + (f"{peak:.5f} N, grip error {100 * grip:.2f} %" if peak is not None else "n/a (all dropped)")
            + (f", {r['dropped']} dropped" if r.get("dropped") else "")
            + f"; selected so far: iteration {best}"
        )

    def snapshot(i):
        return {
            "theta": theta,
            "opt_state": opt_state,
            "history": history,
            "iteration": i,
            "bad": bad,
            "fingerprint": fingerprint,
            "validation": validation,
            "kept": kept,
        }

    bar = tqdm(total=cfg.iterations, initial=start, disable=not progress, unit="it", dynamic_ncols=True)
    i = start
    try:
        if every and not validation:
            run_validation(0)
        elif every and (start % every == 0 or start == cfg.iterations) and validation[-1]["iteration"] != start:
            run_validation(start)  # interrupted between a step and its validation
        for i in range(start, cfg.iterations):
            scen = sample_scenarios(jax.random.fold_in(jax.random.key(cfg.seed), i), cfg.batch, train_base)
            t0 = time.perf_counter()
            if value_and_grad is None:
                value_and_grad = build_value_and_grad(theta, scen)
            (value, terms), grad = value_and_grad(theta, scen)
            gnorm = float(optax.tree.norm(grad))
            finite = math.isfinite(float(value)) and math.isfinite(gnorm)
            if finite:
                updates, opt_state = opt.update(grad, opt_state, theta)
                theta = optax.apply_updates(theta, updates)
                bad = 0
            else:
                bad += 1
                bar.write(
                    f"iteration {i}: non-finite cost or gradient (cost {float(value)}, |grad| {gnorm}); step skipped"
                )
                if bad >= cfg.max_bad_steps:
                    g = _gains.to_dict(spec.to_gains(theta, base))
                    raise TuneError(
                        f"{bad} non-finite gradients in a row, the last at iteration {i}; stopping. "
                        f"Gains at that point: {g}"
                    )
            row = {
                "iteration": i,
                "cost": float(value),
                "grad_norm": gnorm,
                "skipped": int(not finite),
                "seconds": time.perf_counter() - t0,
                **{f"term_{k}": float(v) for k, v in terms.items()},
            }
            history.append(row)
            bar.set_postfix(cost=f"{float(value):.4g}", grad=f"{gnorm:.3g}")
            bar.update(1)
            if on_iteration is not None:
                on_iteration(i, theta, row)
            if every and ((i + 1) % every == 0 or i + 1 == cfg.iterations):
                run_validation(i + 1)
            if ckpt and ((i + 1) % cfg.checkpoint_every == 0 or i + 1 == cfg.iterations):
                _save_checkpoint(ckpt, snapshot(i + 1))
    except KeyboardInterrupt:
        if ckpt:
            _save_checkpoint(ckpt, snapshot(len(history)))
            bar.write(
                f"interrupted: checkpoint saved to {ckpt} after {len(history)} iterations; "
                "run again with --resume to continue"
            )
        raise
    finally:
        bar.close()
    state = snapshot(cfg.iterations)
    state["last_gains"] = spec.to_gains(theta, base)
    state["selected"] = select_iterate(validation)
    if state["selected"] is not None:
        return spec.to_gains(kept[state["selected"]["iteration"]], base), history, state
    return state["last_gains"], history, state


# -------------------------------------------------------------------- CLI


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


def plot_loss(history: list[dict], path: str, validation: list[dict] | None = None, selected=None) -> None:
    """The training cost and its terms; with validation, a second panel of the
    validation settled peak and grip error, the selected iterate marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    it = [r["iteration"] for r in history]
    panels = 2 if validation else 1
    fig, axes = plt.subplots(panels, 1, figsize=(7, 4 * panels), squeeze=False)
    ax = axes[0, 0]
    ax.semilogy(it, [r["cost"] for r in history], label="batch cost", color="k")
    for k in sorted(k for k in history[0] if k.startswith("term_")):
        ax.semilogy(it, [max(r[k], 1e-12) for r in history], lw=0.8, label=k[5:])
    ax.set_xlabel("iteration")
    ax.set_ylabel("cost (training batch)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if validation:
        ax = axes[1, 0]
        vi = [v["iteration"] for v in validation]
        peak = [v["settled_peak_resultant_N"] or float("nan") for v in validation]
        grip = [100 * (v["grip_force_error_rel"] or float("nan")) for v in validation]
        ax.plot(vi, peak, "o-", color="C0", label="settled peak resultant (N)")
        ax.set_xlabel("iteration")
        ax.set_ylabel("validation settled peak resultant (N)", color="C0")
        ax.grid(alpha=0.3)
        ax2 = ax.twinx()
        ax2.plot(vi, grip, "s--", color="C3", label="grip error (%)")
        ax2.axhline(grip[0], color="C3", lw=0.6, ls=":")
        ax2.set_ylabel("validation grip-force error (%)", color="C3")
        if selected is not None:
            ax.axvline(selected["iteration"], color="k", lw=0.8, ls="--")
            ax.set_title(f"selected iterate: {selected['iteration']}", fontsize=9)
    fig.tight_layout()
    _io.save_figure(fig, path)
    plt.close(fig)


def cmd_tune(args) -> int:
    from jaxsync.optimize.params import TUNABLE

    from jaxsync._model import load_model

    _io.ensure_writable_dir(args.out)
    tuned = _names(args.tune) or list(TuneSpec().tuned)
    frozen = _names(args.freeze)
    unknown = sorted(set(frozen) - set(TUNABLE))
    if unknown:
        raise ConfigError(f"--freeze: unknown parameter(s) {unknown}; tunable: {list(TUNABLE)}")
    spec = TuneSpec(tuned=tuple(n for n in tuned if n not in frozen), per_arm=args.per_arm, isotropic=args.isotropic)
    cfg = TuneConfig(
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
    ).validate()
    weights = _weights(args.weight)
    base = _gains.load(args.gains) if args.gains else _gains.default_gains()
    if args.resume and not os.path.exists(os.path.join(args.out, "checkpoint.pkl")):
        raise ConfigError(f"--resume: no checkpoint at {os.path.join(args.out, 'checkpoint.pkl')}")
    options = {k: v for k, v in vars(args).items() if k != "func"}
    fingerprint = {k: v for k, v in options.items() if k not in ("resume", "iterations", "out", "cache_dir")}

    t_start = time.perf_counter()
    accurate = load_model(args.model, solver="accurate")
    evaluate = make_evaluator(accurate, cfg.eval_duration)
    held = heldout_scenarios(cfg)
    summary_path = os.path.join(args.out, "summary.json")
    before = None
    if args.resume and os.path.exists(os.path.join(args.out, "heldout_before.json")):
        import json

        with open(os.path.join(args.out, "heldout_before.json")) as f:
            before = json.load(f)
    if before is None:
        print(
            f"held-out evaluation before tuning ({cfg.heldout_batch} scenarios, {cfg.eval_duration:g} s)...", flush=True
        )
        before = _eval_summary(evaluate(base, held))
        _io.write_json(os.path.join(args.out, "heldout_before.json"), before)

    diff_model = load_model(args.model, solver="differentiable")
    print(
        f"tuning {', '.join(spec.tuned)}: {cfg.iterations} iterations, batch {cfg.batch} "
        f"(the first iteration compiles the gradient, minutes on a small CPU)",
        flush=True,
    )
    valid = validation_scenarios(cfg)

    def validate(g):
        return _eval_summary(evaluate(g, valid))

    if cfg.validate_every:
        print(
            f"validation: {cfg.validation_batch} full-task scenarios (seed {cfg.validation_seed}) every "
            f"{cfg.validate_every} iterations pick the iterate (lowest settled peak with a grip error not "
            "worse than the start's)",
            flush=True,
        )
    gains, history, state = tune(
        diff_model,
        spec,
        base,
        cfg,
        out=args.out,
        resume=args.resume,
        fingerprint=fingerprint,
        validate=validate if cfg.validate_every else None,
        weights=weights,
    )
    selected = state["selected"]
    if selected is not None:
        print(f"selected iterate: {selected['iteration']} of {len(history)} (by validation)", flush=True)

    print("held-out evaluation after tuning...", flush=True)
    after = _eval_summary(evaluate(gains, held))
    _io.write_json(os.path.join(args.out, "gains.json"), {"gains": _gains.to_dict(gains), "tune": spec.describe()})
    _io.write_json(
        os.path.join(args.out, "gains_last.json"),
        {"gains": _gains.to_dict(state["last_gains"]), "tune": spec.describe()},
    )
    cols = {k: [r[k] for r in history] for k in history[0]} if history else {}
    if cols:
        _io.write_csv(os.path.join(args.out, "history.csv"), cols)
        plot_loss(history, os.path.join(args.out, "loss.png"), state["validation"], selected)
    summary = {
        "initial_cost": history[0]["cost"] if history else None,
        "final_cost": history[-1]["cost"] if history else None,
        "heldout_settled_peak_resultant_N_before": before["settled_peak_resultant_N"],
        "heldout_settled_peak_resultant_N_after": after["settled_peak_resultant_N"],
        "heldout_grip_force_error_rel_before": before["grip_force_error_rel"],
        "heldout_grip_force_error_rel_after": after["grip_force_error_rel"],
        "heldout_before": before,
        "heldout_after": after,
        "wall_time_s": time.perf_counter() - t_start,
        "iterations": len(history),
        "skipped_steps": int(sum(r["skipped"] for r in history)),
        "selected_iteration": selected["iteration"] if selected is not None else len(history),
        "validation": [{k: v for k, v in r.items()} for r in state["validation"]],
        "options": options,
        "weights": weights._asdict(),
        "tune": spec.describe(),
    }
    _io.write_json(summary_path, summary)
    b, a = before["settled_peak_resultant_N"], after["settled_peak_resultant_N"]
    print(f"held-out settled peak resultant: {b:.5f} N -> {a:.5f} N" + (f" ({b / a:.2f}x lower)" if a else ""))
    print(f"held-out grip-force error: {before['grip_force_error_rel']:.4f} -> {after['grip_force_error_rel']:.4f}")
    print(f"results in {args.out}: gains.json (selected), gains_last.json, history.csv, loss.png, summary.json")
    return 0


def add_tune_parser(sub) -> None:
    from jaxsync.optimize.params import TUNABLE

    p = sub.add_parser(
        "tune",
        help="tune the synchronisation and impedance gains by gradient through MJX rollouts",
        description="Gradient-based gain tuning (optax) on batches of randomised scenarios, "
        "evaluated on held-out scenarios before and after.",
    )
    p.add_argument("--iterations", type=int, default=60, help="optimisation steps (60)")
    p.add_argument("--batch", type=int, default=4, help="randomised scenarios per step (4)")
    p.add_argument("--lr", type=float, default=0.05, help="learning rate (0.05)")
    p.add_argument("--optimizer", default="adam", help="an optax optimiser by name (adam)")
    p.add_argument("--schedule", default="cosine", choices=["cosine", "constant"])
    p.add_argument("--clip", type=float, default=1.0, help="global-norm gradient clipping (1.0)")
    p.add_argument(
        "--tune", default=None, help=f"comma-separated parameters to tune (default all: {','.join(TUNABLE)})"
    )
    p.add_argument("--freeze", default=None, help="comma-separated parameters to keep fixed")
    p.add_argument("--per-arm", action="store_true", help="separate impedance parameters per arm")
    p.add_argument("--isotropic", action="store_true", help="one impedance value for translations, one for rotations")
    p.add_argument("--truncate-every", type=int, default=100, help="truncated backprop window, steps (0: none)")
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
        "--weight",
        action="append",
        default=None,
        metavar="NAME=VALUE",
        help="a cost weight (repeatable): resultant_ms, resultant_peak, grip, sync, effort, peak_temperature "
        "(defaults in docs/tuning.md)",
    )
    p.add_argument("--gains", default=None, help="start from this gains JSON (default: built-in)")
    p.add_argument("--model", default=None, help="MJCF file (default: the packaged paper model)")
    p.add_argument("--out", default="results/tune", help="output folder (results/tune)")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint in --out")
    p.set_defaults(func=cmd_tune)
