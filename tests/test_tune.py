"""Gain tuning: constraints by construction, a resumed run ending where an
uninterrupted one ends (on jaxsync tune's own program, whose gradient
tests/test_gradient.py checks against central differences), the command's
plumbing and errors."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import re
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tqdm as tqdm_module
from conftest import TEST_DURATION, build_tuning_program, fake_heldout_metrics, paper_model

import jaxsync
from jaxsync.cli import build_parser, main
from jaxsync.control import gains as _gains
from jaxsync.io import results as _results
from jaxsync.optimize.tuning import checkpoint, methods, pipeline, scenarios, tune_state
from jaxsync.optimize.tuning import loss as loss_mod
from jaxsync.optimize.tuning import params as _params
from jaxsync.optimize.tuning import starts as starts_mod
from jaxsync.optimize.tuning import tune as tune_mod
from jaxsync.optimize.tuning.config import Problem
from jaxsync.optimize.tuning.cost import CostWeights
from jaxsync.optimize.tuning.loss import make_loss
from jaxsync.optimize.tuning.methods import LBFGS, Oracle
from jaxsync.optimize.tuning.params import FORCE, OBJECT, ZETA_MAX, ZETA_MIN, TuneSpec, check_tuned, damping_ratio
from jaxsync.optimize.tuning.scenarios import sample_scenarios, training_base, training_batch
from jaxsync.optimize.tuning.tune import TuneConfig, TuneResult, tune
from jaxsync.optimize.tuning.tune_report import change_text, convergence_text, mujoco_text, summary_lines
from jaxsync.optimize.tuning.tune_state import select_iterate
from jaxsync.physics import step as _physics
from jaxsync.sim import actuation as _actuation
from jaxsync.sim import crosscheck as _crosscheck
from jaxsync.sim import metrics as _metrics

# The resumed-run test tunes with jaxsync tune's defaults (the full task, the
# exact gradient) at batch 2: the program of the session fixture
# ``tuning_program``, whose gradient tests/test_gradient.py checks against
# central differences in every parameter. Two iterations, a checkpoint and a
# validation after each: the run is stopped after the first and resumed.
RESUME = dict(iterations=2, checkpoint_every=1, validate_every=1, method="adam")


def compile_ahead():
    """The session's ``tuning_program`` (tests/conftest.py: compiled ahead in a second process)."""
    p = build_tuning_program(paper_model())
    jax.block_until_ready(p["value_and_grad"](p["theta0"], p["scenarios"]))


def test_parametrisation_is_constrained_and_round_trips():
    base = _gains.default_gains()
    spec = TuneSpec()
    theta = spec.init(base)
    g = spec.to_gains(theta, base)
    for k in ("k_rk", "k_lk", "k_rl", "k_ll", "imp_mass", "imp_stiffness", "imp_damping"):
        np.testing.assert_allclose(np.asarray(getattr(g, k)), np.asarray(getattr(base, k)), rtol=1e-9)
    # any theta gives valid gains: |k| < 1, M, K > 0, damping ratio inside the band
    rng = np.random.default_rng(0)
    for _ in range(20):
        wild = jax.tree_util.tree_map(lambda x: x + 30 * rng.standard_normal(np.shape(x)), theta)
        g = spec.to_gains(wild, base)
        assert all(abs(float(getattr(g, k))) <= 1 for k in ("k_rk", "k_lk", "k_rl", "k_ll"))
        assert np.all(np.asarray(g.imp_mass) > 0) and np.all(np.asarray(g.imp_stiffness) > 0)
        z = np.asarray(damping_ratio(g))
        assert np.all(z >= ZETA_MIN - 1e-9) and np.all(z <= ZETA_MAX + 1e-9)


def test_the_rules_impedance_is_tuned_within_the_exported_rules_stability_margin():
    """Where the gains deploy as ros2_controllers' rule (deploy_dt), every theta
    gives gains the export writes without a warning: each mass raised to
    DEPLOY_MARGIN (2 dt D + dt^2 K) / 4 with D and K kept, gains already within
    left as they are (the rule's defaults round-trip), masses within the
    controller's bounds, and the raised mass
    still moves with the damping ratio. Without it, the same thetas leave the
    margin (so this can fail)."""
    from jaxsync.control import ros2_admittance as ra  # noqa: PLC0415
    from jaxsync.io.export_gains import deployed_stability  # noqa: PLC0415

    dt = 0.002
    base = _gains.default_gains(paper_model(), "position")
    free = TuneSpec(tuned=_params.IMPEDANCE, per_arm=True)
    held = dataclasses.replace(free, deploy_dt=dt)
    theta = held.init(base)
    g = held.to_gains(theta, base)
    for k in ("imp_mass", "imp_stiffness", "imp_damping"):
        np.testing.assert_allclose(np.asarray(getattr(g, k)), np.asarray(getattr(base, k)), rtol=1e-9)
    rng = np.random.default_rng(1)
    outside = 0
    for _ in range(20):
        wild = jax.tree_util.tree_map(lambda x: x + 3 * rng.standard_normal(np.shape(x)), theta)
        g, f = held.to_gains(wild, base), free.to_gains(wild, base)
        index = ra.stability_index(np.asarray(g.imp_mass), np.asarray(g.imp_damping), np.asarray(g.imp_stiffness), dt)
        assert index.max() <= 1 / ra.DEPLOY_MARGIN * (1 + 1e-12) and deployed_stability(g, dt) == []
        np.testing.assert_array_equal(np.asarray(g.imp_damping), np.asarray(f.imp_damping))
        np.testing.assert_array_equal(np.asarray(g.imp_stiffness), np.asarray(f.imp_stiffness))
        free_index = ra.stability_index(
            np.asarray(f.imp_mass), np.asarray(f.imp_damping), np.asarray(f.imp_stiffness), dt
        )
        kept = (free_index <= 1 / ra.DEPLOY_MARGIN) & (np.asarray(f.imp_mass) >= ra.MASS_BOUNDS[0])
        assert np.asarray(g.imp_mass).min() >= ra.MASS_BOUNDS[0]  # and the controller's own bounds
        np.testing.assert_array_equal(np.asarray(g.imp_mass)[kept], np.asarray(f.imp_mass)[kept])
        outside += int((~kept).sum())
    assert outside > 0
    # the paper model's normal axis, its damping ratio raised past the margin: the mass follows it
    past = {**theta, "imp_damping_ratio": theta["imp_damping_ratio"].at[0, 2].add(0.5)}
    assert float(held.to_gains(past, base).imp_mass[0, 2]) > float(free.to_gains(past, base).imp_mass[0, 2])
    grad = jax.grad(lambda t: held.to_gains(t, base).imp_mass[0, 2])(past)
    assert float(grad["imp_damping_ratio"][0, 2]) > 0 and float(grad["imp_stiffness"][0, 2]) != 0
    with pytest.raises(jaxsync.ConfigError, match="deploy_dt must be a positive control period"):
        dataclasses.replace(free, deploy_dt=0.0)


def test_spec_sharing_and_errors():
    base = _gains.default_gains()
    spec = TuneSpec(tuned=("imp_stiffness",), per_arm=True, isotropic=True)
    theta = spec.init(base)
    assert theta["imp_stiffness"].shape == (2, 2) and set(theta) == {"imp_stiffness"}
    g = spec.to_gains(jax.tree_util.tree_map(lambda x: x + 1.0, theta), base)
    assert float(g.k_rk) == float(base.k_rk)  # frozen
    with pytest.raises(jaxsync.ConfigError, match="unknown parameter"):
        TuneSpec(tuned=("k_zz",))
    with pytest.raises(jaxsync.ConfigError, match="learning_rate"):
        TuneConfig(learning_rate=0.0).validate()
    with pytest.raises(jaxsync.ConfigError, match="batch"):
        TuneConfig(batch=0).validate()


def test_the_joint_command_loops_gain_is_tunable_in_log_space():
    """kp_pos (tune on request): positive for any theta, kd_pos kept, one
    scalar, every controller may tune it (each ends in that loop)."""
    base = _gains.default_gains()
    spec = TuneSpec(tuned=("k_rk", "kp_pos"))
    theta = spec.init(base)
    assert spec.size() == 2 and float(spec.to_gains(theta, base).kp_pos) == pytest.approx(float(base.kp_pos))
    g = spec.to_gains({**theta, "kp_pos": theta["kp_pos"] + np.log(0.25)}, base)
    assert float(g.kp_pos) == pytest.approx(0.25 * float(base.kp_pos)) and float(g.kd_pos) == float(base.kd_pos)
    assert float(spec.to_gains({**theta, "kp_pos": jnp.asarray(-800.0)}, base).kp_pos) >= 0.0
    for controller in ("task_space", "ros2_admittance"):
        check_tuned(("kp_pos",), controller)
    with pytest.raises(jaxsync.ConfigError, match="kp_pos > 0"):
        spec.init(base._replace(kp_pos=jnp.asarray(0.0)))


def test_scenario_sampling_is_seeded_and_in_range():
    base = jaxsync.short_task()
    a = sample_scenarios(jax.random.key(3), 16, base)
    b = sample_scenarios(jax.random.key(3), 16, base)
    c = sample_scenarios(jax.random.key(4), 16, base)
    np.testing.assert_array_equal(np.asarray(a.object_mass), np.asarray(b.object_mass))
    assert not np.allclose(np.asarray(a.object_mass), np.asarray(c.object_mass))
    m = np.asarray(a.object_mass) / float(base.object_mass)
    assert m.min() >= 0.7 and m.max() <= 1.3
    assert np.abs(np.asarray(a.object_offset)[:, 1]).max() <= 0.005


def test_grip_spread_varies_the_grip_force_and_nothing_else():
    base = jaxsync.default_scenario()
    plain = sample_scenarios(jax.random.key(3), 8, base)
    spread = sample_scenarios(jax.random.key(3), 8, base, grip_spread=0.2)
    g = np.asarray(spread.grip_force)
    assert np.all((g >= 8.0 - 1e-9) & (g <= 12.0 + 1e-9)) and np.ptp(g) > 1.0
    np.testing.assert_array_equal(np.asarray(plain.grip_force), float(base.grip_force))
    for f in ("object_mass", "contact_timeconst", "friction", "force_noise", "object_offset"):  # the same draws
        np.testing.assert_array_equal(np.asarray(getattr(plain, f)), np.asarray(getattr(spread, f)), err_msg=f)
    ends = np.sort(
        np.asarray(sample_scenarios(jax.random.key(3), 2, base, stratified=True, grip_spread=0.2).grip_force)
    )
    np.testing.assert_allclose(ends, [8.0, 12.0])
    cfg = TuneConfig(grip_spread=0.2, heldout_batch=4)
    assert np.ptp(np.asarray(scenarios.heldout_scenarios(cfg).grip_force)) > 0
    with pytest.raises(jaxsync.ConfigError, match="grip_spread"):
        TuneConfig(grip_spread=1.0).validate()


