"""The coupled loop's stability margin (``jaxsync.sim.loop_stability``): the
period map is the rollout's, the modes at 1 that no gain moves are the ones
removed, and the spectral radius predicts the nonlinear loop: the rule alone
and a tuned-like coupling are stable, a coupling it calls unstable chatters
in the rollout while one on the stable side of its boundary holds the ball,
and near the boundary the radius grows with the delay.

The comparison task (``default_scenario``, 4 s) on the paper model, on
position-controlled arms. Two MJX programs serve every radius (the hold and
the period's Jacobian), one every rollout (controller ros2_coupled)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaxsync
from jaxsync._errors import ConfigError
from jaxsync.control import coupling as _coupling
from jaxsync.control import gains as _gains
from jaxsync.sim import loop_stability as _ls
from jaxsync.sim import metrics as _metrics
from jaxsync.sim import scenario as _scenario
from jaxsync.sim.scenario import default_scenario

DURATION = 4.0  # the comparison's: the hold from 2.2 s


def _coupled(model, field, value):
    """The rule's position-stack defaults with one coupling gain on the pad normal (z) of both arms."""
    g = jaxsync.default_gains(model, "position", "ros2_admittance")
    return g._replace(**{field: getattr(g, field).at[:, 2].set(value)})


def _rollout(model, g, delay):
    s = default_scenario(model, delay=float(delay))
    traj = jaxsync.rollout(model, g, s, controller="ros2_coupled", duration=DURATION, actuation="position")
    return traj, _metrics.summarize(traj, s)


def compile_ahead():
    """The hold's and the Jacobian's programs (tests/conftest.py: compiled ahead; the rollouts are the slow tier's)."""
    from conftest import paper_model

    m = paper_model()
    _ls.loop_margin(m, _coupled(m, "cpl_other", -0.4), "ros2_coupled", delay=1)


MARGINS = {  # name: (controller, coupling gain on the pad normal, its value, delay, scale)
    "rule": ("ros2_admittance", "cpl_other", 0.0, 1, 1.5),  # the defaults, no coupling
    "tuned": ("ros2_coupled", "cpl_other", -0.4, 1, 1.5),
    "tuned_d3": ("ros2_coupled", "cpl_other", -0.4, 3, 1.5),
    "force": ("ros2_coupled", "cpl_force", -0.3, 1, 1.5),  # scaled: -0.45
    "other_d3": ("ros2_coupled", "cpl_other", 0.6, 3, 4.0 / 3.0),  # scaled: 0.8
    "near": ("ros2_coupled", "cpl_other", -1.8, 1, 1.5),  # late: delay 2
    "near_d3": ("ros2_coupled", "cpl_other", -1.8, 3, 1.5),
}
ROLLOUTS = {  # name: (coupling gain on the pad normal, its value, delay)
    "tuned": ("cpl_other", -0.4, 1),
    "force": ("cpl_force", -0.3, 1),
    "force_scaled": ("cpl_force", -0.45, 1),
    "other_d3": ("cpl_other", 0.6, 3),
    "other_d3_scaled": ("cpl_other", 0.8, 3),
    "near": ("cpl_other", -1.8, 1),
}


def _once(compute):
    done = {}
    return lambda name: done[name] if name in done else done.setdefault(name, compute(name))


@pytest.fixture(scope="module")
def margins(model):
    """loop_margin of each case in ``MARGINS``, computed when a test first asks (scale chosen so that
    radius_scaled is the other side of the boundary)."""

    def margin(name):
        controller, field, value, delay, scale = MARGINS[name]
        return _ls.loop_margin(model, _coupled(model, field, value), controller, delay=delay, scale=scale)

    return _once(margin)


@pytest.fixture(scope="module")
def rollouts(model):
    """The full task with each coupling in ``ROLLOUTS`` from the start, sensor noise on: (trajectory,
    metrics), rolled out when a test first asks."""

    def run(name):
        field, value, delay = ROLLOUTS[name]
        return _rollout(model, _coupled(model, field, value), delay)

    return _once(run)


def _holds(m):
    return not (bool(m.chattering) or bool(m.dropped) or bool(m.nonfinite))


