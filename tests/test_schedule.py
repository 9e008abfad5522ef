"""Gain schedules: blending, files, the tuned parameters, rollouts."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import TEST_DURATION, fast_scenario, paper_model

from jaxsync._errors import ConfigError
from jaxsync.cli import main
from jaxsync.control import gains as _gains
from jaxsync.control import schedule as _schedule
from jaxsync.io import gains_file
from jaxsync.optimize.studies import compare as _compare
from jaxsync.optimize.tuning.params import TuneSpec
from jaxsync.sim import metrics as _metrics
from jaxsync.sim import scenario as _scenario
from jaxsync.sim.rollout import rollout


def _bounds(s):
    """The phases' boundaries, as the closed loop passes them to the schedule."""
    return jnp.stack(_scenario.phase_times(s))


def test_weights_are_a_partition_exact_inside_phases_and_smooth_across_boundaries():
    s = _scenario.short_task()
    bounds = [float(b) for b in _scenario.phase_times(s)]
    ts = np.linspace(0.0, 1.7, 1701)
    w = np.stack([np.asarray(_schedule.weights(_bounds(s), t)) for t in ts])
    assert np.all(w >= 0) and np.allclose(w.sum(1), 1.0, atol=1e-15)
    half = _schedule.BLEND_S / 2
    edges = [0.0, *bounds, 10.0]
    for p in range(4):
        inside = (ts > edges[p] + half + 1e-9) & (ts < edges[p + 1] - half - 1e-9)
        assert inside.any()
        assert np.all(w[inside, p] == 1.0) and np.all(w[inside][:, [q for q in range(4) if q != p]] == 0.0)
    # at a boundary, half and half; the derivative in time is continuous (C2 smoothstep: no jump at the edges)
    for p, b in enumerate(bounds):
        np.testing.assert_allclose(np.asarray(_schedule.weights(_bounds(s), b))[p : p + 2], [0.5, 0.5], atol=1e-15)
        dw = jax.grad(lambda t, p=p: _schedule.weights(_bounds(s), t)[p + 1])
        assert float(dw(b - half)) == pytest.approx(0.0, abs=1e-12)
        assert float(dw(b)) == pytest.approx(15 / 8 / _schedule.BLEND_S)  # the quintic's peak slope


def test_blended_gains_and_their_derivative_against_finite_differences():
    s = _scenario.short_task()
    g = _gains.default_gains()
    sched = _schedule.constant(g)
    k = jnp.array([0.5, 0.3, 0.2, 0.1])
    sched = sched._replace(phases=sched.phases._replace(k_rk=k))
    t_sq = float(_scenario.phase_times(s)[0])
    assert float(_schedule.at(sched, _bounds(s), 0.1).k_rk) == 0.5
    assert float(_schedule.at(sched, _bounds(s), t_sq).k_rk) == pytest.approx(0.4)
    t = t_sq + 0.01
    d = jax.grad(lambda k: _schedule.at(sched._replace(phases=sched.phases._replace(k_rk=k)), _bounds(s), t).k_rk)(k)
    h = 1e-6
    fd = [
        (
            float(_schedule.at(sched._replace(phases=sched.phases._replace(k_rk=k.at[i].add(h))), _bounds(s), t).k_rk)
            - float(
                _schedule.at(sched._replace(phases=sched.phases._replace(k_rk=k.at[i].add(-h))), _bounds(s), t).k_rk
            )
        )
        / (2 * h)
        for i in range(4)
    ]
    np.testing.assert_allclose(np.asarray(d), fd, atol=1e-9)
    assert np.asarray(d)[0] > 0 and np.asarray(d)[1] > 0 and np.asarray(d)[1] > np.asarray(d)[0]
    # constant gains pass through untouched
    assert _schedule.at(g, _bounds(s), 0.3) is g


