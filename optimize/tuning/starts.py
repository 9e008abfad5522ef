"""Several tuning runs from the same gains, each on its own training batches,
and the best by validation (``jaxsync tune --starts K``).

One L-BFGS run trains on a few scenarios at a time and ends wherever its path
has taken it when its iterations run out: two runs whose training batches
differ (or whose models differ slightly) can end a factor of a few apart on
the same validation scenarios (docs/tuning.md). Starting ``K`` runs and
keeping the best validated one makes the result depend less on one path, at
``K`` times the cost.

Start ``k`` is a whole tuning run (:func:`pipeline.tune_and_evaluate`) with
training seed ``seed + k``, in ``out/seed_<seed + k>``: the same starting
gains, validation and held-out scenarios, settings otherwise (the starting
gains' held-out scores are the first start's, given to the others). Each is resumed
on its own, and a finished one (its ``summary.json`` from the same settings)
is read back, not run again. The kept start is the one whose selected iterate
has the lowest validation settled peak among those that qualify
(:func:`tune_state.select_iterate`'s rules, against the starting gains'
validation: a grip error not worse, nothing dropped, no more chatter, within
the bounds); the held-out scores never choose. Its ``gains.json``,
``gains_last.json``, ``history.csv``, ``loss.png`` and ``heldout_before.json``
are copied to ``out``, and ``out/summary.json`` is its summary with
``starts``: every start's seed, folder, selected iteration, validation and
held-out figures, and which was kept.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
from collections.abc import Callable

from jaxsync._errors import ConfigError
from jaxsync.io import gains_file
from jaxsync.io import results as _results
from jaxsync.optimize.tuning import pipeline as _pipeline
from jaxsync.optimize.tuning.tune_state import CHECKPOINT, prepare_out, select_iterate
from jaxsync.runtime import distributed as _distributed

COPIED = ("gains.json", "gains_last.json", "history.csv", "loss.png", _pipeline.HELDOUT_BEFORE)
"""The kept start's files copied to the top folder (with its summary.json, which gains ``starts``)."""


def start_folder(out: str, seed: int) -> str:
    return os.path.join(out, f"seed_{seed}")


def select_start(validations: list[list[dict]], selected: list[int]) -> int:
    """Index of the start to keep: ``validations[k]`` is start ``k``'s
    validation list (its first entry the starting gains', the same in every
    start), ``selected[k]`` the iteration it selected. The lowest validation
    settled peak among the qualifying selected iterates; start 0 when none
    improved on the starting gains.

    Example:
      >>> v0 = {"iteration": 0, "settled_peak_resultant_N": 0.02, "grip_force_error_rel": 0.01,
      ...       "dropped": 0, "nonfinite": 0}
      >>> a = dict(v0, iteration=40, settled_peak_resultant_N=0.004)
      >>> b = dict(v0, iteration=55, settled_peak_resultant_N=0.001)
      >>> select_start([[v0, a], [v0, b]], [40, 55])
      1
    """
    picks = [next(v for v in val if v["iteration"] == it) for val, it in zip(validations, selected, strict=True)]
    best = select_iterate([validations[0][0], *picks])
    return next((k for k, p in enumerate(picks) if p is best), 0)