@pytest.mark.slow
def test_the_period_map_is_the_rollouts(model, rollouts):
    """The linearised map runs the position stack as the rollout does: the
    hold program's state after k periods is the rollout's at step k, to
    rounding, over the whole 4 s task (noise and delay included)."""
    traj, _ = rollouts("tuned")
    settle = _ls._programs(model, "reference", "jazzy", 1)[0]
    g = _gains.strongly_typed(_coupled(model, "cpl_other", -0.4))
    s = _scenario.strongly_typed(default_scenario(model, delay=1.0))
    k = traj.time.shape[0] - 1
    d = settle(g, s, k)[0]
    assert float(jnp.abs(d.qpos - traj.qpos[k]).max()) < 1e-9
    assert float(jnp.abs(d.qvel - traj.qvel[k]).max()) < 1e-9
    assert float(jnp.abs(d.qpos - traj.qpos[k - 100]).max()) > 1e-6  # the comparison can fail


def test_the_modes_at_one_are_the_removed_ones(margins):
    """Over the whole state the rule alone has modes at (or just past) 1 that
    no gain moves: the object's orientation, its spin and drift in the pads'
    plane, each rule's null-space offset. Removed, each sits at 1 (the
    quaternion's norm at 0), the split neglects nothing larger than 1e-4, and
    what is left is stable."""
    for name in ("rule", "tuned"):
        r = margins(name)
        assert r.radius_whole >= 1.0, r.radius_whole  # the removed modes exist
        assert r.radius < 1.0, r.radius
        away = np.abs(np.abs(r.removed) - 1.0)
        assert np.all((away < 2e-4) | (np.abs(r.removed) < 1e-9)), r.removed
        assert r.residual < 1e-4, r.residual
        assert len(r.removed) == 4 + 4 + 3  # N, M (two 7-joint arms), H
        assert r.tested_size < r.state_size - len(r.removed)  # less what the period overwrites


@pytest.mark.slow
def test_the_rule_alone_and_a_tuned_like_coupling_are_stable(margins, rollouts):
    """The rule alone and cpl_other = -0.4 on the pad normal, at delay 1 and
    3: stable with margin, and the rollout holds the ball quietly."""
    for name in ("rule", "tuned", "tuned_d3"):
        r = margins(name)
        assert r.verdict == "stable with margin", r.phrase
        assert r.radius < 1.0 and r.radius_scaled < 1.0 and r.radius_rule < 1.0
    assert _holds(rollouts("tuned")[1])
    np.testing.assert_allclose(margins("tuned").radius_rule, margins("rule").radius, rtol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["force", "other_d3"])
def test_the_radius_predicts_which_coupling_chatters(margins, rollouts, case):
    """cpl_force = -0.3 at delay 1 and cpl_other = 0.6 at delay 3: stable by
    the radius, and the rollout holds; -0.45 and 0.8 (radius_scaled): past
    the radius's boundary, and the rollout chatters (its force chatter
    tens of times the stable one's)."""
    r = margins(case)
    assert r.radius < 1.0 < r.radius_scaled, r.phrase
    assert r.verdict == "within margin"
    (_, stable), (_, unstable) = rollouts(case), rollouts(f"{case}_scaled")
    assert _holds(stable), float(stable.force_chatter_N)
    assert bool(unstable.chattering), float(unstable.force_chatter_N)
    assert float(unstable.force_chatter_N) > 10 * float(stable.force_chatter_N)


@pytest.mark.slow
def test_near_the_boundary_the_radius_grows_with_the_delay(margins, rollouts):
    """cpl_other = -1.8 on the pad normal: stable at delay 1, unstable at 2
    and more so at 3. Stable but within the margin (x1.5 is unstable), its
    rollout at delay 1 rings for the whole hold: the margin's reason."""
    d1, d3 = margins("near"), margins("near_d3")
    assert d1.radius < 1.0 < d1.radius_late < d3.radius, (d1.phrase, d3.phrase)
    assert d1.verdict == "within margin" and d3.verdict == "unstable"
    assert bool(rollouts("near")[1].chattering)