def test_stratified_batches_hold_each_ranges_ends():
    """A stratified batch takes every level from the bottom of each range to its
    top once (a batch of 2: the softest and the stiffest contact, ...), paired
    differently per seed; the default iid draw is unchanged by the option."""
    base = jaxsync.short_task()
    ranges = {
        "contact_timeconst": (0.015, 0.03),
        "friction": (0.8, 1.2),
        "force_noise": (0.05, 0.15),
    }
    for n in (2, 4):
        s = sample_scenarios(jax.random.key(5), n, base, stratified=True)
        for name, (lo, hi) in ranges.items():
            np.testing.assert_allclose(np.sort(np.asarray(getattr(s, name))), np.linspace(lo, hi, n), rtol=1e-12)
        np.testing.assert_allclose(
            np.sort(np.asarray(s.object_mass)) / float(base.object_mass), np.linspace(0.7, 1.3, n), rtol=1e-12
        )
        np.testing.assert_allclose(np.sort(np.asarray(s.object_offset)[:, 1]), np.linspace(-0.005, 0.005, n))
    pairings = {
        tuple(np.argsort(np.asarray(sample_scenarios(jax.random.key(k), 4, base, stratified=True).friction)))
        for k in range(6)
    }
    assert len(pairings) > 1  # the levels are paired at random, not in one fixed order
    iid = sample_scenarios(jax.random.key(5), 4, base)
    assert not np.allclose(np.sort(np.asarray(iid.contact_timeconst)), np.linspace(0.015, 0.03, 4))
    # training batches are stratified by default, iid on request
    cfg = TuneConfig(batch=2, task="short")
    tb = training_batch(cfg, 0, base)
    np.testing.assert_allclose(np.sort(np.asarray(tb.contact_timeconst)), [0.015, 0.03])
    tb_iid = training_batch(cfg.replace(sampling="iid"), 0, base)
    assert not np.allclose(np.sort(np.asarray(tb_iid.contact_timeconst)), [0.015, 0.03])
    with pytest.raises(jaxsync.ConfigError, match="sampling must be"):
        TuneConfig(sampling="sobol").validate()


def _fake_validation(g):
    """A cheap stand-in for the held-out-style evaluation: a smooth function of the gains."""
    return {
        "settled_peak_resultant_N": float(abs(g.k_rl - 0.55) + abs(g.k_ll - 0.55)),
        "grip_force_error_rel": float(0.01 + abs(g.k_rk)),
        "dropped": 0,
        "nonfinite": 0,
    }