def _finished(folder: str, cfg) -> _pipeline.TuneSummary | None:
    """The start's summary when its folder holds a finished run of exactly these settings."""
    path = os.path.join(folder, "summary.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        doc = json.load(f)
    if doc.get("config") != json.loads(json.dumps(cfg.to_dict())):
        return None  # other settings (e.g. more iterations): resumed from its checkpoint, which checks them
    names = [f.name for f in dataclasses.fields(_pipeline.TuneSummary) if f.name not in ("gains", "last_gains")]
    if any(n not in doc for n in names if n != "starts"):
        return None
    loaded = {n: gains_file.load(os.path.join(folder, n + ".json")) for n in ("gains", "gains_last")}
    return _pipeline.TuneSummary(
        gains=loaded["gains"], last_gains=loaded["gains_last"], **{n: doc[n] for n in names if n in doc}
    )


def run_tune(model=None, cfg=None, starts: int = 2, *, gains=None, any_model: bool = False, visual: bool = True,
             **job) -> _pipeline.TuneSummary | None:  # fmt: skip
    """``jaxsync tune --starts K``'s job: :func:`pipeline.run_tune`'s arguments
    (``job``: ``out``, ``resume``, ``restart``, ``mujoco_check``, ``options``,
    ``log``), ``starts`` runs, the best by validation (:func:`run_starts`).

    Example:
      >>> summary = run_tune("mjcf/robots/iiwa14_twice.yaml", TuneConfig(), 2, out="results/tune")  # doctest: +SKIP
    """
    model, base, cfg = _pipeline.job_inputs(model, cfg, gains, any_model, visual)
    return run_starts(model, base, cfg, starts, **job)


def run_starts(model, base, cfg, starts: int, *, out: str, resume: bool = False, restart: bool = False,
               log: Callable[[str], None] = print, **job) -> _pipeline.TuneSummary | None:  # fmt: skip
    """``starts`` tuning runs (training seeds ``cfg.data.seed`` and on), the best
    by validation (the module's doc); ``job``: :func:`pipeline.tune_and_evaluate`'s
    other keywords. Returns the kept start's summary with ``starts``; None on a
    process other than the first of a multi-process run."""
    if starts < 1:
        raise ConfigError(f"starts must be a positive integer, got {starts}", inputs=("starts",))
    if not cfg.loop.validate_every:
        raise ConfigError(
            "starts are compared on the validation scenarios: validate_every must be positive with starts > 1",
            inputs=("starts", "validate_every"),
        )
    seeds = [cfg.data.seed + k for k in range(starts)]
    for s in seeds:  # every start's seeds checked before anything runs
        cfg.replace(seed=s).validate()
    main = _distributed.is_main()
    if main:
        _check_out(out, seeds, resume, restart)  # reads only: nothing is made or removed before it passes
        _results.ensure_writable_dir(out)
    with _results.run_lock(out, "tune starts", log=log) if main else contextlib.nullcontext():
        if main and restart:
            prepare_out(out, restart=True)  # the kept start's copies, as a run's files
        return _run_starts(model, base, cfg, seeds, out, resume, restart, log, main, job)


def _check_out(out: str, seeds: list[int], resume: bool, restart: bool) -> None:
    """What ``out`` holds against resume and restart, as for one run (``tune_state.prepare_out``)."""
    held = [os.path.basename(start_folder(out, s)) for s in seeds if os.path.isdir(start_folder(out, s))]
    if resume and restart:
        prepare_out(out, resume=True, restart=True)  # the error naming both
    if resume and not held:
        raise ConfigError(
            f"no tuning starts in {out!r} to resume (seed_{seeds[0]} ... seed_{seeds[-1]}): restart instead to "
            "start them there, or choose another output folder",
            inputs=("resume", "restart", "out"),
        )
    if not (resume or restart) and held:
        raise ConfigError(
            f"output folder {out!r} holds tuning starts ({', '.join(held)}): resume to continue them, restart "
            "to discard them and start over, or choose another output folder",
            inputs=("resume", "restart", "out"),
        )
    if not (resume or restart):
        prepare_out(out)  # refuses a single run's files


def _run_starts(model, base, cfg, seeds, out, resume, restart, log, main, job):
    starts = len(seeds)
    runs, before = [], None
    for k, s in enumerate(seeds):
        folder, cfg_k = start_folder(out, s), cfg.replace(seed=s)
        done = _finished(folder, _pipeline.job_config(model, cfg_k)[0]) if resume else None  # as it records it
        if done is not None:
            log(f"start {k + 1} of {starts} (seed {s}): finished in {folder}, read back")
        else:
            log(f"start {k + 1} of {starts} (seed {s}) in {folder}")
            again = resume and os.path.exists(os.path.join(folder, CHECKPOINT))
            done = _pipeline.tune_and_evaluate(model, base, cfg_k, out=folder, resume=again, restart=restart or (
                not again and os.path.isdir(folder)), log=log, before=before, **job)  # fmt: skip
        runs.append(done)
        if main and before is None:  # the same gains on the same held-out scenarios: scored once, by the first
            before = _read_before(folder)
    if not main:
        return None
    k = select_start([r.validation for r in runs], [r.selected_iteration for r in runs])
    table = [
        {"seed": s, "folder": os.path.basename(start_folder(out, s)), "selected_iteration": r.selected_iteration,
         "validation": _figures(next(v for v in r.validation if v["iteration"] == r.selected_iteration)),
         "heldout_after": _figures(r.heldout_after), "wall_time_s": r.wall_time_s, "kept": i == k}
        for i, (s, r) in enumerate(zip(seeds, runs, strict=True))
    ]  # fmt: skip
    kept = dataclasses.replace(runs[k], starts=table)
    folder = start_folder(out, seeds[k])
    for name in COPIED:  # each whole or not at all: a copy beside it, then renamed
        if os.path.exists(os.path.join(folder, name)):
            shutil.copyfile(os.path.join(folder, name), os.path.join(out, name + ".part"))
            os.replace(os.path.join(out, name + ".part"), os.path.join(out, name))
    _results.write_json(os.path.join(out, "summary.json"), kept.to_dict())
    for row in table:
        peak = row["validation"]["settled_peak_resultant_N"]
        log(f"seed {row['seed']}: validation settled peak " + (f"{peak:.5f} N" if peak is not None else "none")
            + f" at iteration {row['selected_iteration']}" + (" (kept)" if row["kept"] else ""))  # fmt: skip
    return kept


def _read_before(folder: str) -> dict | None:
    path = os.path.join(folder, _pipeline.HELDOUT_BEFORE)
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def _figures(e: dict) -> dict:
    keys = ("settled_peak_resultant_N", "grip_force_error_rel", "dropped", "chattering")
    return {key: e.get(key) for key in keys}