def test_the_phrase_names_the_numbers(margins):
    r = margins("force")
    for number in (r.radius, r.radius_scaled, r.radius_rule, r.radius_late):
        assert f"{number:.5f}" in r.phrase
    assert "delay 1" in r.phrase and "x1.5" in r.phrase and r.verdict in r.phrase


def test_scaling_is_the_whole_coupling_offset(model):
    """ros2_synchronous runs as its family form; scaled, every channel's gain
    (the own channel's k_il - 1 included) is times the factor: the offset
    o_i the coupling adds to the rule's, 1.5 times; the rule alone is the
    family zeroed."""
    g = _gains.strongly_typed(jaxsync.default_gains(model, "position", "ros2_synchronous"))
    placement, family = _ls.family_form(g, "ros2_synchronous")
    assert placement == "reference"
    stretched, rule = _ls.scaled(family, 1.5), _ls.scaled(family, 0.0)
    np.testing.assert_allclose(stretched.cpl_own, 1.5 * (float(g.k_rl) - 1.0))
    np.testing.assert_allclose(stretched.cpl_rel[0], 1.5 * float(g.k_rk))
    for f in (*_coupling.GAIN_FIELDS, _coupling.BLOCK_FIELD):
        assert not np.any(np.asarray(getattr(rule, f)))
    assert _ls.family_form(g, "ros2_coupled_direct")[0] == "direct"


def test_it_refuses_what_it_cannot_linearise(model):
    g = jaxsync.default_gains(model, "position", "ros2_admittance")
    with pytest.raises(ConfigError, match="position"):
        _ls.loop_margin(model, g, "synchronous", delay=1)
    with pytest.raises(ConfigError, match="one delay"):
        _ls.loop_margin(model, g, "ros2_coupled", delay=(1, 3))
    with pytest.raises(ConfigError, match="scale"):
        _ls.loop_margin(model, g, "ros2_coupled", delay=1, scale=0.5)
    with pytest.raises(ConfigError, match="Gains"):
        _ls.loop_margin(model, {"phases": [g]}, "ros2_coupled", delay=1)


def test_it_refuses_a_rule_that_does_not_hold_the_object(model):
    """The normal axis's mass at 1.8 kg (dt D/M = 2.22, past the rule's own
    bound, tests/test_ros2_loop.py): the rule alone loses the grip, so there
    is no hold to linearise about, and it says so."""
    g = jaxsync.default_gains(model, "position", "ros2_admittance")
    g = g._replace(imp_mass=g.imp_mass.at[:, :3].set(1.8))
    with pytest.raises(ConfigError, match="does not hold the object"):
        _ls.loop_margin(model, g, "ros2_coupled", delay=1)


def test_an_export_of_the_coupled_loop_is_checked_at_its_delays(model, tmp_path):
    """jaxsync export (ros2-admittance) runs the check at every delay asked: a coupling stable with its
    margin is written with the radii in the notes; one within the margin is refused, naming the numbers,
    with nothing written, and written with a WARNING in synchronisation.yaml when forced."""
    done = jaxsync.export_gains(
        _coupled(model, "cpl_other", -0.4), "ros2-admittance", str(tmp_path / "ok"), model=model,
        controller="ros2_coupled", delay=(1, 1),
    )  # fmt: skip
    assert done.same and any("stable with margin" in n and "delay 1" in n for n in done.notes), done.notes
    risky = _coupled(model, "cpl_force", -0.3)
    with pytest.raises(ConfigError, match=r"ros2_coupled, delay 1\) has spectral radius 0\.99.*within margin"):
        jaxsync.export_gains(
            risky, "ros2-admittance", str(tmp_path / "no"), model=model, controller="ros2_coupled", delay=1
        )
    assert not (tmp_path / "no").exists()
    jaxsync.export_gains(
        risky, "ros2-admittance", str(tmp_path / "forced"), model=model, controller="ros2_coupled", delay=1, force=True
    )
    head = (tmp_path / "forced" / "synchronisation.yaml").read_text().splitlines()[0]
    assert head.startswith("# WARNING: the coupled loop (ros2_coupled, delay 1)") and "within margin" in head