def test_schedule_file_round_trip_and_errors(tmp_path):
    g = _gains.default_gains()
    sched = _schedule.constant(g)
    sched = sched._replace(phases=sched.phases._replace(k_rk=jnp.array([0.5, 0.3, 0.2, 0.1])))
    path = tmp_path / "gains.json"
    path.write_text(json.dumps({"gains": _schedule.to_file_dict(sched)}))
    back = gains_file.load(path)
    assert isinstance(back, _schedule.Schedule)
    for a, b in zip(sched.phases, back.phases, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # partial phases over 'all' over the defaults
    part = _schedule.from_dict({"all": {"k_rk": 0.2}, "hold": {"k_rk": -0.3}})
    np.testing.assert_array_equal(np.asarray(part.phases.k_rk), [0.2, 0.2, 0.2, -0.3])
    np.testing.assert_array_equal(np.asarray(part.phases.kp_pos), [1600.0] * 4)
    with pytest.raises(ConfigError, match="phase 'carry'.*k_rk"):
        _schedule.from_dict({"carry": {"k_rk": 1.5}})
    with pytest.raises(ConfigError, match="unknown entries.*'lift'"):
        _schedule.from_dict({"lift": {}})
    with pytest.raises(ConfigError, match="holds only 'schedule'"):
        path.write_text(json.dumps({"schedule": {}, "k_rk": 0.1}))
        gains_file.load(path)


def test_tune_spec_with_a_schedule_has_160_parameters_and_starts_at_the_base():
    g = _gains.default_gains()
    spec = TuneSpec(per_arm=True, schedule=True)
    assert spec.size() == 160 and TuneSpec().size() == 22
    theta = spec.init(g)
    assert sum(np.size(v) for v in theta.values()) == 160
    sched = spec.to_gains(theta, g)
    for a, b in zip(sched.phases, g, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.broadcast_to(np.asarray(b), np.shape(a)), rtol=1e-12)
    theta2 = {**theta, "imp_stiffness": theta["imp_stiffness"].at[3, 1, 2].add(0.5)}
    st = np.asarray(spec.to_gains(theta2, g).phases.imp_stiffness)
    assert st[3, 1, 2] == pytest.approx(50.0 * np.exp(0.5)) and st[2, 1, 2] == pytest.approx(50.0)
    # a schedule as the base needs a schedule spec
    with pytest.raises(ConfigError, match="per phase"):
        TuneSpec().init(sched)
    # the base's phases are kept
    back = spec.to_gains(spec.init(spec.to_gains(theta2, g)), g)
    np.testing.assert_allclose(np.asarray(back.phases.imp_stiffness), st, rtol=1e-12)


def compile_ahead():
    """rollout() of a schedule (tests/conftest.py: compiled ahead in a second process)."""
    sched = _schedule.constant(_gains.default_gains())
    jax.block_until_ready(rollout(paper_model(), sched, fast_scenario(), duration=TEST_DURATION))


@pytest.fixture(scope="module")
def schedule_rollouts(model, rollouts):
    g, s = rollouts["gains"], rollouts["scenario"]
    const = _schedule.constant(g)
    hold_changed = const._replace(phases=const.phases._replace(k_rk=jnp.array([0.5, 0.5, 0.5, 0.0])))
    run = lambda gains: jax.block_until_ready(rollout(model, gains, s, duration=TEST_DURATION))  # noqa: E731
    return {"constant": run(const), "hold_changed": run(hold_changed)}


def test_a_constant_schedule_is_the_constant_gains_bit_for_bit(rollouts, schedule_rollouts):
    ref, got = rollouts["synchronous"], schedule_rollouts["constant"]
    for name, a in ref._asdict().items():
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(a), err_msg=name)


def test_a_schedule_acts_from_its_phase_on(rollouts, schedule_rollouts):
    s = rollouts["scenario"]
    t_hold = float(_scenario.phase_times(s)[2])
    a, b = schedule_rollouts["constant"], schedule_rollouts["hold_changed"]
    t = np.asarray(a.time)
    before = t < t_hold - _schedule.BLEND_S / 2
    after = t > t_hold + 0.1
    np.testing.assert_array_equal(np.asarray(a.qpos)[before], np.asarray(b.qpos)[before])
    assert np.abs(np.asarray(a.torque)[after] - np.asarray(b.torque)[after]).max() > 1e-6


def test_commands_that_take_constant_gains_name_the_schedule(tmp_path, capsys):
    path = tmp_path / "sched.json"
    path.write_text(json.dumps({"gains": {"schedule": {"hold": {"k_rk": 0.1}}}}))
    for cmd in (["sensitivity"], ["sweep", "--param", "k_rl=0.2,0.4"]):
        rc = main([*cmd, "--gains", str(path), "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err
        assert rc == 2 and "holds a gain schedule" in err and "Traceback" not in err, (cmd, err)
        assert not (tmp_path / "o").exists()


def test_compare_records_a_schedule_that_loads_back(tmp_path, rollouts):
    """compare --gains takes a schedule: its summary.json records it in the gains-file form."""
    s = rollouts["scenario"]
    sched = _schedule.from_dict({"all": {"k_rl": 0.4}, "hold": {"k_rk": -0.2}})
    results = {n: (rollouts[n], _metrics.summarize(rollouts[n], s)) for n in ("classical", "synchronous")}
    _compare.write_results(str(tmp_path), results, s, sched, {}, 1.0)
    back = gains_file.load(tmp_path / "summary.json")
    assert isinstance(back, _schedule.Schedule)
    for a, b in zip(sched.phases, back.phases, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_a_per_phase_spec_from_constant_gains_says_what_moved():
    """``jaxsync tune --per-phase`` starts from constant gains by default: the
    start's check compares them with each phase of the schedule it becomes."""
    g = _gains.default_gains()
    spec = TuneSpec(schedule=True)
    assert spec.moved(g) == []
    assert spec.moved(g._replace(k_rk=jnp.asarray(1.0))) == ["k_rk: 1 -> 0.999"]
    assert spec.moved(_schedule.constant(g._replace(k_rk=jnp.asarray(1.0)))) == ["k_rk: 1 -> 0.999"]