def test_resume_ends_where_an_uninterrupted_run_ends(model, tuning_program, tmp_path):
    cfg = tuning_program["cfg"].replace(**RESUME)
    base = tuning_program["base"]
    kw = dict(progress=False, validate=_fake_validation)
    r_full = tune(model, base, cfg, out=str(tmp_path / "a"), **kw)
    full, hist_full = r_full.gains, r_full.history
    # Ctrl-C during the first iteration's callback (before its validation): a
    # checkpoint is written, then resume to the end

    def interrupt(i, theta, row):
        if i == 0:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        tune(model, base, cfg, out=str(tmp_path / "b"), on_iteration=interrupt, **kw)
    assert (tmp_path / "b" / "checkpoint.npz").exists()
    r_res = tune(model, base, cfg, out=str(tmp_path / "b"), resume=True, **kw)
    resumed, hist_res = r_res.gains, r_res.history
    assert len(hist_res) == len(hist_full) == cfg.loop.iterations
    for a, b in zip(jax.tree_util.tree_leaves(full), jax.tree_util.tree_leaves(resumed), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the same records, keys in the same order (history.csv's columns), timing aside
    assert [list(r) for r in hist_res] == [list(r) for r in hist_full]
    untimed = lambda h: [{k: v for k, v in r.items() if k != "seconds"} for r in h]  # noqa: E731
    assert untimed(hist_res) == untimed(hist_full)
    assert hist_full[-1]["cost"] != hist_full[0]["cost"]  # it did move
    # validated at 0, 1, 2 in both runs; the selection is the same
    assert [v["iteration"] for v in r_full.validation] == [0, 1, 2]
    assert [v["iteration"] for v in r_res.validation] == [0, 1, 2]
    assert r_res.selected["iteration"] == r_full.selected["iteration"]
    # the returned gains are the selected iterate's, which the fake validation agrees is best allowed
    scores = {v["iteration"]: v for v in r_full.validation}
    sel = r_full.selected
    assert _fake_validation(full) == {k: scores[sel["iteration"]][k] for k in _fake_validation(full)}
    allowed = [v for v in r_full.validation if v["grip_force_error_rel"] <= scores[0]["grip_force_error_rel"]]
    assert sel["settled_peak_resultant_N"] == min(v["settled_peak_resultant_N"] for v in allowed)
    if sel["iteration"] != cfg.loop.iterations:
        assert _gains.to_dict(r_full.last_gains) != _gains.to_dict(full)


def test_gradient_losses_run_the_tree_passes_and_evaluated_ones_mjx(model, monkeypatch):
    """make_loss(differentiated=True) (what tune's gradient and the tuner
    benchmark's differentiate) steps with jaxsync's tree passes, the loss a
    CMA-ES population or a held-out score only evaluates with MJX's (faster
    over large vmapped batches): each loss traced up to its first physics
    stage, whose ``passes`` is recorded (the trace stops there: no step is
    traced, nothing compiled)."""

    class Reached(Exception):
        pass

    seen = []

    def recording(m, d, passes="mjx"):
        seen.append(passes)
        raise Reached

    monkeypatch.setattr(_physics, "before_control", recording)
    cfg = TuneConfig(task="short", batch=1)
    spec, base = TuneSpec(), _gains.default_gains()
    scen = sample_scenarios(jax.random.key(0), 1, training_base(cfg.training)[0])
    passes = {}
    for differentiated in (True, False):
        seen.clear()
        loss = make_loss(model, base, cfg, differentiated=differentiated)
        with pytest.raises(Reached):
            jax.eval_shape(loss, spec.init(base), scen)
        passes[differentiated] = seen[:]
    assert passes == {True: ["tree"], False: ["mjx"]}


def test_select_iterate_keeps_within_the_compliance_bounds():
    start = {
        "iteration": 0,
        "settled_peak_resultant_N": 0.05,
        "grip_force_error_rel": 0.01,
        "dropped": 0,
        "nonfinite": 0,
        "within_bounds": False,
        "bound_excess": 0.4,
    }
    near = dict(start, iteration=5, settled_peak_resultant_N=0.03, bound_excess=0.1)
    nearer = dict(start, iteration=10, settled_peak_resultant_N=0.04, bound_excess=0.05)
    inside = dict(start, iteration=15, settled_peak_resultant_N=0.045, within_bounds=True, bound_excess=-0.1)
    # none within: the least excess, not the start
    assert select_iterate([start, near, nearer])["iteration"] == 10
    # one within: it, though others have lower peaks
    assert select_iterate([start, near, nearer, inside])["iteration"] == 15
    # unbounded runs (no such keys): the lowest peak
    plain = [{k: v for k, v in r.items() if k not in ("within_bounds", "bound_excess")} for r in (start, near)]
    assert select_iterate(plain)["iteration"] == 5


def test_select_iterate_keeps_the_grip_error():
    def v(i, peak, grip, dropped=0):
        return {
            "iteration": i,
            "settled_peak_resultant_N": peak,
            "grip_force_error_rel": grip,
            "dropped": dropped,
            "nonfinite": 0,
        }

    assert select_iterate([]) is None
    runs = [v(0, 0.010, 0.005), v(5, 0.004, 0.006), v(10, 0.006, 0.005), v(15, 0.003, 0.004, dropped=1)]
    assert select_iterate(runs)["iteration"] == 10  # 5 is lower but worsens the grip; 15 dropped an object
    assert select_iterate(runs[:2])["iteration"] == 0  # nothing better allowed: the start
    # a floor lets a run continued from tuned gains trade grip error below it for a lower peak
    assert select_iterate(runs, grip_floor=0.006)["iteration"] == 5
    assert select_iterate(runs, grip_floor=0.0055)["iteration"] == 10  # 5's 0.6 % is above the floor
    with pytest.raises(jaxsync.ConfigError, match="grip_floor must be a relative grip error"):
        TuneConfig(grip_floor=1.5).validate()


def test_tune_cli_rejects_bad_input(tmp_path, capsys):
    bad = tmp_path / "g.json"
    bad.write_text('{"k_lk": -2}')
    blocker = tmp_path / "f"
    blocker.write_text("")
    schedule_file = tmp_path / "sched.json"
    schedule_file.write_text('{"gains": {"schedule": {"hold": {"k_rk": 0.1}}}}')
    cases = [
        (["--lr", "0"], "learning_rate must be positive, got 0.0 (--lr)"),
        (["--batch", "0"], "batch must be a positive integer"),
        (["--tune", "k_rk,foo"], "unknown parameter"),
        (["--freeze", "bar"], "unknown parameter"),
        (["--gains", str(bad)], "k_lk"),
        (["--method", "nope"], "or a first-order optax optimiser"),
        (["--out", str(blocker / "x")], "cannot be written"),
        (["--resume", "--out", str(tmp_path / "empty")], "no checkpoint at"),
        (["--resume", "--out", str(tmp_path / "empty")], "restart instead to start a run there"),
        (["--validate-every", "-1"], "validate_every must be 0 (off) or a positive integer, got -1 (--validate-every)"),
        (["--validation-seed", "1000"], "seeds must differ"),
        (["--popsize", "1", "--method", "cmaes"], "popsize must be at least 2"),
        (["--gains", str(schedule_file)], "tune them per phase (TuneSpec(schedule=True)) (--per-phase)"),
        (["--controller", "classical", "--tune", "k_rk"], "does not use k_rk"),
        (["--controller", "task_space", "--tune", "imp_mass"], "it tunes force_p, force_i"),
        (["--delay", "0:3"], "delay applies to position-controlled arms (actuation='position'), got delay 3"),
        (["--delay", "0:3"], "(--delay, --actuation)"),
        (["--servo-spread", "0.3"], "servo_spread applies to position-controlled arms"),
        (["--actuation", "position", "--servo-spread", "1.5"], "servo_spread must be a share in [0, 1)"),
        (["--actuation", "position", "--delay", "2:1"], "within 0..8, got '2:1' (--delay)"),
        (["--actuation", "position", "--control-rate", "300"], "divide the physics rate 500 Hz"),
        (["--starts", "2", "--validate-every", "0"], "validate_every must be positive with starts > 1"),
        (["--starts", "2", "--resume"], "no tuning starts in"),
    ]
    for args, msg in cases:  # in this process (the console script itself: tests/test_model.py)
        rc = main(["tune", "--out", str(tmp_path / "o"), *args])
        err = capsys.readouterr().err
        assert rc == 2 and msg in err and "Traceback" not in err, (args, err[-500:])
        assert not (tmp_path / "o").exists() and not (tmp_path / "empty").exists(), args  # no folder left
    parser = build_parser()
    for args, msg in [
        (["--controller", "bogus"], "invalid choice"),
        (["--max-impact", "0"], "must be positive"),
        (["--max-stiffness", "-5"], "must be positive"),
        (["--starts", "0"], "must be positive"),
    ]:  # argparse's own: usage and exit status 2 (the console script: tests/test_model.py)
        with pytest.raises((SystemExit, argparse.ArgumentError)) as err:
            parser.parse_args(["tune", *args])
        text = str(err.value) + capsys.readouterr().err
        assert (err.type is argparse.ArgumentError or err.value.code == 2) and msg in text, (args, text)


@pytest.fixture
def fake_tuning(monkeypatch):
    """The optimisation loop and the held-out rollouts replaced by stand-ins
    (both are tested above; compiling them for a test of the job would cost minutes).
    Returns the dict the fake loop records its arguments in."""
    fake_metrics = fake_heldout_metrics()
    calls = {}

    def fake_evaluator(model, duration, controller="synchronous", **stack):
        calls["evaluator_controller"], calls["evaluator_stack"] = controller, stack
        return lambda g, s: fake_metrics

    monkeypatch.setattr(loss_mod, "make_evaluator", fake_evaluator)

    def fake_tune(model, base, cfg, *, validate=None, **kw):
        calls["weights"], calls["cfg"], calls["kw"] = cfg.problem.weights, cfg, kw
        v0 = {"iteration": 0, **validate(base)}
        last = base._replace(k_rl=0.4)
        # the row's keys in another order than an uninterrupted run's (as a
        # resumed run's once came back from the checkpoint): the header is fixed
        row = {"iteration": 0, "cost": 2.0, "grad_norm": 1.0, "skipped": 0, "seconds": 0.1, "term_grip": 1.0}
        history = [dict(sorted(row.items()))]
        return TuneResult(base, history, [v0], v0, last, None)

    monkeypatch.setattr(tune_mod, "tune", fake_tune)

    def fake_sim_to_sim(model, gains, baseline, scenarios, duration, *, n=4, mjx_rows=None, **kw):
        """MuJoCo C's rollouts replaced: the held-out MJX rows as given, MuJoCo C's
        settled peak after tuning 0.03 N in every scenario (MJX: 0.01, 0.02)."""
        calls["mujoco_check"], calls["mjx_rows"], calls["mujoco_stack"] = n, mjx_rows, kw.get("stack")
        m = min(n, len(mjx_rows["before"]))
        per = {
            "mjx_before": mjx_rows["before"][:m],
            "mjx_after": mjx_rows["after"][:m],
            "mujoco_before": mjx_rows["before"][:m],
            "mujoco_after": [dict(r, settled_peak_resultant_N=0.03) for r in mjx_rows["after"][:m]],
        }
        return _crosscheck.sim_to_sim_verdict(per, m, duration)

    monkeypatch.setattr(_crosscheck, "sim_to_sim", fake_sim_to_sim)
    return calls


def _run_tune(model, out, cfg=None, starts=1, **kw):
    """``jaxsync tune``'s job (``pipeline.run_tune``; ``starts.run_tune`` with starts) with one iteration
    and no MuJoCo C check unless told."""
    cfg = cfg if cfg is not None else TuneConfig(iterations=1)
    job = pipeline.run_tune if starts == 1 else functools.partial(starts_mod.run_tune, starts=starts)
    return job(model, cfg, out=str(out), **{"mujoco_check": False, "log": lambda m: None, **kw})


def test_tune_job_writes_its_results(model, tmp_path, fake_tuning):
    """The job's plumbing (files, summary keys, selected vs last gains)."""
    calls = fake_tuning
    out = tmp_path / "run"
    cfg = TuneConfig(problem=Problem(weights=CostWeights(grip=3.0)), iterations=1)
    summary = _run_tune(model, out, cfg, mujoco_check=True, options={"weight": ["grip=3"]})
    cfg = calls["cfg"]
    assert calls["weights"].grip == 3.0 and cfg.training.task == "full" and cfg.data.heldout_batch == 16
    assert summary.peak_before == pytest.approx(0.015) and summary.to_dict() == json.loads(
        (out / "summary.json").read_text()
    )
    summary = json.loads((out / "summary.json").read_text())
    for key in (
        "initial_cost",
        "final_cost",
        "heldout_settled_peak_resultant_N_before",
        "heldout_settled_peak_resultant_N_after",
        "heldout_grip_force_error_rel_before",
        "heldout_grip_force_error_rel_after",
        "wall_time_s",
        "iterations",
        "options",
        "selected_iteration",
        "validation",
        "weights",
        "config",
    ):
        assert key in summary, key
    assert summary["heldout_settled_peak_resultant_N_before"] == pytest.approx(0.015)
    assert summary["options"]["weight"] == ["grip=3"] and summary["config"]["problem"]["weights"]["grip"] == 3.0
    # the MuJoCo C check ran (a stand-in here) and is recorded beside MJX's figures
    assert calls["mujoco_check"] == 4 and summary["mujoco_check"]["factor_mujoco"] == pytest.approx(0.5)
    assert summary["mujoco_check"]["mjx_before_N"] == pytest.approx(0.015) and summary["mujoco_check"]["agree"] is False
    # MJX's side is the held-out scoring's rows, passed on, not rolled out again
    assert [r["settled_peak_resultant_N"] for r in calls["mjx_rows"]["before"]] == [0.01, 0.02]
    selected = json.loads((out / "gains.json").read_text())["gains"]
    last = json.loads((out / "gains_last.json").read_text())["gains"]
    assert selected["k_rl"] == 0.5 and last["k_rl"] == 0.4
    for f in ("history.csv", "loss.png"):
        assert (out / f).stat().st_size > 0
    header = (out / "history.csv").read_text().splitlines()[0]
    assert header == "iteration,cost,grad_norm,skipped,seconds,term_grip"


def test_tune_job_tunes_the_named_controller_under_bounds(model, tmp_path, fake_tuning):
    """The problem's controller reaches the loop, the evaluator and every file; its bounds the loop."""
    calls = fake_tuning
    out = tmp_path / "run"
    problem = Problem(controller="object_impedance", max_impact_N=6.5)
    _run_tune(model, out, TuneConfig(problem=problem, iterations=1))
    p = calls["cfg"].problem
    assert p.controller == "object_impedance" and p.max_impact_N == 6.5 and p.max_stiffness_N_per_m is None
    assert calls["evaluator_controller"] == "object_impedance"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["controller"] == "object_impedance"
    assert summary["tune"]["tuned"] == ["imp_mass", "imp_stiffness", "imp_damping_ratio", *OBJECT]
    for name in ("gains.json", "gains_last.json"):
        assert json.loads((out / name).read_text())["controller"] == "object_impedance"
    # the fake held-out scenarios' mean first impact is 6.5 N: at the bound, within it
    assert summary["heldout_before"]["first_impact_peak_N"] == pytest.approx(6.5)
    assert summary["heldout_before"]["within_bounds"] is True
    assert summary["heldout_before"]["apparent_stiffness_normal_N_per_m"] > 1e3


def test_a_position_stack_tune_runs_its_stack_everywhere_and_records_it(model, tmp_path, fake_tuning):
    """TuneConfig(actuation="position", delay, servo_spread): the held-out and
    validation evaluator and the MuJoCo C check run that stack, the held-out
    scenarios draw its delays and servo scales, summary.json records it."""
    calls = fake_tuning
    cfg = TuneConfig(iterations=1, actuation="position", control_rate=250.0, delay=(0, 3), servo_spread=0.3)
    _run_tune(model, tmp_path / "run", cfg, mujoco_check=True)
    assert calls["evaluator_stack"] == {"actuation": "position", "control_substeps": 2, "distro": "jazzy"}
    assert calls["mujoco_stack"] == _actuation.Stack("position", 250.0, (0, 3))
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["stack"]["delay"] == [0, 3] and summary["stack"]["servo"]["source"]
    assert summary["config"]["training"]["actuation"] == "position" and summary["config"]["data"]["servo_spread"] == 0.3
    held = scenarios.heldout_scenarios(calls["cfg"])
    assert set(np.asarray(held.delay).tolist()) == {0.0, 1.0, 2.0, 3.0}
    scale = np.asarray(held.servo_scale)
    assert scale.min() >= 0.7 and scale.max() <= 1.3 and np.ptp(scale) > 0.2


def test_ros2_admittance_tunes_on_position_arms_only(model, tmp_path, fake_tuning, capsys):
    """tune --controller ros2_admittance: refused on the torque stack (library
    words; the command adds its flags); on the position stack the evaluator
    and the MuJoCo C check run it, its stiffness figures are the classical
    law's (the same spring at the pad), and the loss traces to the physics."""
    with pytest.raises(jaxsync.ConfigError, match="runs on position-controlled arms only") as err:
        TuneConfig(problem=Problem(controller="ros2_admittance")).validate()
    assert err.value.inputs == ("controller", "actuation")
    assert main(["tune", "--controller", "ros2_admittance", "--out", str(tmp_path / "t")]) == 2
    assert "(--controller, --actuation)" in capsys.readouterr().err and not (tmp_path / "t").exists()
    cfg = TuneConfig(
        problem=Problem(controller="ros2_admittance"), iterations=1, actuation="position", delay=(0, 3), distro="humble"
    )
    _run_tune(model, tmp_path / "run", cfg, mujoco_check=True)
    assert calls_of(fake_tuning) == (
        "ros2_admittance",
        {"actuation": "position", "control_substeps": 1, "distro": "humble"},
    )  # the release chosen runs in every evaluation
    assert fake_tuning["mujoco_stack"].distro == "humble"
    assert fake_tuning["cfg"].problem.tuned.tuned == ("imp_mass", "imp_stiffness", "imp_damping_ratio")
    assert fake_tuning["cfg"].problem.tuned.deploy_dt == float(model.mj_model.opt.timestep)  # held deployable
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["config"]["problem"]["spec"]["deployed_rule"] == {"control_period_s": 0.002, "margin": 1.5}
    g = _gains.default_gains(model, "position")
    classical = loss_mod.compliance_fn(model, "classical")(g)
    assert summary["heldout_before"]["apparent_stiffness_normal_N_per_m"] == pytest.approx(float(classical))
    assert json.loads((tmp_path / "run" / "gains.json").read_text())["controller"] == "ros2_admittance"
    assert summary["stack"]["ros_distro"] == "humble" and summary["config"]["training"]["distro"] == "humble"
    # gains the exported rule would run unstably start raised to its margin, and the job says so
    g = _gains.default_gains(model, "position")
    soft = g._replace(imp_mass=g.imp_mass.at[:, 2].multiply(0.5))
    said = []
    _run_tune(model, tmp_path / "soft", cfg, gains=soft, log=said.append)
    raised = r"imp_mass: 1\.5\d* -> 3\.0\d* \(masses raised to the exported rule's stability margin at 0\.002 s"
    assert any(re.search(raised, line) for line in said), said


def test_the_rule_plus_the_coupling_tunes_from_its_own_defaults(model, tmp_path, fake_tuning):
    """tune --controller ros2_synchronous without --gains starts from that
    controller's defaults (k_rk = -k_lk = 0.25), not the synchronous law's."""
    from jaxsync.io import gains_file  # noqa: PLC0415 -- this test alone reads a gains file back

    cfg = TuneConfig(problem=Problem(controller="ros2_synchronous"), iterations=1, actuation="position")
    _run_tune(model, tmp_path / "run", cfg)
    start = gains_file.load(str(tmp_path / "run" / "gains.json"))  # the stand-in loop keeps its start
    assert float(start.k_rk) == 0.25 == -float(start.k_lk)
    assert float(_gains.default_gains(model, "position").k_rk) == 0.5


def test_the_rules_tuned_gains_export_as_the_rule_alone(model, tmp_path, fake_tuning, capsys):
    """tune --controller ros2_admittance starts from the rule's own defaults, none of the paper's
    coupling (the rule never reads it), so its gains export as the rule alone: synchronisation.yaml
    configures ros2_admittance, not a coupling the run never tuned, and says nothing of one."""
    import yaml  # noqa: PLC0415 -- this test alone reads exported files

    cfg = TuneConfig(problem=Problem(controller="ros2_admittance"), iterations=1, actuation="position")
    _run_tune(model, tmp_path / "run", cfg)
    argv = ["export", str(tmp_path / "run" / "gains.json"), "--format", "ros2-admittance"]
    capsys.readouterr()
    assert main([*argv, "--out", str(tmp_path / "ros2")]) == 0
    sync = yaml.safe_load(open(tmp_path / "ros2" / "synchronisation.yaml"))
    params = sync["dual_arm_synchronisation"]["ros__parameters"]
    assert params["controller"] == "ros2_admittance"
    assert [params[k] for k in ("k_rk", "k_lk", "k_rl", "k_ll")] == [0.0] * 4
    assert "not tuned through the admittance rule it couples" not in capsys.readouterr().out


def test_the_loop_gain_is_tuned_by_default_where_the_servo_limits_it(model, tmp_path, fake_tuning, monkeypatch):
    """A controller's default set gains kp_pos and the command's feed-forward
    of the plan's acceleration (ff_acc) on position-controlled arms whose servo lowered the
    joint-command loop (the iiwa-like pair's stands in here for the paper
    model's, which does not), for jaxsync's own laws only; named parameters,
    what is frozen, the torque stack and the rule keep their sets; the
    feed-forward is refused where there is no joint command (torque) or no
    law that reads it (the rule); the job says why and records the set it
    tuned."""
    robots = os.path.join(os.path.dirname(jaxsync.default_model_path()), "robots")
    iiwa = jaxsync.load_model(os.path.join(robots, "iiwa14_pair.yaml"), visual=False)
    assert _gains.servo_limits_loop(iiwa) and not _gains.servo_limits_loop(model)
    sync = _params.spec_for("synchronous")
    added = ("kp_pos", "ff_acc")
    assert sync.for_model("synchronous", iiwa, "position").tuned == _params.DEFAULT_TUNED + added
    assert sync.for_model("synchronous", model, "position") is sync
    assert sync.for_model("synchronous", iiwa, "torque") is sync
    classical = _params.spec_for("classical")
    assert classical.for_model("classical", iiwa, "position").tuned[-2:] == added
    got = _params.spec_for("synchronous", frozen=["kp_pos"]).for_model("synchronous", iiwa, "position")
    assert got.tuned == _params.DEFAULT_TUNED + ("ff_acc",)
    for spec in (
        _params.spec_for("synchronous", ["k_rk", "imp_mass"]),
        _params.spec_for("synchronous", frozen=list(added)),
    ):
        assert spec.for_model("synchronous", iiwa, "position") is spec
    fed = _params.spec_for("synchronous", ["k_rk", "ff_acc"])
    with pytest.raises(jaxsync.ConfigError, match="ff_acc: the joint command's feed-forward acts on position-"):
        fed.for_model("synchronous", model, "torque")
    with pytest.raises(jaxsync.ConfigError, match="the ros2_admittance controller does not use ff_vel"):
        _params.check_tuned(("imp_mass", "ff_vel"), "ros2_admittance")
    rule = _params.spec_for("ros2_admittance")
    held = rule.for_model("ros2_admittance", iiwa, "position")  # held within the exported rule's margin only
    assert held.tuned == rule.tuned and held.deploy_dt == float(iiwa.mj_model.opt.timestep) and rule.deploy_dt is None
    monkeypatch.setattr(_params, "servo_limits_loop", lambda m: True)
    said = []
    cfg = TuneConfig(iterations=1, actuation="position", delay=(0, 3))
    _run_tune(model, tmp_path / "run", cfg, log=said.append)
    assert fake_tuning["cfg"].problem.tuned.tuned[-2:] == added
    assert tuple(json.loads((tmp_path / "run" / "summary.json").read_text())["tune"]["tuned"][-2:]) == added
    assert any(line.startswith("kp_pos, ff_acc are tuned too") and "lambda = 40 1/s" in line for line in said)
    cfg = TuneConfig(problem=Problem(controller="ros2_admittance"), iterations=1, actuation="position")
    _run_tune(model, tmp_path / "rule", cfg)
    assert fake_tuning["cfg"].problem.tuned.tuned == ("imp_mass", "imp_stiffness", "imp_damping_ratio")


def calls_of(calls):
    return calls["evaluator_controller"], calls["evaluator_stack"]


def test_the_ft_filter_is_drawn_log_uniform_from_its_own_key():
    base = jaxsync.default_scenario()
    plain = sample_scenarios(jax.random.key(3), 8, base, stratified=True)
    drawn = sample_scenarios(jax.random.key(3), 8, base, stratified=True, ft_filter=(0.05, 1.0))
    a = np.sort(np.asarray(drawn.ft_filter))
    np.testing.assert_allclose(a, np.exp(np.linspace(np.log(0.05), 0.0, 8)), rtol=1e-12)  # evenly in log
    assert np.all(np.asarray(plain.ft_filter) == 1.0)
    np.testing.assert_array_equal(np.asarray(plain.object_mass), np.asarray(drawn.object_mass))
    cfg = TuneConfig(actuation="position", ft_filter=(0.1, 0.5)).validate()
    held = np.asarray(scenarios.heldout_scenarios(cfg).ft_filter)
    assert held.min() >= 0.1 - 1e-12 and held.max() <= 0.5 + 1e-12 and len(set(held.tolist())) > 1
    for bad in ((0.5, 0.1), (0.0, 1.0), (0.5, 2.0)):
        with pytest.raises(jaxsync.ConfigError, match="ft_filter must be a range"):
            TuneConfig(ft_filter=bad).validate()


def test_delay_and_servo_draws_span_their_ranges_and_leave_the_rest():
    base = jaxsync.default_scenario()
    plain = sample_scenarios(jax.random.key(3), 8, base, stratified=True)
    drawn = sample_scenarios(jax.random.key(3), 8, base, stratified=True, delay=(1, 4), servo_spread=0.3)
    assert sorted(np.asarray(drawn.delay).tolist()) == [1, 1, 2, 2, 3, 3, 4, 4]
    np.testing.assert_allclose(np.sort(np.asarray(drawn.servo_scale)), np.linspace(0.7, 1.3, 8), rtol=1e-12)
    for f in ("object_mass", "contact_timeconst", "friction", "force_noise", "object_offset", "grip_force"):
        np.testing.assert_array_equal(np.asarray(getattr(plain, f)), np.asarray(getattr(drawn, f)), err_msg=f)
    np.testing.assert_array_equal(np.asarray(plain.delay), 0.0)
    np.testing.assert_array_equal(np.asarray(plain.servo_scale), 1.0)
    iid = np.asarray(sample_scenarios(jax.random.key(3), 64, base, delay=(0, 3)).delay)
    assert set(iid.tolist()) == {0.0, 1.0, 2.0, 3.0}  # whole periods, every one of them
    fixed = sample_scenarios(jax.random.key(3), 4, base, delay=(2, 2))
    np.testing.assert_array_equal(np.asarray(fixed.delay), 2.0)


def test_tune_cli_parses_into_one_job_and_prints_it(tmp_path, monkeypatch, capsys):
    """jaxsync tune is its flags read into a TuneConfig, one call of
    pipeline.run_tune and the summary's lines; a library error comes out as
    one line naming the flags, exit 2, with no folder left behind."""
    got = {}

    def job(model, cfg, **kw):
        got.update(model=model, cfg=cfg, **kw)
        return None  # another process than the first of a multi-process run: nothing to print

    monkeypatch.setattr(pipeline, "run_tune", job)
    argv = ["tune", "--out", str(tmp_path / "o"), "--weight", "grip=3", "--iterations", "1", "--method", "sgd"]
    argv += ["--controller", "object_impedance", "--max-impact", "6.5", "--freeze", "imp_mass", "--lr", "0.01"]
    assert main(argv) == 0
    cfg = got["cfg"]
    assert cfg.problem.weights.grip == 3.0 and cfg.problem.controller == "object_impedance"
    assert cfg.problem.max_impact_N == 6.5 and cfg.problem.max_stiffness_N_per_m is None
    assert cfg.problem.tuned.tuned == ("imp_stiffness", "imp_damping_ratio", *OBJECT)
    assert (cfg.method.name, cfg.method.learning_rate, cfg.loop.iterations) == ("sgd", 0.01, 1)
    assert (cfg.training.task, cfg.data.heldout_batch, cfg.loop.validate_every) == ("full", 16, 5)
    assert got["model"] is None and got["gains"] is None and got["options"]["weight"] == ["grip=3"]
    assert cfg.stack() == _actuation.TORQUE and cfg.data.servo_spread == 0.0
    assert capsys.readouterr().out == ""
    argv = ["tune", "--out", str(tmp_path / "o"), "--actuation", "position", "--delay", "0:3", "--servo-spread", "0.3"]
    assert main([*argv, "--control-rate", "250", "--ros-distro", "rolling"]) == 0
    cfg = got["cfg"]
    assert cfg.stack() == _actuation.Stack("position", 250.0, (0, 3), "rolling") and cfg.data.servo_spread == 0.3

    def refused(model, cfg, *, out, **kw):
        _results.ensure_writable_dir(out)  # the job made the folder, then refused
        raise jaxsync.ConfigError("resume and restart: give one of them", inputs=("resume", "restart"))

    monkeypatch.setattr(pipeline, "run_tune", refused)
    assert main(["tune", "--out", str(tmp_path / "r"), "--resume", "--restart"]) == 2
    err = capsys.readouterr().err
    assert err == "jaxsync tune: error: resume and restart: give one of them (--resume, --restart)\n"
    assert not (tmp_path / "r").exists()
    for flags, message in [
        (["--weight", "grip"], "NAME=VALUE"),
        (["--freeze", "bar"], "unknown parameter(s) ['bar']"),
    ]:  # read before the job is called
        assert main(["tune", "--out", str(tmp_path / "x"), *flags]) == 2
        assert message in capsys.readouterr().err


def test_the_summary_is_said_in_lines(model, tmp_path, fake_tuning):
    out = tmp_path / "run"
    summary = _run_tune(model, out, mujoco_check=True)
    lines = summary_lines(summary, str(out))
    assert lines[0] == "held-out settled peak resultant: 0.01500 N -> 0.01500 N (unchanged)"
    assert lines[1] == "held-out grip-force error: 0.0050 -> 0.0050"
    assert "WARNING: MuJoCo C and MJX disagree" in lines[2] and lines[-1].startswith(f"results in {out}: gains.json")


def test_a_position_stack_tune_says_whether_its_gains_export(model, tmp_path, fake_tuning):
    """On position-controlled arms the summary records whether jaxsync export --format ros2-admittance
    writes the kept gains, and the lines warn where it refuses them (jaxsync's own law, tuned with a
    mass the stock rule runs unstably), not where it writes them."""
    g = _gains.default_gains(model, "position")
    soft = g._replace(imp_mass=g.imp_mass.at[:, 2].multiply(0.5))  # dt D/M past the rule's margin
    cfg = TuneConfig(problem=Problem(controller="classical"), iterations=1, actuation="position")
    summary = _run_tune(model, tmp_path / "classical", cfg, gains=soft)  # the stand-in loop keeps its start
    d = json.loads((tmp_path / "classical" / "summary.json").read_text())["deployment"]
    assert d["format"] == "ros2-admittance" and d["update_rate_hz"] == 500 and not d["exports"]
    assert "pad axis z unstable" in d["problems"][0]
    warned = [line for line in summary_lines(summary, "x") if line.startswith("WARNING: jaxsync export")]
    assert len(warned) == 1 and "refuses these gains at 500 Hz" in warned[0] and "(and 1 more)" in warned[0]
    rule = TuneConfig(problem=Problem(controller="ros2_admittance"), iterations=1, actuation="position")
    summary = _run_tune(model, tmp_path / "rule", rule)
    assert summary.deployment["exports"] and summary.deployment["problems"] == []
    assert not any(line.startswith("WARNING: jaxsync export") for line in summary_lines(summary, "x"))
    torque = _run_tune(model, tmp_path / "torque", TuneConfig(problem=Problem(controller="classical"), iterations=1))
    assert torque.deployment is None


def test_the_kept_start_is_the_best_qualifying_one_on_validation():
    v0 = {"iteration": 0, "settled_peak_resultant_N": 0.02, "grip_force_error_rel": 0.01, "dropped": 0, "nonfinite": 0}
    a = dict(v0, iteration=40, settled_peak_resultant_N=0.004)
    b = dict(v0, iteration=55, settled_peak_resultant_N=0.001)
    loose = dict(b, grip_force_error_rel=0.02)  # lower, but gripping worse than the start
    assert starts_mod.select_start([[v0, a], [v0, b]], [40, 55]) == 1
    assert starts_mod.select_start([[v0, a], [v0, loose]], [40, 55]) == 0
    assert starts_mod.select_start([[v0, a], [v0, b], [v0, dict(b)]], [40, 55, 55]) == 1  # a tie: the first
    assert starts_mod.select_start([[v0], [v0]], [0, 0]) == 0  # none improved on the start


def test_starts_tune_on_successive_seeds_and_keep_the_best_validated(model, tmp_path, fake_tuning, monkeypatch):
    """Each start a whole run in OUT/seed_<s> on its own training seed; the one with the
    lowest validation peak copied to OUT; resumed starts read back, not run again."""
    peaks = {3: 0.004, 4: 0.001}
    tuned = []

    def fake_tune(model, base, cfg, *, validate=None, **kw):
        seed = cfg.data.seed
        tuned.append(seed)
        v0 = {"iteration": 0, **validate(base)}
        v1 = dict(v0, iteration=1, settled_peak_resultant_N=peaks[seed])
        g = base._replace(k_rl=0.1 * seed)
        row = {"iteration": 0, "cost": 2.0, "grad_norm": 1.0, "skipped": 0, "seconds": 0.1}
        return TuneResult(g, [row], [v0, v1], v1, g._replace(k_ll=0.3), None)

    monkeypatch.setattr(tune_mod, "tune", fake_tune)
    # a robot file's object (as a job records it in its config, which a finished start is read back by)
    monkeypatch.setattr(scenarios, "model_overrides", lambda model: (("object_mass", 0.5),))
    out = tmp_path / "run"
    cfg = TuneConfig(iterations=1, seed=3)
    logs = []
    summary = _run_tune(model, out, cfg, starts=2, log=logs.append)
    assert tuned == [3, 4] and [s["seed"] for s in summary.starts] == [3, 4]
    # the starting gains scored on the held-out scenarios once, by the first start; each folder holds them
    assert sum(m.startswith("held-out evaluation before tuning") for m in logs) == 1
    before = [(out / f"seed_{s}" / "heldout_before.json").read_bytes() for s in (3, 4)]
    assert before[0] == before[1]
    assert [s["kept"] for s in summary.starts] == [False, True]
    assert [s["validation"]["settled_peak_resultant_N"] for s in summary.starts] == [0.004, 0.001]
    assert summary.config["data"]["seed"] == 4 and summary.to_dict() == json.loads((out / "summary.json").read_text())
    assert json.loads((out / "gains.json").read_text())["gains"]["k_rl"] == pytest.approx(0.4)
    assert (out / "gains.json").read_bytes() == (out / "seed_4" / "gains.json").read_bytes()
    for s in (3, 4):
        assert json.loads((out / f"seed_{s}" / "summary.json").read_text())["config"]["data"]["seed"] == s
    assert summary_lines(summary, str(out))[-2] == f"kept the start on seed 4 of 2 (the lowest validation settled " \
        f"peak; every start in {out}/seed_*)"  # fmt: skip
    with pytest.raises(jaxsync.ConfigError, match="holds tuning starts"):  # no resume, no restart: nothing overwritten
        _run_tune(model, out, cfg, starts=2)
    again = _run_tune(model, out, cfg, starts=2, resume=True)  # every start finished: read back
    assert tuned == [3, 4] and again.starts == summary.starts
    (out / "seed_3" / "summary.json").unlink()  # a start that did not finish (here: with no checkpoint)
    rerun = _run_tune(model, out, cfg, starts=2, resume=True).starts  # that one run again
    assert [(r["seed"], r["kept"], r["validation"]) for r in rerun] == [
        (r["seed"], r["kept"], r["validation"]) for r in summary.starts
    ]
    assert tuned == [3, 4, 3]
    _run_tune(model, out, cfg, starts=2, restart=True)
    assert tuned == [3, 4, 3, 3, 4]
    with pytest.raises(jaxsync.ConfigError, match="no tuning starts in"):
        _run_tune(model, tmp_path / "none", cfg, starts=2, resume=True)
    with pytest.raises(jaxsync.ConfigError, match="validate_every must be positive with starts > 1"):
        _run_tune(model, tmp_path / "x", cfg.replace(validate_every=0), starts=2)
    with pytest.raises(jaxsync.ConfigError, match="seeds must differ"):  # seed 500 is the validation seed
        _run_tune(model, tmp_path / "x", cfg.replace(seed=499), starts=2)
    assert not (tmp_path / "none").exists() and not (tmp_path / "x").exists()


def test_vector_gains_round_trip_through_the_parametrisation():
    g = _gains.default_gains()
    for spec in (TuneSpec(tuned=OBJECT + FORCE), TuneSpec(tuned=OBJECT + FORCE, isotropic=True)):
        back = spec.to_gains(spec.init(g), g)
        if not spec.isotropic:
            for f in ("obj_mass", "obj_stiffness", "obj_damping", "force_p", "force_i"):
                np.testing.assert_allclose(getattr(back, f), getattr(g, f), rtol=1e-9, err_msg=f)
        assert spec.size() == (2 if spec.isotropic else 6) * 5
        moved = spec.to_gains(jax.tree_util.tree_map(lambda v: v + 0.3, spec.init(g)), g)
        used = spec.to_gains(spec.init(g), g)  # shared over axes when isotropic
        np.testing.assert_allclose(np.asarray(moved.force_p), np.exp(0.3) * np.asarray(used.force_p), rtol=1e-9)
        zeta = np.asarray(moved.obj_damping) / (2 * np.sqrt(np.asarray(moved.obj_mass * moved.obj_stiffness)))
        assert np.all((zeta > ZETA_MIN) & (zeta < ZETA_MAX))


def test_a_folder_holding_a_run_needs_resume_or_restart(model, tmp_path, fake_tuning):
    """A checkpoint in the output folder without resume is refused (naming
    resume and restart), before anything is evaluated or written; restart
    starts over and leaves none of the old run's files behind."""
    out = tmp_path / "run"
    out.mkdir()
    old = {"checkpoint.npz": "old", "gains.json": '{"gains": {"k_rl": 0.1}}', "summary.json": "{}"}
    for name, text in old.items():
        (out / name).write_text(text)
    for extra, message, inputs in [
        ({}, "resume to continue it, restart to discard it and start over, or choose another output folder",
         ("resume", "restart", "out")),
        ({"resume": True, "restart": True}, "give one of them", ("resume", "restart")),
    ]:  # fmt: skip
        with pytest.raises(jaxsync.ConfigError, match=message) as err:
            _run_tune(model, out, **extra)
        assert err.value.inputs == inputs
        assert "cfg" not in fake_tuning  # refused before tuning
    assert {p.name: p.read_text() for p in out.iterdir()} == old  # nothing touched
    (out / "checkpoint.npz").unlink()  # results without a checkpoint: only restart
    with pytest.raises(jaxsync.ConfigError, match="no checkpoint to resume from: restart to discard them"):
        _run_tune(model, out)
    (out / "checkpoint.npz").write_text("old")
    _run_tune(model, out, restart=True)
    assert fake_tuning["kw"]["resume"] is False
    assert not (out / "checkpoint.npz").exists()  # the old run's (the stand-in loop writes none)
    assert json.loads((out / "gains.json").read_text())["gains"]["k_rl"] == 0.5
    assert json.loads((out / "summary.json").read_text())["iterations"] == 1


def test_result_line_says_higher_when_tuning_made_it_worse():
    assert change_text(0.01183, 0.10249) == " (8.66x higher)"
    assert change_text(0.01062, 0.00390) == " (2.72x lower)"
    assert change_text(None, 0.1) == "" and change_text(0.1, None) == ""


@pytest.mark.parametrize("clip", [0.0, -1.0, float("nan")])
def test_clip_must_be_positive(clip):
    with pytest.raises(jaxsync.ConfigError, match="clip"):
        TuneConfig(clip_norm=clip).validate()


@pytest.mark.parametrize(
    "data, message",
    [({"k_rk": True}, "not true/false"), ({"k_rk": "abc"}, "a number"), (5, "JSON object"), ({"k_rk": []}, "number")],
)
def test_gains_values_must_be_numbers(tmp_path, capsys, data, message):
    with pytest.raises(jaxsync.ConfigError, match=message):
        _gains.from_dict(data)
    path = tmp_path / "g.json"
    path.write_text(json.dumps({"gains": data}))
    assert main(["compare", "--gains", str(path), "--out", str(tmp_path / "out")]) == 2
    assert message.split()[-1] in capsys.readouterr().err


def test_checkpoint_keeps_records_plain(tmp_path):
    """History rows and validation entries come back as the Python values they
    were (a 0-d array 'iteration' crashed a resumed run at its end)."""
    state = {
        "theta": {"k_rk": jax.numpy.asarray(0.5)},
        "opt_state": (),
        "kept": {5: {"k_rk": jax.numpy.asarray(0.4)}},
        "history": [{"iteration": 0, "cost": 1.25}],
        "validation": [{"iteration": 5, "settled_peak_resultant_N": 0.01, "per_scenario_peak_N": [0.01]}],
        "iteration": 5,
    }
    checkpoint.save(str(tmp_path / "c.pkl"), state)
    back = checkpoint.load(str(tmp_path / "c.pkl"))
    assert back["validation"] == state["validation"] and back["history"] == state["history"]
    assert type(back["validation"][0]["iteration"]) is int and type(back["history"][0]["cost"]) is float
    assert back["kept"][back["validation"][0]["iteration"]]["k_rk"] == 0.4


def test_eta_leaves_out_the_compiling_first_iteration(model, monkeypatch):
    """The progress bar's rate and ETA come from the iterations after the
    first, which traces and compiles the gradient (an ETA of 08:45 for a run
    then taking seconds per step). The gradient is a stand-in whose first
    call takes 1 s ("compiling") and later ones next to nothing."""
    etas = []

    class RecordingBar(tqdm_module.tqdm):
        def update(self, n=1):
            shown = super().update(n)
            d = self.format_dict
            rate = d["rate"] or ((d["n"] - d["initial"]) / d["elapsed"] if d["elapsed"] else None)
            etas.append((d["n"], (d["total"] - d["n"]) / rate if rate else None))
            return shown

    monkeypatch.setattr(tune_mod, "tqdm", RecordingBar)  # the bar tune() draws
    calls = []

    def fake_traced(loss, model, base, cfg, args, log):
        def value_and_grad(theta, scenarios):
            calls.append(1)
            if len(calls) == 1:
                time.sleep(1.0)
            zeros = jax.tree_util.tree_map(jax.numpy.zeros_like, theta)
            return (jax.numpy.asarray(1.0), {"grip": jax.numpy.asarray(1.0)}), zeros

        return value_and_grad

    monkeypatch.setattr(tune_mod, "traced_value_and_grad", fake_traced)
    cfg = TuneConfig(iterations=4, batch=1, validate_every=0, task="short", method="adam")
    tune(model, _gains.default_gains(), cfg, progress=True)
    assert len(calls) == 4
    (eta,) = [e for n, e in etas if n == 2]
    assert eta is not None and eta < 0.75, etas  # 2 iterations left; counting the first: 2 s or more


# ---------------------------------------------------------------- methods


def _quadratic(scale=(1.0, 100.0, 1e4)):
    a = np.diag(scale)
    return Oracle(
        value_and_grad=lambda x: (0.5 * x @ a @ x, a @ x),
        values=lambda xs: 0.5 * np.einsum("pi,ij,pj->p", xs, a, xs),
    )


@pytest.mark.parametrize("name", ["adam", "lbfgs", "cmaes", "cmaes-lbfgs"])
def test_methods_minimise_an_ill_conditioned_quadratic(name):
    m, oracle = methods.get(name), _quadratic()
    state = m.init(np.ones(3), seed=0)
    f0 = 0.5 * (1 + 100 + 1e4)
    for _ in range(40):
        state, row = m.step(state, oracle)
    x = m.incumbent(state)
    f = 0.5 * float(x @ np.diag([1.0, 100.0, 1e4]) @ x)
    # L-BFGS learns the curvature (condition number 1e4); Adam's fixed steps do not get far in 40
    bound = {"adam": 0.01 * f0, "lbfgs": 1e-12, "cmaes": 1e-3, "cmaes-lbfgs": 1e-12}[name]
    assert f < bound, (name, f)
    if name in ("lbfgs", "cmaes-lbfgs"):
        assert oracle.gradient_calls < 120  # one to a few per iteration
    if name == "cmaes":
        assert oracle.gradient_calls == 0 and oracle.forward_rollouts == 40 * m.popsize
    with pytest.raises(jaxsync.ConfigError, match="method"):
        methods.get("newton")


def test_lbfgs_skips_non_finite_trials_and_keeps_the_iterate():
    calls = []

    def vg(x):
        calls.append(x.copy())
        return (float("nan"), np.full_like(x, np.nan)) if len(calls) > 1 else (float(x @ x), 2 * x)

    m = LBFGS(max_trials=3)
    state, row = m.step(m.init(np.ones(2)), Oracle(value_and_grad=vg))
    assert row["accepted"] == 0 and np.array_equal(m.incumbent(state), np.ones(2)) and len(calls) == 4


def _rosenbrock(x):
    a, b = x[:-1], x[1:]
    g = np.zeros_like(x)
    g[:-1] += -400 * a * (b - a**2) - 2 * (1 - a)
    g[1:] += 200 * (b - a**2)
    return float(np.sum(100 * (b - a**2) ** 2 + (1 - a) ** 2)), g


def test_lbfgs_backtracks_on_values_alone_with_the_same_iterates():
    """Given the oracle's forward-only value, L-BFGS's backtracking trials take
    no gradient: the same iterates step by step (also across a checkpoint),
    fewer gradient calls, and one value or one gradient per trial (plus the
    gradient at a point accepted on its value)."""
    plain, cheap = (
        Oracle(value_and_grad=_rosenbrock),
        Oracle(value_and_grad=_rosenbrock, value=lambda x: _rosenbrock(x)[0]),
    )
    m = LBFGS()
    sp, sc = m.init(np.full(4, -1.2)), m.init(np.full(4, -1.2))
    trials, backtracked, on_value = 0, 0, 0
    for i in range(80):
        sp, rp = m.step(sp, plain)
        v0 = cheap.value_calls
        sc, rc = m.step(sc, cheap)
        np.testing.assert_array_equal(m.incumbent(sc), m.incumbent(sp))
        assert rc["trials"] == rp["trials"] and rc["train_cost"] == rp["train_cost"]
        trials += rp["trials"]
        backtracked += rp["trials"] > 1
        on_value += rc["accepted"] and cheap.value_calls > v0  # accepted on a value: then its gradient
        if i == 20:
            sc = m.from_data(m.to_data(sc))  # the line-search memory survives a checkpoint
        if rp.get("converged"):
            assert rc.get("converged")
            break
    assert backtracked >= 3 and plain.gradient_calls == trials + 1  # the start's gradient, then one per trial
    assert cheap.value_calls > 0 and cheap.gradient_calls < plain.gradient_calls
    assert cheap.gradient_calls + cheap.value_calls == trials + 1 + on_value
    np.testing.assert_allclose(m.incumbent(sc), np.ones(4), atol=1e-3)


def test_tune_oracle_values_on_its_training_batch_and_follows_renewals():
    """jaxsync tune's method oracle: its forward-only value is the loss on the
    current training batch (the gradient's value there), also after a renewal."""
    theta = {"a": jax.numpy.array([0.5, -1.0]), "b": jax.numpy.array(2.0)}
    batches = {0: jax.numpy.array(1.0), 1: jax.numpy.array(3.0)}

    def loss(th, s):
        return s * (jax.numpy.sum(th["a"] ** 2) + th["b"] ** 2), {}

    vg = jax.jit(jax.value_and_grad(loss, has_aux=True))
    cfg = TuneConfig(iterations=1, batch=1, task="short", method="lbfgs")
    o = tune_mod._MethodOracle(loss, lambda scen: vg, theta, batches[0], cfg, None, batches.get).oracle
    x = np.array([1.0, 2.0, -0.5])
    for k, want in ((0, 1.0 * 5.25), (1, 3.0 * 5.25)):
        o.use(k)
        assert o.v(x) == pytest.approx(want) and o.vg(x)[0] == pytest.approx(want)
    assert o.value_calls == 2 and o.gradient_calls == 2


def test_lbfgs_renews_its_batch_after_converging_and_resumes_on_it():
    """On a batch whose minimum it has reached, L-BFGS takes the oracle's next
    batch (here: a quadratic centred elsewhere) and converges there; a state
    written to data and read back mid-run continues on the same batch; with no
    renewals left it reports convergence."""
    centres = [np.zeros(3), np.full(3, 0.5), np.array([1.0, -1.0, 0.2])]
    current = {"c": centres[0]}

    def vg(x):
        d = x - current["c"]
        return float(d @ d), 2 * d

    def renew(k):
        current["c"] = centres[k]

    m = LBFGS(renewals=2)
    oracle = Oracle(value_and_grad=vg, renew=renew)
    state, rows = m.init(np.ones(3)), []
    for _ in range(40):
        state, row = m.step(state, oracle)
        rows.append(row)
        if row.get("renewed") == 1:  # mid-run: written to data, read back, a fresh oracle on batch 0
            current["c"] = centres[0]
            oracle = Oracle(value_and_grad=vg, renew=renew)
            state = m.from_data(m.to_data(state))
        if row.get("converged"):
            break
    assert [r["renewed"] for r in rows if "renewed" in r] == [1, 2]
    assert rows[-1].get("converged") == 1 and oracle.batch == 2
    assert m.converged(state) and m.converged(m.from_data(m.to_data(state))) and not m.converged(m.init(np.ones(3)))
    np.testing.assert_allclose(m.incumbent(state), centres[2], atol=1e-6)
    # where the oracle cannot renew: converged on the first batch, as before
    m2, state2, rows2 = LBFGS(), LBFGS().init(np.ones(3)), []
    current["c"] = centres[0]
    for _ in range(40):
        state2, row = m2.step(state2, Oracle(value_and_grad=vg))
        rows2.append(row)
        if row.get("converged"):
            break
    assert rows2[-1].get("converged") == 1 and not any("renewed" in r for r in rows2)
    np.testing.assert_allclose(m2.incumbent(state2), centres[0], atol=1e-6)


def test_lbfgs_leaves_a_batch_it_lowers_by_ever_smaller_steps():
    """A batch whose cost holds a large constant without gradient (a dropped scenario's) and whose
    other part falls toward an asymptote: every step lowers it a little less. Counting a step that
    lowers it by at most ftol of the cost as none, L-BFGS converges there in a fraction of the steps
    it crawls without; on the same cost without the constant the test changes nothing."""

    def run(constant, ftol):
        def vg(x):
            return float(constant + np.exp(-x[0]) + x[1] ** 2), np.array([-np.exp(-x[0]), 2 * x[1]])

        m = LBFGS(ftol=ftol) if ftol is not None else LBFGS()
        oracle, state = Oracle(value_and_grad=vg), m.init(np.array([0.0, 0.5]))
        for i in range(200):
            state, row = m.step(state, oracle)
            if row.get("converged"):
                return i, m.incumbent(state)
        raise AssertionError("did not converge")

    steps, x = run(2e5, None)
    crawled, _ = run(2e5, 0.0)
    assert steps < 25 < 35 < crawled, (steps, crawled)
    assert np.exp(-x[0]) < 1e-3 and abs(x[1]) < 1e-2  # what is left is below the cost's resolution
    plain, plain0 = run(0.0, None), run(0.0, 0.0)
    assert plain[0] == plain0[0] and np.array_equal(plain[1], plain0[1])


def test_lbfgs_carries_its_curvature_to_a_fresh_batch():
    """On an ill-conditioned quadratic whose centre moves with the batch, the next batch starts
    from the last batch's curvature pairs (kept through a checkpoint) and converges there in
    fewer steps than starting over from steepest descent."""
    scales = np.array([1.0, 30.0, 900.0])
    # a minimum no float lands on (the gradient never exactly 0): 0.5 x.Hx - b.x + (x.x)^2 / 100
    centres = [np.array([0.21, 0.13, -0.37]), np.array([0.53, -0.11, -0.23])]
    current = {"c": centres[0]}

    def vg(x):
        b = scales * current["c"]
        return float(0.5 * x @ (scales * x) - b @ x + (x @ x) ** 2 / 100), scales * x - b + 0.04 * (x @ x) * x

    def renew(k):
        current["c"] = centres[k]

    def steps_on_second_batch(memory: bool) -> tuple[int, dict]:
        m = LBFGS(renewals=1, renewal_memory=memory, ftol=0.0)  # converged: no lower float, twice
        current["c"] = centres[0]
        oracle, state, after, first = Oracle(value_and_grad=vg, renew=renew), m.init(np.ones(3)), None, None
        for i in range(200):
            state, row = m.step(state, oracle)
            if row.get("renewed") == 1:
                state, after, first = m.from_data(m.to_data(state)), i, state
            if row.get("converged"):
                np.testing.assert_allclose(vg(m.incumbent(state))[1], 0.0, atol=1e-6)  # on the second batch's minimum
                return i - after, first
        raise AssertionError("did not converge")

    kept, renewed = steps_on_second_batch(True)
    forgotten, renewed_without = steps_on_second_batch(False)
    assert renewed["s"] and not renewed_without["s"]  # the pairs the fresh batch starts from
    assert kept < forgotten, (kept, forgotten)


def test_lbfgs_tunes_on_the_shared_program_and_checkpoints_its_state(model, tuning_program, tmp_path):
    """jaxsync tune --method lbfgs on tune's own (full-task, exact) gradient program:
    two iterations lower the training cost on its fixed batch, every accepted step
    satisfies Armijo's condition, and the checkpoint holds the method's state exactly."""

    cfg = tuning_program["cfg"].replace(iterations=2, checkpoint_every=1, validate_every=0, method="lbfgs")
    spec, base = tuning_program["spec"], tuning_program["base"]
    r = tune(model, base, cfg, out=str(tmp_path / "l"), progress=False)
    h = r.history
    assert [row["iteration"] for row in h] == [0, 1] and all(row["skipped"] == 0 for row in h)
    assert all(row["gradient_calls"] >= 1 for row in h)
    # the fixed batch's cost at the start, from the same program
    scen = training_batch(cfg, 0, training_base(cfg.training)[0])
    (c0, _), _ = tuning_program["value_and_grad"](spec.init(base), scen)
    assert h[0]["cost"] < float(c0) and h[1]["cost"] < h[0]["cost"]

    ckpt = str(tmp_path / "l" / "checkpoint.npz")
    saved = tune_state.resumed_state(ckpt, None, spec, base, methods.get("lbfgs"))
    mine = r.state.opt_state
    assert saved.iteration == 2
    np.testing.assert_array_equal(saved.opt_state["x"], mine["x"])
    assert len(saved.opt_state["s"]) == len(mine["s"]) >= 1
    for a, b in zip(saved.opt_state["y"], mine["y"], strict=True):
        np.testing.assert_array_equal(a, b)


def _fingerprint(scenarios) -> bytes:
    return b"".join(np.asarray(x).tobytes() for x in jax.tree_util.tree_leaves(scenarios))


def test_lbfgs_goes_on_with_fresh_batches_then_stops_when_no_step_lowers_the_cost(model, monkeypatch, tmp_path):
    """A line search that finds no lower cost twice in a row (the second time after
    the curvature memory is reset) is convergence on the batch: L-BFGS goes on
    from where it stands on a fresh training batch (the iteration-k batch of the
    run's seed), up to its 4 renewals; converged on the last, tune() stops,
    validates and checkpoints the last iterate and returns normally."""
    seen = []

    def fake_traced(loss, model, base, cfg, args, log):
        theta0 = args[0]

        def value_and_grad(theta, scenarios):  # the cost rises along -grad: every trial step fails
            seen.append(_fingerprint(scenarios))
            pairs = zip(jax.tree_util.tree_leaves(theta), jax.tree_util.tree_leaves(theta0), strict=True)
            d = sum(jax.numpy.sum((a - b) ** 2) for a, b in pairs)
            ones = jax.tree_util.tree_map(jax.numpy.ones_like, theta)
            return (1.0 + d, {"grip": jax.numpy.asarray(1.0)}), ones

        return value_and_grad

    def fake_forward(model, base, cfg, *, differentiated=True):  # the same cost, for the trials taken on values
        theta0 = cfg.problem.tuned.init(base)

        def loss(theta, scenarios):
            pairs = zip(jax.tree_util.tree_leaves(theta), jax.tree_util.tree_leaves(theta0), strict=True)
            return 1.0 + sum(jax.numpy.sum((a - b) ** 2) for a, b in pairs), {}

        return loss

    monkeypatch.setattr(tune_mod, "traced_value_and_grad", fake_traced)
    monkeypatch.setattr(tune_mod, "make_loss", fake_forward)  # no rollout is compiled
    cfg = TuneConfig(iterations=14, batch=1, validate_every=5, task="short", method="lbfgs")
    r = tune(model, _gains.default_gains(), cfg, out=str(tmp_path), progress=False, validate=_fake_validation)
    # two failed line searches per batch, 5 batches (the first and 4 fresh ones)
    assert [row["skipped"] for row in r.history] == [1] * 10
    assert [v["iteration"] for v in r.validation] == [0, 5, 10]  # the last iterate validated
    assert (tmp_path / "checkpoint.npz").exists()
    np.testing.assert_array_equal(np.asarray(r.gains.k_rk), np.asarray(_gains.default_gains().k_rk))
    # each batch's first evaluation is the start of its run of calls: 5 distinct batches, in order
    train_base = training_base(cfg.training)[0]
    expected = [_fingerprint(training_batch(cfg, k, train_base)) for k in range(5)]
    assert len(set(expected)) == 5
    assert list(dict.fromkeys(seen)) == expected
    # resumed (with iterations to spare), a converged run takes no step and validates nothing again
    calls = len(seen)
    again = tune(model, _gains.default_gains(), cfg.replace(iterations=20), out=str(tmp_path), resume=True,
                 progress=False, validate=_fake_validation)  # fmt: skip
    assert len(again.history) == 10 and len(seen) == calls and len(again.validation) == 3


def test_a_run_whose_iterates_drop_everything_stops_and_stays_stopped(model, monkeypatch, tmp_path):
    """Adam on a stand-in cost; the validation drops every scenario from
    iteration 10 on: after the second such validation (15) the run stops,
    checkpointed, the selected iterate before; resumed with iterations to
    spare, it takes no step. Lost at its last validation alone, a run ends
    where it would have."""

    def fake_traced(loss, model, base, cfg, args, log):
        def value_and_grad(theta, scenarios):
            ones = jax.tree_util.tree_map(jax.numpy.ones_like, theta)
            return (jax.numpy.asarray(1.0), {"grip": jax.numpy.asarray(1.0)}), ones

        return value_and_grad

    def validation(lost_from):
        def validate(g):
            calls.append(1)
            lost = len(calls) > 1 and (len(calls) - 1) * 5 >= lost_from
            held = {"settled_peak_resultant_N": 0.01 / len(calls), "grip_force_error_rel": 0.01, "dropped": 0}
            return {**held, "nonfinite": 0, **({"settled_peak_resultant_N": None, "dropped": 4} if lost else {})}

        return validate

    monkeypatch.setattr(tune_mod, "traced_value_and_grad", fake_traced)
    monkeypatch.setattr(tune_mod, "make_loss", lambda *a, **k: None)  # no rollout is compiled
    cfg = TuneConfig(iterations=30, batch=1, validate_every=5, task="short", method="adam", schedule="constant")
    calls = []
    r = tune(model, _gains.default_gains(), cfg, out=str(tmp_path / "a"), progress=False, validate=validation(10))
    assert len(r.history) == 15 and [v["iteration"] for v in r.validation] == [0, 5, 10, 15]
    assert r.selected["iteration"] == 5 and (tmp_path / "a" / "checkpoint.npz").exists()
    again = tune(model, _gains.default_gains(), cfg.replace(iterations=40), out=str(tmp_path / "a"), resume=True,
                 progress=False, validate=validation(10))  # fmt: skip
    assert len(again.history) == 15 and len(again.validation) == 4
    calls.clear()  # lost at the last validation only (30): the run goes to its end
    r = tune(model, _gains.default_gains(), cfg, out=str(tmp_path / "b"), progress=False, validate=validation(30))
    assert len(r.history) == 30 and r.validation[-1]["dropped"] == 4


def test_a_run_stops_converged_when_its_validation_figure_stops_moving(model, monkeypatch, tmp_path):
    """Adam on a stand-in cost; the validation figure falls, then stays within
    1 % (0.004 N, 0.00401 N, ...): with the plateau at 2 % over 4 validations
    the run stops at the first validation whose figure moved less than that
    since four validations before (iteration 30), says it converged and what
    it cost, and takes no step when resumed. With a tolerance of 0 it runs to
    its cap and says it did not converge; a tighter tolerance (0.1 %) does
    not hold on the same figures either."""

    def fake_traced(loss, model, base, cfg, args, log):
        def value_and_grad(theta, scenarios):
            ones = jax.tree_util.tree_map(jax.numpy.ones_like, theta)
            return (jax.numpy.asarray(1.0), {"grip": jax.numpy.asarray(1.0)}), ones

        return value_and_grad

    peaks = [0.01, 0.005, 0.004, 0.00401, 0.00399, 0.00402, 0.004, 0.00398, 0.00401, 0.004, 0.004]

    def validate(g):
        calls.append(1)
        return {"settled_peak_resultant_N": peaks[len(calls) - 1], "grip_force_error_rel": 0.01, "dropped": 0,
                "nonfinite": 0}  # fmt: skip

    monkeypatch.setattr(tune_mod, "traced_value_and_grad", fake_traced)
    monkeypatch.setattr(tune_mod, "make_loss", lambda *a, **k: None)  # no rollout is compiled
    cfg = TuneConfig(iterations=50, batch=3, validate_every=5, task="short", method="adam", schedule="constant",
                     plateau_tol=0.02)  # fmt: skip
    calls = []
    r = tune(model, _gains.default_gains(), cfg, out=str(tmp_path / "a"), progress=False, validate=validate)
    c = r.convergence
    assert len(r.history) == 30 and [v["iteration"] for v in r.validation] == [0, 5, 10, 15, 20, 25, 30]
    assert (c["converged"], c["reason"], c["iterations"]) == (True, "plateau", 30)
    assert (c["gradient_calls"], c["training_rollouts"], c["validation_rollouts"]) == (30, 90, 7 * 16)
    assert c["criterion"] == {"plateau_tol": 0.02, "plateau_validations": 4, "validate_every": 5, "iterations_cap": 50}
    assert convergence_text(c).startswith("converged (the validation figure moved by less than")
    again = tune(model, _gains.default_gains(), cfg, out=str(tmp_path / "a"), resume=True, progress=False,
                 validate=validate)  # fmt: skip
    assert len(again.history) == 30 and again.convergence["reason"] == "plateau"
    for tol in (0.0, 0.001):
        calls.clear()
        r = tune(model, _gains.default_gains(), cfg.replace(plateau_tol=tol), out=str(tmp_path / f"b{tol}"),
                 progress=False, validate=validate)  # fmt: skip
        assert len(r.history) == 50 and (r.convergence["converged"], r.convergence["reason"]) == (False, "cap")
        text = convergence_text(r.convergence)
        assert text.startswith("WARNING: not converged (the cap came before "), text
        assert ("moving by at most 0.1 % over 4 validations" in text) == (tol > 0), text


@pytest.mark.parametrize("tol", [-0.1, 1.0, float("nan")])
def test_the_plateau_tolerance_is_a_share(tol):
    with pytest.raises(jaxsync.ConfigError, match="plateau_tol must be a relative change"):
        TuneConfig(plateau_tol=tol).validate()


def test_tuned_gains_are_checked_on_mujoco_c(model, rollouts, shared_rollout, monkeypatch):
    """The gains before and after on MuJoCo C beside MJX, through
    the one sim-to-sim check (jaxsync.sim.crosscheck.sim_to_sim) with MJX's rows as tune
    has them from its held-out scoring; the factors agree here (the same control
    law, the same scenario), and a disagreement is flagged in the printed line."""
    s, g = rollouts["scenario"], rollouts["gains"]
    g2 = g._replace(k_rl=jax.numpy.asarray(0.2), k_ll=jax.numpy.asarray(0.2))
    batch = jax.tree_util.tree_map(lambda x: jax.numpy.asarray(x)[None], s)
    one = lambda x: jax.tree_util.tree_map(lambda v: jax.numpy.asarray(v)[None], x)  # noqa: E731
    run = lambda x: shared_rollout(model, x, s, controller="synchronous", duration=TEST_DURATION)  # noqa: E731
    mjx = {
        which: _crosscheck.metric_rows(one(_metrics.summarize(run(x), s)))
        for which, x in (("before", g), ("after", g2))
    }
    monkeypatch.setattr(_crosscheck, "rollout", shared_rollout)  # MuJoCo C's rollouts, run once for the session
    check = _crosscheck.sim_to_sim(model, g2, g, batch, TEST_DURATION, n=4, mjx_rows=mjx, log=lambda m: None)
    assert check["scenarios"] == 1
    assert check["per_scenario"]["mjx_before"] == mjx["before"]  # taken as given
    assert check["mjx_before_N"] == mjx["before"][0]["settled_peak_resultant_N"]
    assert check["mujoco_before_N"] == pytest.approx(check["mjx_before_N"], rel=0.05)
    assert check["mujoco_after_N"] == pytest.approx(check["mjx_after_N"], rel=0.05)
    assert check["mujoco_after_N"] != check["mjx_after_N"]  # MuJoCo C's own rollout, not MJX's row
    assert check["agree"] and "agree within 10 %" in mujoco_text(check)
    per = dict(check["per_scenario"])
    double = lambda r: dict(r, settled_peak_resultant_N=2 * r["settled_peak_resultant_N"])  # noqa: E731
    per["mujoco_after"] = [double(r) for r in per["mujoco_after"]]
    off = _crosscheck.sim_to_sim_verdict(per, 1, TEST_DURATION)
    assert not off["agree"] and "WARNING" in mujoco_text(off) and "below MJX's" in mujoco_text(off)


def test_a_checkpoint_from_before_a_gain_existed_resumes_where_that_gain_is_at_its_default():
    now = {"batch": 2, "gains_start": _gains.to_dict(_gains.default_gains())}
    before = {"batch": 2, "gains_start": {k: v for k, v in now["gains_start"].items() if k != "cpl_block"}}
    assert tune_state._gains_added_since(before, now) == now  # the run ran the gain at its default
    moved = {
        **now,
        "gains_start": {
            **now["gains_start"],
            "cpl_block": (np.asarray(now["gains_start"]["cpl_block"]) + 0.1).tolist(),
        },
    }
    assert tune_state._gains_added_since(before, moved) != moved  # not the default: another run
    assert tune_state._gains_added_since({**before, "batch": 4}, now) != now  # other settings still differ
