"""Does the coupling family lower the tuned rule any further? Both continued alike from the rule's optimum.

Reads a finished ``jaxsync study`` folder that tuned ``ros2_admittance``
(e.g. ``--controllers ros2_admittance,...``). For each of its seeds and
bounds, from that run's tuned gains (the coupling family at 0: the rule
alone, exactly), two runs of ``--iterations`` more on the study's own tuning
job (its batches, bounds, held-out set; a fresh training seed, seed + 100,
so that neither replays the batches it was tuned on):

- ``rule``: ros2_admittance, its own parameters (the rule's impedance);
- ``coupled``: ros2_coupled (or ``--family ros2_coupled_direct``), the
  same impedance and the family's four channel gains, starting at 0
  (``--family-only``: the family's gains alone, the impedance kept;
  ``--tune NAMES``: those).

``--from-defaults`` instead starts the coupled run where the study started
its own (the defaults, the study's seed) and compares it with the study's
rule run: e.g. the family less a channel, ``--tune``.

Both runs start from the rule's optimum with each impedance mass raised to
the deployed rule's stability margin (``jaxsync.control.gains.deployable_gains``),
and the tuner holds them there (``TuneSpec.deploy_dt``): every gain compared
is one ``jaxsync export --format ros2-admittance`` writes.

The family contains the rule and both start at the same point with the same
added budget, so a ratio coupled / rule below 1 is what the coupling adds.
Prints and writes per seed and bound the held-out settled peak of both, the
paired ratio over the held-out scenarios with a bootstrap 95 % interval,
drops, whether each run converged, and the lowest validation figure each
run reached without a drop. Selection asks for a grip error no worse than
the start's or at most ``--grip-floor`` (0.1 %: a tuned start's is 0.02-0.07
%, which a continued run rarely keeps exactly), the same for both runs.
With ``--synchronous`` a third run, the paper's coupling on the rule
(``ros2_synchronous`` from k_ik = 0, k_il = 1/2: in the squeeze, the rule's
own offset), goes on from the same start;
else where the study tuned it, its run is taken. Each row then also gives
coupled / synchronous with its interval. Runs go
to L-BFGS's convergence or the cap (``--iterations``, 300).

Which channel does what: the coupled run's selected gains are scored again
on the held-out set with each channel's gain (and block) set to 0 in turn,
``without_<channel>_over_rule`` (1 where the channel was left at 0).
``--reuse`` reads both runs from ``--out`` instead of tuning them;
``--resume`` continues runs stopped there from their checkpoints.

    python experiments/coupling_on_the_rule.py --study results/study_coupling --out results/cor
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os

import jax
import numpy as np

import jaxsync
from jaxsync.control import coupling as C
from jaxsync.control import gains as _gains
from jaxsync.io import gains_file
from jaxsync.optimize.studies import study as S
from jaxsync.optimize.tuning import loss as L
from jaxsync.optimize.tuning import pipeline as P
from jaxsync.optimize.tuning import scenarios as SC
from jaxsync.optimize.tuning.cost import CostWeights
from jaxsync.optimize.tuning.params import FAMILY_GAINS, TuneSpec


def _peaks(summary: dict) -> np.ndarray:
    return np.asarray(summary["heldout_after"]["per_scenario_peak_N"], dtype=float)


def _ratio(a: np.ndarray, b: np.ndarray, n: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """Mean of a over mean of b, paired bootstrap 95 % interval over the scenarios."""
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(a), (n, len(a)))
    boot = a[idx].mean(1) / b[idx].mean(1)
    return float(a.mean() / b.mean()), float(np.quantile(boot, 0.025)), float(np.quantile(boot, 0.975))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--study", required=True)
    p.add_argument("--iterations", type=int, default=300, help="the cap (300); runs stop at convergence")
    p.add_argument(
        "--grip-floor",
        type=float,
        default=0.001,
        help="an iterate qualifies with a grip error no worse than the start's or at most this (0.001: 0.1 %%)",
    )
    p.add_argument("--family", default="ros2_coupled", choices=["ros2_coupled", "ros2_coupled_direct"])
    p.add_argument(
        "--family-only",
        action="store_true",
        help="the coupled run tunes the family's four gains alone, the rule's impedance kept at its optimum",
    )
    p.add_argument("--tune", default="", help="what the coupled run tunes, comma-separated (its defaults)")
    p.add_argument(
        "--from-defaults",
        action="store_true",
        help="the coupled run starts from its defaults on the study's seed, beside the study's own rule run",
    )
    p.add_argument(
        "--batch",
        type=int,
        default=0,
        help="training scenarios per iteration of both runs (default: the study's); a batch of 2 tuned from an "
        "optimum finds gains that drop the object in scenarios it did not train on",
    )
    p.add_argument("--skip-rule", action="store_true", help="reuse the rule runs already in --out")
    p.add_argument(
        "--only",
        choices=["rule", "coupled", "synchronous"],
        help="tune that run alone and stop (one process each on two cores); then --reuse compares them",
    )
    p.add_argument(
        "--synchronous",
        action="store_true",
        help="a third run from the same start: the paper's coupling on the rule (ros2_synchronous from "
        "k_ik = 0, k_il = 1/2) tuned with the impedance, which coupled / synchronous is then taken against",
    )
    p.add_argument("--reuse", action="store_true", help="reuse both runs already in --out (the channels scored anew)")
    p.add_argument("--resume", action="store_true", help="continue runs stopped in --out from their checkpoints")
    p.add_argument(
        "--against-study",
        action="store_true",
        help="tune the coupled run alone and compare it with the study's rule run, not continued (cheaper; "
        "it credits the coupling with what a continued rule would also have found)",
    )
    p.add_argument("--out", default="results/coupling_on_the_rule")
    args = p.parse_args()
    jaxsync.set_xla_flags()
    jax.config.update("jax_enable_x64", True)
    jaxsync.enable_compilation_cache()
    with open(os.path.join(args.study, S.STUDY_FILE)) as f:
        stored = json.load(f)
    flat = dict(stored["config"])
    own = {k: flat.pop(k) for k in ("controllers", "bounds", "seeds", "bootstrap")}
    for k in ("controller", "spec", "max_impact_N", "max_stiffness_N_per_m"):
        flat.pop(k, None)
    flat["iterations"] = args.iterations
    flat["batch"] = args.batch or flat["batch"]
    flat["weights"] = CostWeights(**flat["weights"])
    flat["delay"] = tuple(flat["delay"])
    flat["ft_filter"] = tuple(flat["ft_filter"])
    flat["scenario"] = tuple(tuple(x) for x in flat["scenario"])
    flat["train_scenario"] = tuple(tuple(x) for x in flat["train_scenario"])
    cfg = S.StudyConfig(**own, **flat).validate()
    if "ros2_admittance" not in cfg.controllers:
        raise SystemExit(f"{args.study}: the study did not tune ros2_admittance")
    model_path = stored["model"].split("(")[1].split(",")[0]
    model = jaxsync.load_model(model_path, visual=False)
    rate = cfg.tuning.training.control_rate
    dt = 1.0 / rate if rate else float(model.mj_model.opt.timestep)  # the rule's period
    with open(os.path.join(args.study, "reference.json")) as f:
        reference = json.load(f)
    rows = []
    for factor in cfg.bounds:
        bounds = S.bounds_for(reference, factor)
        for seed in cfg.seeds:
            rule_run = S.run_dir(args.study, "ros2_admittance", factor, seed)
            done = {}
            if args.against_study:  # the study's own rule run is the comparison; the family starts from its gains
                with open(os.path.join(rule_run, "summary.json")) as f:
                    done["rule"] = json.load(f)
                start = gains_file.load(os.path.join(rule_run, "gains.json"))
                jobs = [("coupled", args.family, start, seed + 100)]
            elif args.from_defaults:  # the study's own rule run is the comparison; the family starts where it did
                with open(os.path.join(rule_run, "summary.json")) as f:
                    done["rule"] = json.load(f)
                jobs = [("coupled", args.family, jaxsync.default_gains(model, "position", args.family), seed)]
            else:  # the rule's optimum as it deploys (both runs are held there: TuneSpec.deploy_dt)
                start = _gains.deployable_gains(gains_file.load(os.path.join(rule_run, "gains.json")), dt)
                jobs = [("rule", "ros2_admittance", start, seed + 100), ("coupled", args.family, start, seed + 100)]
                if args.synchronous:  # k_ik = 0, k_il = 1/2: the rule's own offset in the squeeze (ros2_loop)
                    k = {n: 0.0 * start.k_rk + v for n, v in (("k_rk", 0), ("k_lk", 0), ("k_rl", 0.5), ("k_ll", 0.5))}
                    jobs.append(("synchronous", "ros2_synchronous", start._replace(**k), seed + 100))
            for label, controller, start, train_seed in jobs:
                if args.only and label != args.only:
                    continue
                out = os.path.join(args.out, f"bound_{factor:g}", f"seed_{seed}", label)
                tcfg = cfg.tune_config(controller, train_seed, bounds).replace(grip_floor=args.grip_floor)
                tuned = args.tune.split(",") if args.tune else FAMILY_GAINS if args.family_only else None
                if label == "coupled" and tuned:
                    tcfg = tcfg.replace(problem=dataclasses.replace(tcfg.problem, spec=TuneSpec(tuned=tuple(tuned))))
                if (label == "rule" and args.skip_rule) or args.reuse:
                    with open(os.path.join(out, "summary.json")) as f:
                        done[label] = json.load(f)
                    continue
                done[label] = P.tune_and_evaluate(
                    model,
                    start,
                    tcfg,
                    out=out,
                    resume=args.resume,
                    restart=not args.resume,
                    mujoco_check=False,
                    log=lambda m: None,
                ).to_dict()
            if args.only:
                continue
            r, lo, hi = _ratio(_peaks(done["coupled"]), _peaks(done["rule"]))
            coupled_out = os.path.join(args.out, f"bound_{factor:g}", f"seed_{seed}", "coupled")
            without = _without_each_channel(model, cfg.tune_config(args.family, seed, bounds), coupled_out)
            rule_mean = float(np.nanmean(_peaks(done["rule"])))
            sync_run = os.path.join(S.run_dir(args.study, "ros2_synchronous", factor, seed), "summary.json")
            sync = {}
            if "synchronous" in done or os.path.exists(sync_run):
                done_sync = done["synchronous"] if "synchronous" in done else _load(sync_run)
                rs, ls, hs = _ratio(_peaks(done["coupled"]), _peaks(done_sync))
                rr, lr, hr = _ratio(_peaks(done_sync), _peaks(done["rule"]))
                sync = {
                    "synchronous_N": done_sync["heldout_settled_peak_resultant_N_after"],
                    "synchronous_converged": done_sync["convergence"]["converged"],
                    "synchronous_iterations": done_sync["convergence"]["iterations"],
                    "coupled_over_synchronous": rs,
                    "ci95_synchronous": [ls, hs],
                    "synchronous_over_rule": rr,
                    "ci95_synchronous_over_rule": [lr, hr],
                }
            row = {
                "bound": factor,
                "seed": seed,
                "start_N": done["rule"]["heldout_settled_peak_resultant_N_before"],
                **{
                    f"{k}_{what}": v
                    for k, d in done.items()
                    for what, v in (
                        ("N", d["heldout_settled_peak_resultant_N_after"]),
                        ("dropped", d["heldout_after"]["dropped"]),
                        ("converged", d["convergence"]["converged"]),
                        ("iterations", d["convergence"]["iterations"]),
                        ("selected", d["selected_iteration"]),
                        ("seconds", d["convergence"]["seconds"]),
                    )
                },
                **{
                    f"{k}_best_validated_N": min(
                        (v["settled_peak_resultant_N"] for v in d["validation"][1:] if not v["dropped"]),
                        default=None,
                    )
                    for k, d in done.items()
                },
                "coupled_over_rule": r,
                "ci95": [lo, hi],
                **sync,
                **{f"without_{c}_over_rule": v / rule_mean if v is not None else None for c, (v, _) in without.items()},
                **{f"without_{c}_dropped": d for c, (_, d) in without.items()},
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.only:  # the other run, and the comparison, come from --reuse
        return
    a = np.concatenate([_peaks_of(args.out, r, "coupled") for r in rows])
    b = np.concatenate(
        [
            _peaks_of(args.out, r, "rule")
            if not (args.from_defaults or args.against_study)
            else _peaks(
                _load(os.path.join(S.run_dir(args.study, "ros2_admittance", r["bound"], r["seed"]), "summary.json"))
            )
            for r in rows
        ]
    )
    pooled = _ratio(a, b)
    result = {
        "study": args.study,
        "family": args.family,
        "iterations": args.iterations,
        "grip_floor": args.grip_floor,
        "batch": cfg.tuning.training.batch,
        "from_defaults": args.from_defaults,
        "tuned": args.tune or ("family only" if args.family_only else "defaults"),
        "rows": rows,
        "pooled": pooled,
    }
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "coupling_on_the_rule.json"), "w") as f:
        json.dump(result, f, indent=1)
    print("pooled coupled / rule:", pooled)


def _without_each_channel(model, tcfg, coupled_out: str) -> dict:
    """Per channel, (held-out mean settled peak, drops) of the coupled run's gains with that channel's gain
    and block at 0; (None, 0) where the channel was 0 already."""
    g = gains_file.load(os.path.join(coupled_out, "gains.json"))
    options = tcfg.stack().rollout_options(model)
    evaluate = L.make_evaluator(model, tcfg.training.eval_duration, tcfg.problem.controller, **options)
    held = SC.heldout_scenarios(tcfg)
    block = np.asarray(g.cpl_block)
    out = {}
    for k, (channel, gain) in enumerate(zip(C.CHANNELS, C.GAIN_FIELDS, strict=True)):
        if not np.any(np.asarray(getattr(g, gain))) and not np.any(block[k]):
            out[channel] = (None, 0)
            continue
        keep = (np.arange(len(C.CHANNELS)) != k)[:, None, None, None]
        cut = g._replace(**{gain: np.zeros_like(np.asarray(getattr(g, gain)))}, cpl_block=block * keep)
        s = L.eval_summary(evaluate(cut, held))
        out[channel] = (s["settled_peak_resultant_N"], s["dropped"])
    return out


def _load(path: str) -> dict:
    with open(path) as f:
        return json.load(f)


def _peaks_of(out: str, row: dict, label: str) -> np.ndarray:
    return _peaks(_load(os.path.join(out, f"bound_{row['bound']:g}", f"seed_{row['seed']}", label, "summary.json")))


if __name__ == "__main__":
    main()
