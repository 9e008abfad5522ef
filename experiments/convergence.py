"""Does the converged criterion predict a longer run, and is a converged tune reproducible?

One start per process (two processes use the two cores):

  python experiments/convergence.py run --start default   --out results/convergence
  python experiments/convergence.py run --start perturbed --out results/convergence
  python experiments/convergence.py extend --start default --to 300   # each start, a run of 300 iterations
  python experiments/convergence.py report --out results/convergence

``run`` tunes ``jaxsync tune``'s default job (paper model, synchronous,
L-BFGS) until it converges, with the validation plateau ``--plateau-tol``
on, or to its cap (``--iterations``), from the
default gains (``default``) or from every gain x (1 + ``--perturb``)
(``perturbed``), or from the default gains on the paper model with every
body's mass and inertia x (1 + ``--perturb``) (``model``); then continues a copy of that run past its stop with the
criterion off for ``--extend`` more iterations (the longer run), and writes
both summaries; ``extend`` continues a copy of the longer run to ``--to``
iterations. ``report`` says, for each start, how far the longer run moved
the validation and held-out figures past the stop, and how far the two starts
ended apart (held-out settled peak), at the stop and after the longer run.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import shutil
import sys

import jax

import jaxsync
from jaxsync.control.gains import default_gains
from jaxsync.optimize.tuning import pipeline
from jaxsync.optimize.tuning.config import TuneConfig
from jaxsync.optimize.tuning.cost import parse_weights
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags


def _summary(path: str) -> dict:
    with open(os.path.join(path, "summary.json")) as f:
        return json.load(f)


def _start(args):
    """jaxsync's settings, the paper model and the start's gains (moved by ``--perturb`` for "perturbed")."""
    set_xla_flags()
    jax.config.update("jax_enable_x64", True)
    enable_compilation_cache()
    base = default_gains()
    if args.start == "perturbed":
        base = jax.tree_util.tree_map(lambda x: x * (1 + args.perturb), base)
    model = jaxsync.load_model()
    if args.start == "model":
        model = _heavier(model, args.perturb)
    return model, base


def _heavier(model, rel: float):
    """The same model with every body's mass and inertia x (1 + ``rel``): a change of the model far below
    anything a user knows it to."""
    import dataclasses

    from mujoco import mjx

    from jaxsync.physics import step as _physics

    m = copy.deepcopy(model.mj_model)
    m.body_mass[:] *= 1 + rel
    m.body_inertia[:] *= 1 + rel
    mx = mjx.put_model(m, device=_physics.local_device(), impl="jax")
    return dataclasses.replace(model, mj_model=m, mjx_model=mx)


def _forget_curvature() -> None:
    """L-BFGS as it ran before it carried its curvature pairs to a fresh batch (the comparison's other arm)."""
    from jaxsync.optimize.tuning import methods

    get = methods.get
    methods.get = lambda name, **o: get(name, **({"renewal_memory": False} | o) if name == "lbfgs" else o)


def run(args) -> None:
    if args.forget_curvature:
        _forget_curvature()
    model, base = _start(args)
    cfg = TuneConfig(iterations=args.iterations, plateau_tol=args.plateau_tol, weights=parse_weights(args.weight),
                     seed=args.seed)  # fmt: skip
    first = os.path.join(args.out, args.start)
    if not os.path.exists(os.path.join(first, "summary.json")):
        pipeline.tune_and_evaluate(model, base, cfg, out=first, restart=True, mujoco_check=False)
    stopped = _summary(first)
    longer = first + "_longer"
    if args.extend > 0 and not os.path.exists(os.path.join(longer, "summary.json")):
        shutil.rmtree(longer, ignore_errors=True)
        shutil.copytree(first, longer, ignore=shutil.ignore_patterns(".jaxsync.lock", "summary.json"))
        n = stopped["convergence"]["iterations"] + args.extend
        pipeline.tune_and_evaluate(
            model, base, cfg.replace(iterations=n, plateau_tol=0.0), out=longer, resume=True, mujoco_check=False
        )


def extend(args) -> None:
    """A copy of the longer run continued to ``--to`` iterations (the criterion off)."""
    model, base = _start(args)
    src, dst = os.path.join(args.out, args.start + "_longer"), os.path.join(args.out, f"{args.start}_{args.to}")
    if not os.path.exists(os.path.join(dst, "summary.json")):
        shutil.rmtree(dst, ignore_errors=True)
        shutil.copytree(src, dst, ignore=shutil.ignore_patterns(".jaxsync.lock", "summary.json"))
        cfg = TuneConfig(iterations=args.to, plateau_tol=0.0)
        pipeline.tune_and_evaluate(model, base, cfg, out=dst, resume=True, mujoco_check=False)


def _row(s: dict) -> dict:
    sel = next(v for v in s["validation"] if v["iteration"] == s["selected_iteration"])
    c = s["convergence"]
    return {
        "iterations": c["iterations"],
        "reason": c["reason"],
        "converged": c["converged"],
        "selected_iteration": s["selected_iteration"],
        "validation_N": sel["settled_peak_resultant_N"],
        "heldout_N": s["heldout_settled_peak_resultant_N_after"],
        "heldout_before_N": s["heldout_settled_peak_resultant_N_before"],
        "seconds": c["seconds"],
    }


def report(args) -> None:
    rows = {}
    for start in ("default", "perturbed", "model"):
        kinds = ["", "_longer"] + sorted(d[len(start) :] for d in os.listdir(args.out) if d.startswith(start + "_")
                                         and d[len(start) + 1 :].isdigit())  # fmt: skip
        for kind in kinds:
            p = os.path.join(args.out, start + kind)
            if os.path.exists(os.path.join(p, "summary.json")):
                rows[start + kind] = _row(_summary(p))
    out = {"rows": rows}
    for start in ("default", "perturbed"):
        a, b = rows.get(start), rows.get(start + "_longer")
        if a and b:
            out[f"{start}: longer / stopped"] = {
                "validation": b["validation_N"] / a["validation_N"],
                "heldout": b["heldout_N"] / a["heldout_N"],
            }
    for kind in sorted({k[len("default") :] for k in rows if k.startswith("default")}):
        for other in ("perturbed", "model"):
            a, b = rows.get("default" + kind), rows.get(other + kind)
            if a and b:
                out[f"{other} / default{kind or ' (at the stop)'}"] = b["heldout_N"] / a["heldout_N"]
    print(json.dumps(out, indent=1))
    with open(os.path.join(args.out, "report.json"), "w") as f:
        json.dump(out, f, indent=1)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    r = sub.add_parser("run")
    r.add_argument("--start", choices=["default", "perturbed", "model"], required=True)
    r.add_argument("--perturb", type=float, default=1e-6,
                   help="relative change of every starting gain, or (model) every mass and inertia (1e-6)")  # fmt: skip
    r.add_argument("--iterations", type=int, default=200, help="the cap of the first run (200)")
    r.add_argument("--plateau-tol", type=float, default=0.02, help="the first run's plateau (0.02; 0: L-BFGS's own)")
    r.add_argument("--extend", type=int, default=60, help="iterations the longer run adds past the stop (60)")
    r.add_argument("--out", default="results/convergence")
    r.add_argument("--weight", action="append", metavar="NAME=VALUE", help="a cost weight, as jaxsync tune's")
    r.add_argument("--seed", type=int, default=0, help="the training seed (0)")
    r.add_argument(
        "--forget-curvature",
        action="store_true",
        help="each fresh L-BFGS batch starts from steepest descent, not the last batch's curvature",
    )
    e = sub.add_parser("extend", help="continue a copy of the longer run to --to iterations")
    e.add_argument("--start", choices=["default", "perturbed"], required=True)
    e.add_argument("--perturb", type=float, default=1e-6)
    e.add_argument("--to", type=int, required=True)
    e.add_argument("--out", default="results/convergence")
    q = sub.add_parser("report")
    q.add_argument("--out", default="results/convergence")
    args = p.parse_args(argv)
    {"run": run, "extend": extend, "report": report}[args.what](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
