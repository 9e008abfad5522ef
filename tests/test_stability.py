"""The chatter metric: an unstable force loop named, never selected, never averaged in."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxsync.optimize.studies import compare as _compare
from jaxsync.optimize.studies.sweep_report import summarize_sweep
from jaxsync.optimize.tuning.tune_state import select_iterate
from jaxsync.sim import metrics


def _forces(normal_right, normal_left):
    """(T, 2, 3) pad forces along fixed normals +y (right) and -y (left), and the normals."""
    T = len(normal_right)
    n = jnp.broadcast_to(jnp.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]), (T, 2, 3))
    f = n * jnp.stack([jnp.asarray(normal_right), jnp.asarray(normal_left)], axis=1)[:, :, None]
    return f, n


def test_force_chatter_is_the_rms_step_change_of_the_worse_pad():
    T = 100
    steady = np.full(T, 10.0)
    flip = np.where(np.arange(T) % 2 == 0, 2.7, 20.0)  # 17.3 N every step
    f, n = _forces(steady, flip)
    mask = jnp.ones(T)
    assert float(metrics.force_chatter(f, n, mask)) == pytest.approx(17.3)
    f, n = _forces(steady, steady + 0.1 * np.sin(np.arange(T)))
    assert float(metrics.force_chatter(f, n, mask)) < 0.2
    # only the window counts: the flips outside it do not
    f, n = _forces(steady, np.where(np.arange(T) < 50, flip, 10.0))
    assert float(metrics.force_chatter(f, n, jnp.asarray(np.arange(T) >= 50, float))) == 0.0
    assert metrics.CHATTER_THRESHOLD_N == 1.0


def _entry(i, peak, chattering=0):
    return {"iteration": i, "settled_peak_resultant_N": peak, "grip_force_error_rel": 0.004, "dropped": 0,
            "nonfinite": 0, "chattering": chattering}  # fmt: skip


def test_validation_never_selects_an_iterate_that_chattered_more_than_the_start():
    v = [_entry(0, 0.01), _entry(5, 0.001, chattering=2), _entry(10, 0.004)]
    assert select_iterate(v)["iteration"] == 10
    v = [_entry(0, 0.01, chattering=1), _entry(5, 0.001, chattering=1)]
    assert select_iterate(v)["iteration"] == 5  # no worse than the start
    assert select_iterate([_entry(0, 0.01), _entry(5, 0.001)])["iteration"] == 5


def test_compare_and_sweep_name_chattering_points():
    summary = {"classical": {"chattering": True}, "synchronous": {"chattering": False}}
    assert _compare.chattering(summary) == ["classical"]

    class Plan:
        points = np.zeros((3, 1))
        params = []

    m = {
        "settled_peak_resultant_N": np.array([0.01, 0.002, 0.02]),
        "grip_force_error_rel": np.array([0.01, 0.01, 0.01]),
        "dropped": np.array([0, 0, 0]),
        "nonfinite": np.array([0, 0, 0]),
        "chattering": np.array([0, 1, 0]),
    }
    s = summarize_sweep(Plan(), m)
    assert s["n_ok"] == 2 and s["n_chattering"] == 1
    assert s["best_ok_point"]["settled_peak_resultant_N"]["point"] == 0  # the chattering point's low peak is not "best"


def test_torque_limit_share_counts_the_steps_an_arm_saturates():
    T, n = 10, 6
    torque = np.zeros((T, 2 * n))
    torque[:3, 2] = 150.0  # right arm, joint 3, at its limit for 3 of 10 steps
    torque[5, 2] = -149.9  # 99.93 % of it: at the limit
    torque[6, 2] = 149.0  # 99.3 %: not
    torque[:, n + 5] = 40.0  # left arm's joint 6 beyond its 28 N m on every step
    limits = np.array([[150, 150, 150, 28, 28, 28]] * 2, dtype=float)
    np.testing.assert_allclose(metrics.torque_limit_share(torque, limits), [0.4, 1.0])
