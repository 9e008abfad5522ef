"""Ctrl-C stops a long run at its next safe point, with its checkpoint,
wherever the signal lands: also inside a garbage-collection callback, which
swallows the KeyboardInterrupt that Python's own handler raises there.

The tuning loop's gradient and the held-out rollouts are stand-ins: what is
tested is the loop's control flow, not its numbers.
"""

from __future__ import annotations

import json
import signal
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ctrl_c_in_a_gc_callback, fake_heldout_metrics

from jaxsync.cli import main
from jaxsync.optimize.tuning import checkpoint
from jaxsync.optimize.tuning import loss as loss_mod
from jaxsync.optimize.tuning import tune as tune_mod
from jaxsync.optimize.tuning.tune_state import CHECKPOINT
from jaxsync.runtime import interrupt


def test_a_ctrl_c_swallowed_by_a_callback_still_stops_at_the_next_check():
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with pytest.raises(KeyboardInterrupt), interrupt.deferred():
        ctrl_c_in_a_gc_callback()
        assert interrupt.requested()
        interrupt.check()
        pytest.fail("check() did not stop")
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    assert not interrupt.requested()


def test_a_second_ctrl_c_stops_at_once_and_a_late_one_when_the_block_ends():
    with pytest.raises(KeyboardInterrupt), interrupt.deferred():
        signal.raise_signal(signal.SIGINT)  # recorded
        signal.raise_signal(signal.SIGINT)  # raised here
        pytest.fail("the second Ctrl-C did not stop at once")
    with pytest.raises(KeyboardInterrupt), interrupt.deferred(), interrupt.deferred():
        signal.raise_signal(signal.SIGINT)  # after the last check: the outermost block's end stops
    with interrupt.deferred():  # nothing asked: nothing raised
        interrupt.check()


@pytest.fixture
def stand_in_gradient(monkeypatch):
    """Adam on 0.5 |theta|^2 in place of the rollouts' gradient; the held-out
    scoring as test_run_safety's stand-ins. ``at["ctrl_c"]``: the iteration
    during which a Ctrl-C lands in a garbage-collection callback."""
    at = {"ctrl_c": None, "calls": 0}

    def traced_value_and_grad(loss, model, base, cfg, args, log):
        def value_and_grad(theta, scen):
            if at["calls"] == at["ctrl_c"]:
                ctrl_c_in_a_gc_callback()
            at["calls"] += 1
            value = sum(0.5 * jnp.sum(v**2) for v in jax.tree_util.tree_leaves(theta))
            return (value, {"grip": value}), theta

        return value_and_grad

    monkeypatch.setattr(tune_mod, "make_loss", lambda *a, **k: None)
    monkeypatch.setattr(tune_mod, "traced_value_and_grad", traced_value_and_grad)
    monkeypatch.setattr(loss_mod, "make_evaluator", lambda *a, **k: lambda g, s: fake_heldout_metrics())
    return at


TUNE = ["tune", "--method", "adam", "--iterations", "4", "--checkpoint-every", "100", "--validate-every", "0"]
TUNE += ["--task", "short", "--batch", "1", "--heldout-batch", "2", "--no-mujoco-check"]


def test_tune_stops_after_the_iteration_a_lost_ctrl_c_landed_in(tmp_path, stand_in_gradient, capsys):
    stand_in_gradient["ctrl_c"] = 1
    out = tmp_path / "run"
    assert main([*TUNE, "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert "jaxsync tune: interrupted" in err
    assert checkpoint.load(str(out / CHECKPOINT))["iteration"] == 2  # the iteration it landed in, finished
    assert stand_in_gradient["calls"] == 2 and not (out / "summary.json").exists()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    stand_in_gradient["ctrl_c"] = None
    assert main([*TUNE, "--out", str(out), "--resume"]) == 0  # and the run goes on from there
    assert stand_in_gradient["calls"] == 4
    assert np.isfinite(json.loads((out / "summary.json").read_text())["final_cost"])


def test_a_run_in_another_thread_leaves_the_handler_alone():
    seen = []

    def work():
        with interrupt.deferred():
            seen.append(signal.getsignal(signal.SIGINT))

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert seen == [signal.default_int_handler]
    with interrupt.deferred():  # the main thread's block is still the outermost
        assert signal.getsignal(signal.SIGINT) is not signal.default_int_handler
