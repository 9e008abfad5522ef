"""The scenarios tuning trains, validates and scores on.

Training batches are randomised around the training task (the full default
task, or the short one) and seeded by the iteration, so a resumed run sees the
same batches. Validation scenarios (their own seed) pick the iterate; held-out
scenarios (a third seed) only score it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxsync.sim import scenario as _scenario


def training_base(training) -> tuple[_scenario.Scenario, float]:
    """The training scenario family's base and its rollout duration (``training``: a TuneConfig's ``training``)."""
    over = {**dict(training.scenario), **dict(training.train_scenario)}
    if training.task == "full":
        return _scenario.default_scenario(**over), training.eval_duration
    return _scenario.short_task(**over), training.train_duration


def sample_scenarios(
    key: jax.Array,
    n: int,
    base: _scenario.Scenario,
    *,
    stratified: bool = False,
    grip_spread: float = 0.0,
    delay: tuple[int, int] = (0, 0),
    servo_spread: float = 0.0,
    ft_filter: tuple[float, float] = (1.0, 1.0),
) -> _scenario.Scenario:
    """A batch of randomised scenarios around ``base``: object mass +-30 % (the
    controller keeps the nominal estimate), offset along the clamping axis
    +-5 mm, contact time constant 15-30 ms, friction 0.8-1.2, wrist force
    noise 0.5-1.5 times the base's (0.05-0.15 N at the default 0.1 N), fresh
    noise keys; with ``grip_spread`` g > 0 also the desired grip force, +-g
    relative; with ``delay`` (lo, hi), hi > lo, the command delay, whole
    control periods from lo to hi; with ``servo_spread`` s > 0 the servo
    gains' scale, 1 +- s (position-controlled arms); with ``ft_filter``
    (lo, hi) other than (1, 1) the admittance rule's F/T filter coefficient,
    log-uniform in [lo, hi]. Each of the last four from its own key: the
    other draws stay as they are without them.

    Each quantity is drawn independently and uniformly over its range. With
    ``stratified`` the batch is a Latin hypercube on the ranges' ends instead:
    each quantity takes ``n`` evenly spaced levels from the bottom of its
    range to the top (both ends included), each level once, the levels paired
    at random across quantities. A batch of 2 then holds the softest and the
    stiffest contact, the lightest and the heaviest object, and so on: a small
    fixed training batch holds the range's extremes, where the controller is
    closest to its limits (the softest contact is the first to chatter when a
    gain moves toward instability), rather than whatever the draw gave.

    Example:
      >>> batch = sample_scenarios(jax.random.key(0), 4, jaxsync.short_task())
      >>> batch.object_mass.shape
      (4,)
    """
    ks = jax.random.split(key, 7)
    strata = jax.random.split(jax.random.fold_in(key, 1), 5)

    def u(i, lo, hi):
        if stratified:
            r = jax.random.permutation(strata[i], n) / max(n - 1, 1) if n > 1 else jnp.full((1,), 0.5)
        else:
            r = jax.random.uniform(ks[i], (n,), dtype=jnp.float64)
        return lo + (hi - lo) * r

    rep = lambda x: jnp.broadcast_to(x, (n, *jnp.shape(x)))  # noqa: E731
    batch = jax.tree_util.tree_map(rep, base)
    offset = jnp.zeros((n, 3)).at[:, 1].set(u(1, -0.005, 0.005))
    noise_keys = jax.vmap(lambda k: jax.random.key_data(k))(jax.random.split(ks[6], n)).astype(jnp.uint32)

    def own(i):  # a draw in [0, 1] from its own key
        k = jax.random.fold_in(key, i)
        if stratified:
            return jax.random.permutation(k, n) / max(n - 1, 1) if n > 1 else jnp.full((1,), 0.5)
        return jax.random.uniform(k, (n,), dtype=jnp.float64)

    if grip_spread:
        batch = batch._replace(grip_force=base.grip_force * (1.0 - grip_spread + 2.0 * grip_spread * own(2)))
    lo, hi = delay
    if hi > lo:  # whole periods, each of lo..hi equally likely (stratified: spread evenly over them)
        periods = jnp.minimum(jnp.floor(lo + (hi - lo + 1) * own(3)), hi)
        batch = batch._replace(delay=periods.astype(batch.delay.dtype))
    elif lo:
        batch = batch._replace(delay=jnp.full((n,), float(lo), batch.delay.dtype))
    if servo_spread:
        batch = batch._replace(
            servo_scale=(1.0 - servo_spread + 2.0 * servo_spread * own(4)).astype(batch.servo_scale.dtype)
        )
    lo, hi = ft_filter
    if (lo, hi) != (1.0, 1.0):  # log-uniform: a coefficient of 0.05 is as far from 0.1 as 0.5 from 1
        coefficient = jnp.exp(jnp.log(lo) + (jnp.log(hi) - jnp.log(lo)) * own(5))
        batch = batch._replace(ft_filter=coefficient.astype(batch.ft_filter.dtype))
    return batch._replace(
        object_mass=base.object_mass * u(0, 0.7, 1.3),
        object_offset=offset,
        contact_timeconst=u(2, 0.015, 0.03),
        friction=u(3, 0.8, 1.2),
        force_noise=u(4, 0.05, 0.15) * (base.force_noise / _scenario.FORCE_NOISE_N),  # scaled with the base's
        noise_key=noise_keys,
    )


def training_batch(cfg, iteration: int, base: _scenario.Scenario) -> _scenario.Scenario:
    """The training batch of one iteration (``cfg``: a TuneConfig; seeded by its
    ``data.seed`` and the iteration; holding the ranges' ends unless its
    ``data.sampling`` is "iid")."""
    d = cfg.data
    key = jax.random.fold_in(jax.random.key(d.seed), iteration)
    stratified = d.sampling == "stratified"
    return sample_scenarios(key, cfg.training.batch, base, stratified=stratified, **_draws(d))


def _draws(data) -> dict:
    """What every sampled scenario of ``data`` (a TuneConfig's) draws beyond the task's ranges."""
    return {
        "grip_spread": data.grip_spread,
        "delay": tuple(data.delay),
        "servo_spread": data.servo_spread,
        "ft_filter": tuple(data.ft_filter),
    }


def heldout_scenarios(cfg) -> _scenario.Scenario:
    """Full-task scenarios from the held-out seed (never used for training or selection)."""
    base, d = _scenario.default_scenario(**dict(cfg.training.scenario)), cfg.data
    return sample_scenarios(jax.random.key(d.heldout_seed), d.heldout_batch, base, **_draws(d))


def validation_scenarios(cfg) -> _scenario.Scenario:
    """Full-task scenarios from the validation seed: they pick the iterate, the
    held-out ones only score it."""
    base, d = _scenario.default_scenario(**dict(cfg.training.scenario)), cfg.data
    return sample_scenarios(jax.random.key(d.validation_seed), d.validation_batch, base, **_draws(d))


def model_overrides(model) -> tuple:
    """A tuning configuration's ``training.scenario`` for ``model``: its object
    (``jaxsync.sim.scenario.model_object``), which the controller also assumes;
    none for the paper model."""
    obj = _scenario.model_object(model)
    if not obj:
        return ()
    m, r = obj["object_mass"], obj["object_radius"]
    noise = tuple((k, obj[k]) for k in ("force_noise", "torque_noise") if k in obj)  # a robot file's sensor:
    return (("object_mass", m), ("mass_estimate", m), ("object_radius", r), *noise)
