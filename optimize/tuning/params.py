"""What tuning may change, constrained by construction.

The optimiser sees an unconstrained pytree ``theta`` (only the tuned
parameters); :meth:`TuneSpec.to_gains` maps it to valid gains:

- k_rk, k_lk, k_rl, k_ll = tanh(theta): |k| < 1, the paper's range;
- M_d = exp(theta), K_d = exp(theta): positive;
- ff_vel, ff_acc = FF_MAX tanh(theta) (position-controlled arms: the joint
  command's feed-forward of the plan, within its validation bounds; 0 at theta 0);
- B_d = 2 zeta sqrt(M_d K_d) with the damping ratio
  zeta = ZETA_MIN + (ZETA_MAX - ZETA_MIN) sigmoid(theta): inside the band, so
  every tuned admittance filter is a stable, passive mass-spring-damper;
- where the gains deploy as ros2_controllers' admittance rule (``deploy_dt``,
  its control period: the rule's controllers on position-controlled arms),
  each M_d is then raised to max(M_d, DEPLOY_MARGIN (2 dt B_d + dt^2 K_d) / 4)
  with B_d and K_d kept, the rule defaults' own step
  (``jaxsync.control.gains.deployable_gains``): every iterate is one the
  export runs, stable with D/M and K/M 1.5 times larger, and the raised mass
  still depends on every tuned parameter through B_d and K_d; M_d and K_d are
  held within the controller's own bounds (``MASS_BOUNDS``,
  ``STIFFNESS_BOUNDS`` in ``jaxsync.control.ros2_admittance``).

- the coupling family's gains (ros2_coupled: cpl_rel, cpl_own, cpl_other,
  cpl_force) = GAIN_MAX tanh(theta), 0 at theta 0; its filters (cpl_*_a) =
  A_MIN + (1 - A_MIN) sigmoid(theta), starting at most at A_START_MAX;
  their full 6x6 blocks off the diagonal (cpl_block, by name) = GAIN_MAX
  tanh(theta) off the diagonal: (4, 6, 6) shared by the arms, (4, 2, 6, 6)
  per arm, never isotropic.

Impedance parameters are shared by both arms or per arm (``per_arm``), and
per axis (6 values: the pad frame's x, y, z and rotations about them) or
isotropic (``isotropic``: one value for translations, one for rotations).
The baselines' object-level impedance (obj_mass, obj_stiffness and
obj_damping_ratio, the damping as above) and internal-force loop gains
(force_p, force_i = exp(theta)) are (6,) vectors (``isotropic``: two).
Every controller's impedance goes through the same map and the same bands
(``jaxsync.control.gains.USED`` says which gains each controller reads).
With ``schedule`` every tuned parameter has one value per task phase (close,
squeeze, carry, hold; ``jaxsync.control.schedule``) and the gains are a
:class:`~jaxsync.control.schedule.Schedule`: per arm and per axis that is
4 x (4 + 3 x 2 x 6) = 160 parameters.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import coupling as _coupling
from jaxsync.control import ros2_admittance as _ra
from jaxsync.control import schedule as _schedule
from jaxsync.control.gains import FF_ACC_MAX, FF_VEL_MAX, USED, Gains, servo_limits_loop
from jaxsync.control.names import CONTROLLERS, FAMILY

ZETA_MIN, ZETA_MAX = 0.5, 150.0  # the default normal axis is an integrating force loop, zeta ~ 100
SYNC = ("k_rk", "k_lk", "k_rl", "k_ll")
IMPEDANCE = ("imp_mass", "imp_stiffness", "imp_damping_ratio")
OBJECT = ("obj_mass", "obj_stiffness", "obj_damping_ratio")
FORCE = ("force_p", "force_i")
VECTORS = OBJECT + FORCE  # (6,) gains: one value per axis, not per arm
# the joint-command loop every controller ends in: kp_pos (log space, kd_pos kept), so that on
# position-controlled arms its bandwidth lambda = 2 kp_pos / kd_pos is tuned (on torque arms: its stiffness)
LOOP = ("kp_pos",)
# the joint command's feed-forward of the plan (position-controlled arms, jaxsync's laws): a bounded scalar each
FEED = ("ff_vel", "ff_acc")
FF_MAX = {"ff_vel": FF_VEL_MAX, "ff_acc": FF_ACC_MAX}
# what a slow servo adds to a law's default set: its inertial lag's feed-forward. Not ff_vel: a lead
# shifts the whole carry in time, and tuned on a batch of 4 it ran to its bound (0.05 s, where 6 ms
# does better held out: docs/deploy-tuning.md); set it, or tune it by name
SERVO_ADDED = LOOP + ("ff_acc",)
# the coupling family (ros2_coupled, jaxsync.control.coupling): per arm and axis like the impedance; each
# channel's gain c = GAIN_MAX tanh(theta), each filter a = A_MIN + (1 - A_MIN) sigmoid(theta)
FAMILY_GAINS = _coupling.GAIN_FIELDS
FAMILY_FILTERS = _coupling.FILTER_FIELDS
FAMILY_BLOCK = _coupling.BLOCK_FIELD
A_MIN, A_START_MAX = 1e-3, 0.95  # a filter starts at most at 0.95, where its gradient is not yet 0
TUNABLE = SYNC + IMPEDANCE + OBJECT + FORCE + LOOP + FEED + FAMILY_GAINS + FAMILY_FILTERS + (FAMILY_BLOCK,)
DEFAULT_TUNED = ("k_rk", "k_lk", "k_rl", "k_ll", "imp_mass", "imp_stiffness", "imp_damping_ratio")
# what `jaxsync tune --controller NAME` tunes unless told
DEFAULT_TUNED_FOR = {
    "classical": IMPEDANCE,
    "synchronous": DEFAULT_TUNED,
    "object_impedance": IMPEDANCE + OBJECT,
    "task_space": FORCE,
    "ros2_admittance": IMPEDANCE,  # ros2_controllers' rule: the admittance file's mass, damping, stiffness
    "ros2_synchronous": DEFAULT_TUNED,  # the rule's, and the coupling's factors
    "ros2_coupled": IMPEDANCE + FAMILY_GAINS,  # the rule's, and the family's channel gains (filters: by name)
    "ros2_coupled_direct": IMPEDANCE + FAMILY_GAINS,
}
# ros2_controllers' rule: tuned on position-controlled arms, its impedance is kept within the exported
# rule's stability margin (TuneSpec.deploy_dt)
DEPLOYED = ("ros2_admittance", "ros2_synchronous", *FAMILY)
# the gain each tuned name sets
GAIN_OF = {"imp_damping_ratio": "imp_damping", "obj_damping_ratio": "obj_damping"}


def check_tuned(tuned, controller: str) -> None:
    """ConfigError when a tuned parameter is one ``controller`` never reads
    (its gradient would be zero and the search would wander in it)."""
    own = LOOP + (FEED if controller in CONTROLLERS else ())  # the rule has no feed-forward
    unused = [n for n in tuned if GAIN_OF.get(n, n) not in USED[controller] and n not in own]
    if unused:
        usable = [n for n in TUNABLE if GAIN_OF.get(n, n) in USED[controller] or n in own]
        raise ConfigError(f"the {controller} controller does not use {', '.join(unused)}; it tunes {', '.join(usable)}")


def damping_ratio(g: Gains) -> jax.Array:
    return g.imp_damping / (2.0 * jnp.sqrt(g.imp_mass * g.imp_stiffness))


def object_damping_ratio(g: Gains) -> jax.Array:
    return g.obj_damping / (2.0 * jnp.sqrt(g.obj_mass * g.obj_stiffness))


def _logit(p):
    p = np.clip(p, 1e-9, 1 - 1e-9)
    return np.log(p / (1 - p))


@dataclasses.dataclass(frozen=True)
class TuneSpec:
    """Which parameters are tuned (the rest are frozen at ``base``'s values).

    Example:
      >>> spec = TuneSpec(tuned=("k_rk", "k_lk"))
      >>> theta = spec.init(jaxsync.default_gains())
      >>> gains = spec.to_gains({k: v + 0.1 for k, v in theta.items()}, jaxsync.default_gains())
    """

    tuned: tuple[str, ...] = DEFAULT_TUNED
    per_arm: bool = False
    isotropic: bool = False
    schedule: bool = False  # one value per task phase (jaxsync.control.schedule.PHASES)
    # ``tuned`` is the controller's default set, not named by the user: :meth:`for_model` adds the
    # joint-command loop's gain where the robot's servo limits that loop
    model_default: bool = False
    frozen: tuple[str, ...] = ()  # what :meth:`for_model` leaves out of the model's additions
    # the control period, s, at which the gains deploy as ros2_controllers' admittance rule: each
    # impedance mass raised to the rule's stability margin there (module docstring); None: not held
    deploy_dt: float | None = None

    def __post_init__(self):
        unknown = sorted(set(self.tuned) - set(TUNABLE))
        if unknown:
            raise ConfigError(f"unknown parameter(s) to tune {unknown}; tunable: {list(TUNABLE)}", inputs=("spec",))
        if not self.tuned:
            raise ConfigError("nothing to tune: name at least one of " + ", ".join(TUNABLE), inputs=("spec", "frozen"))
        if self.deploy_dt is not None and not (float(self.deploy_dt) > 0 and np.isfinite(self.deploy_dt)):
            raise ConfigError(
                f"deploy_dt must be a positive control period in s, got {self.deploy_dt}", inputs=("spec",)
            )
        if FAMILY_BLOCK in self.tuned and self.isotropic:
            raise ConfigError(
                f"{FAMILY_BLOCK} couples the pad frame's axes with each other: it has no isotropic form; tune it "
                "without --isotropic",
                inputs=("spec",),
            )

    def for_model(self, controller: str, model, actuation: str, control_rate: float | None = None) -> TuneSpec:
        """This spec on ``model``'s ``actuation`` stack: ros2_controllers'
        rule (``DEPLOYED``) on position-controlled arms is held within the
        exported rule's stability margin at its control period
        (``deploy_dt``: 1 / ``control_rate``, or the model's step where the
        controller runs every step), unless a period is already set. A controller's
        default set (``model_default``) gains kp_pos where jaxsync's own law
        runs on position-controlled arms whose slowest servo lowered its
        joint-command loop (``jaxsync.control.gains.servo_limits_loop``: the
        iiwa-like pair). Its default there is a third of that servo's
        frequency, safe at every delay but slow; the tuner trades it against
        the delay and the servo spread it trains on (docs/deploy-tuning.md:
        on the iiwa-like pair 1.34x without it, 3.7x with it). Not for
        ros2_controllers' rule: its reference loop stands in for the user's
        trajectory and is not exported. There the joint command's
        feed-forward of the plan's acceleration (ff_acc) is tuned too: the
        slow servo's inertial lag is what it cancels
        (docs/deploy-tuning.md). Anything else: this spec.

        ConfigError where ff_vel or ff_acc is tuned on torque-driven arms (no
        joint command to feed forward)."""
        fed = [n for n in self.tuned if n in FEED]
        if fed and actuation != "position":
            raise ConfigError(
                f"{', '.join(fed)}: the joint command's feed-forward acts on position-controlled arms only "
                "(--actuation position)",
                inputs=("spec",),
            )
        if actuation == "position" and controller in DEPLOYED and self.deploy_dt is None:
            dt = 1.0 / float(control_rate) if control_rate else float(model.mj_model.opt.timestep)
            return dataclasses.replace(self, deploy_dt=dt)
        if (
            not self.model_default
            or actuation != "position"
            or controller not in CONTROLLERS
            or not servo_limits_loop(model)
        ):
            return self
        added = tuple(n for n in SERVO_ADDED if n not in self.frozen and n not in self.tuned)
        return dataclasses.replace(self, tuned=self.tuned + added, model_default=False) if added else self

    # --- the shape of one impedance parameter in theta
    def _reduce(self, v: np.ndarray) -> np.ndarray:
        """(2, 6) -> the tuned shape (mean over what is shared)."""
        v = np.asarray(v, dtype=float)
        if not self.per_arm:
            v = v.mean(axis=0, keepdims=True)
        if self.isotropic:
            v = np.stack([v[:, :3].mean(-1), v[:, 3:].mean(-1)], axis=-1)
        return v

    def _expand(self, v: jax.Array) -> jax.Array:
        """The tuned shape -> (2, 6)."""
        if self.isotropic:
            v = jnp.concatenate([jnp.repeat(v[:, :1], 3, axis=1), jnp.repeat(v[:, 1:], 3, axis=1)], axis=1)
        return jnp.broadcast_to(v, (2, 6))

    def _reduce_vector(self, v: np.ndarray) -> np.ndarray:
        """(6,) -> the tuned shape."""
        v = np.asarray(v, dtype=float)
        return np.array([v[:3].mean(), v[3:].mean()]) if self.isotropic else v

    def _expand_vector(self, v: jax.Array) -> jax.Array:
        """The tuned shape -> (6,)."""
        return jnp.concatenate([jnp.repeat(v[:1], 3), jnp.repeat(v[1:], 3)]) if self.isotropic else v

    def init(self, base) -> dict:
        """theta such that ``to_gains(theta, base)`` reproduces ``base`` (up to sharing).

        ``base``: constant gains, or (with ``schedule``) a schedule."""
        if isinstance(base, _schedule.Schedule):
            if not self.schedule:
                raise ConfigError(
                    "the base gains are a schedule: tune them per phase (TuneSpec(schedule=True))",
                    inputs=("per_phase",),
                )
            per = [self._init_constant(_schedule.phase(base, i)) for i in range(len(_schedule.PHASES))]
            return jax.tree_util.tree_map(lambda *v: jnp.stack(v), *per)
        theta = self._init_constant(base)
        if self.schedule:
            n = len(_schedule.PHASES)
            theta = jax.tree_util.tree_map(lambda v: jnp.broadcast_to(v, (n,) + v.shape), theta)
        return theta

    def _init_constant(self, base: Gains) -> dict:
        logs = [n for n in ("imp_mass", "imp_stiffness", "imp_damping_ratio") if n in self.tuned]
        for name in ("imp_mass", "imp_stiffness"):
            if logs and not np.all(np.asarray(getattr(base, name)) > 0):
                raise ConfigError(
                    f"the starting gains' {name} holds {np.asarray(getattr(base, name)).tolist()}: tuning "
                    f"{', '.join(logs)} needs every {name} > 0 (the impedance is tuned in log space and through its "
                    f"damping ratio); start from a positive {name}, or freeze {','.join(logs)}",
                    inputs=("frozen",),
                )
        if "kp_pos" in self.tuned and not float(np.asarray(base.kp_pos)) > 0:
            raise ConfigError(
                f"the starting gains' kp_pos is {float(np.asarray(base.kp_pos))}: tuning it needs kp_pos > 0 (it "
                "is tuned in log space)",
                inputs=("frozen",),
            )
        for name in ("obj_mass", "obj_stiffness", "force_p", "force_i"):
            if (name in self.tuned or (name.startswith("obj") and "obj_damping_ratio" in self.tuned)) and not np.all(
                np.asarray(getattr(base, name)) > 0
            ):
                raise ConfigError(
                    f"the starting gains' {name} holds {np.asarray(getattr(base, name)).tolist()}: tuning it needs "
                    f"every value > 0 (it is tuned in log space); start from a positive {name}, or freeze it",
                    inputs=("frozen",),
                )
        theta = {}
        for name in self.tuned:
            if name in ("obj_mass", "obj_stiffness", "force_p", "force_i"):
                theta[name] = jnp.asarray(np.log(self._reduce_vector(getattr(base, name))))
            elif name == "obj_damping_ratio":
                zeta = np.asarray(object_damping_ratio(base))
                theta[name] = jnp.asarray(_logit((self._reduce_vector(zeta) - ZETA_MIN) / (ZETA_MAX - ZETA_MIN)))
            elif name in SYNC:
                theta[name] = jnp.asarray(np.arctanh(np.clip(float(getattr(base, name)), -0.999, 0.999)))
            elif name in LOOP:
                theta[name] = jnp.asarray(np.log(float(np.asarray(getattr(base, name)))))
            elif name in FEED:
                ratio = float(np.asarray(getattr(base, name))) / FF_MAX[name]
                theta[name] = jnp.asarray(np.arctanh(np.clip(ratio, -0.999, 0.999)))
            elif name in FAMILY_GAINS:
                ratio = self._reduce(getattr(base, name)) / _coupling.GAIN_MAX
                theta[name] = jnp.asarray(np.arctanh(np.clip(ratio, -0.999, 0.999)))
            elif name == FAMILY_BLOCK:
                x = np.asarray(getattr(base, name), dtype=float)
                x = x if self.per_arm else x.mean(axis=1)
                theta[name] = jnp.asarray(np.arctanh(np.clip(x / _coupling.GAIN_MAX, -0.999, 0.999)))
            elif name in FAMILY_FILTERS:
                a = np.clip(self._reduce(getattr(base, name)), 2 * A_MIN, A_START_MAX)
                theta[name] = jnp.asarray(_logit((a - A_MIN) / (1.0 - A_MIN)))
            elif name == "imp_mass":
                theta[name] = jnp.asarray(np.log(self._reduce(base.imp_mass)))
            elif name == "imp_stiffness":
                theta[name] = jnp.asarray(np.log(self._reduce(base.imp_stiffness)))
            else:
                zeta = np.asarray(damping_ratio(base))
                theta[name] = jnp.asarray(_logit((self._reduce(zeta) - ZETA_MIN) / (ZETA_MAX - ZETA_MIN)))
        return theta

    def to_gains(self, theta: dict, base):
        """Valid gains from theta (differentiable): :class:`Gains`, or a
        :class:`~jaxsync.control.schedule.Schedule` when ``schedule`` is set."""
        if not self.schedule:
            if isinstance(base, _schedule.Schedule):
                raise ConfigError(
                    "the base gains are a schedule: tune them per phase (TuneSpec(schedule=True))",
                    inputs=("per_phase",),
                )
            return self._to_constant(theta, base)
        if not isinstance(base, _schedule.Schedule):
            base = _schedule.constant(base)
        return _schedule.Schedule(jax.vmap(self._to_constant)(theta, base.phases))

    def _to_constant(self, theta: dict, base: Gains) -> Gains:
        g = base._asdict()
        for name in SYNC:
            if name in theta:
                g[name] = jnp.tanh(theta[name])
        for name in LOOP:
            if name in theta:
                g[name] = jnp.exp(theta[name])
        for name in FEED:
            if name in theta:
                g[name] = FF_MAX[name] * jnp.tanh(theta[name])
        zeta = damping_ratio(base)
        if "imp_mass" in theta:
            g["imp_mass"] = self._expand(jnp.exp(theta["imp_mass"]))
        if "imp_stiffness" in theta:
            g["imp_stiffness"] = self._expand(jnp.exp(theta["imp_stiffness"]))
            if self.deploy_dt is not None:  # within the deployed controller's bounds
                g["imp_stiffness"] = jnp.minimum(g["imp_stiffness"], _ra.STIFFNESS_BOUNDS[1])
        if "imp_damping_ratio" in theta:
            zeta = self._expand(ZETA_MIN + (ZETA_MAX - ZETA_MIN) * jax.nn.sigmoid(theta["imp_damping_ratio"]))
        if any(n in theta for n in IMPEDANCE):
            g["imp_damping"] = 2.0 * zeta * jnp.sqrt(g["imp_mass"] * g["imp_stiffness"])
            if self.deploy_dt is not None:  # B_d and K_d kept, M_d raised to the deployed rule's margin
                need = _ra.mass_needed(g["imp_damping"], g["imp_stiffness"], self.deploy_dt)
                g["imp_mass"] = jnp.clip(jnp.maximum(g["imp_mass"], need), *_ra.MASS_BOUNDS)
        for name in FAMILY_GAINS:
            if name in theta:
                g[name] = self._expand(_coupling.GAIN_MAX * jnp.tanh(theta[name]))
        if FAMILY_BLOCK in theta:
            x = _coupling.GAIN_MAX * jnp.tanh(theta[FAMILY_BLOCK]) * _coupling.OFF_DIAGONAL
            g[FAMILY_BLOCK] = x if self.per_arm else jnp.broadcast_to(x[:, None], (len(_coupling.CHANNELS), 2, 6, 6))
        for name in FAMILY_FILTERS:
            if name in theta:
                g[name] = self._expand(A_MIN + (1.0 - A_MIN) * jax.nn.sigmoid(theta[name]))
        for name in ("obj_mass", "obj_stiffness", "force_p", "force_i"):
            if name in theta:
                g[name] = self._expand_vector(jnp.exp(theta[name]))
        if any(n in theta for n in OBJECT):
            zeta = object_damping_ratio(base)
            if "obj_damping_ratio" in theta:
                zeta = self._expand_vector(
                    ZETA_MIN + (ZETA_MAX - ZETA_MIN) * jax.nn.sigmoid(theta["obj_damping_ratio"])
                )
            g["obj_damping"] = 2.0 * zeta * jnp.sqrt(g["obj_mass"] * g["obj_stiffness"])
        return Gains(**g)

    def moved(self, base, rtol: float = 1e-6) -> list[str]:
        """Where the tuned parameterisation does not hold ``base`` as given: each
        gain that ``to_gains(init(base), base)`` changes (clipped into its band,
        e.g. k = 1 to 0.999, or shared across arms or axes), as "name: given ->
        used" with the largest change."""
        used = self.to_gains(self.init(base), base)
        if isinstance(used, _schedule.Schedule):  # constant gains tuned per phase start as 4 equal phases
            given = base if isinstance(base, _schedule.Schedule) else _schedule.constant(base)
            a, b = given.phases, used.phases
        else:
            a, b = base, used
        out = []
        for name in Gains._fields:
            given, now = np.asarray(getattr(a, name), dtype=float), np.asarray(getattr(b, name), dtype=float)
            diff = np.abs(now - given)
            if np.any(diff > rtol * np.maximum(np.abs(given), 1e-12)):
                i = np.unravel_index(int(np.argmax(diff)), diff.shape) if diff.shape else ()
                out.append(f"{name}: {float(given[i]):.6g} -> {float(now[i]):.6g}")
        return out

    def size(self) -> int:
        """How many scalars are tuned."""
        arms = 2 if self.per_arm else 1
        axes = 2 if self.isotropic else 6
        block = len(_coupling.CHANNELS) * arms * 30  # off the diagonal
        n = sum(
            1
            if name in SYNC + LOOP + FEED
            else axes
            if name in VECTORS
            else block
            if name == FAMILY_BLOCK
            else arms * axes
            for name in self.tuned
        )
        return n * (len(_schedule.PHASES) if self.schedule else 1)

    def describe(self) -> dict:
        return {
            "tuned": list(self.tuned),
            "per_arm": self.per_arm,
            "isotropic": self.isotropic,
            "schedule": list(_schedule.PHASES) if self.schedule else None,
            "parameters": self.size(),
            "damping_ratio_band": [ZETA_MIN, ZETA_MAX],
            **(
                {"deployed_rule": {"control_period_s": self.deploy_dt, "margin": _ra.DEPLOY_MARGIN}}
                if self.deploy_dt is not None
                else {}
            ),
            "k_range": [-1, 1],
            **(
                {"coupling_gain_range": [-_coupling.GAIN_MAX, _coupling.GAIN_MAX], "coupling_filter_range": [A_MIN, 1]}
                if set(FAMILY_GAINS + FAMILY_FILTERS + (FAMILY_BLOCK,)) & set(self.tuned)
                else {}
            ),
            **(
                {"feedforward_range": {n: [-FF_MAX[n], FF_MAX[n]] for n in FEED}} if set(FEED) & set(self.tuned) else {}
            ),
        }


def spec_for(
    controller: str,
    tuned=None,
    frozen=(),
    *,
    per_arm: bool = False,
    isotropic: bool = False,
    schedule: bool = False,
) -> TuneSpec:
    """The TuneSpec of a tuning job: ``tuned`` (names; default: the
    controller's own, ``DEFAULT_TUNED_FOR``, and kp_pos where the robot's
    servo limits the joint-command loop: :meth:`TuneSpec.for_model`) less
    ``frozen``.

    Example:
      >>> spec_for("synchronous", frozen=("imp_mass",)).tuned[:2]
      ('k_rk', 'k_lk')
    """
    if controller not in DEFAULT_TUNED_FOR:
        raise ConfigError(
            f"controller must be one of {list(DEFAULT_TUNED_FOR)}, got {controller!r}", inputs=("controller",)
        )
    unknown = sorted(set(frozen) - set(TUNABLE))
    if unknown:
        raise ConfigError(f"frozen: unknown parameter(s) {unknown}; tunable: {list(TUNABLE)}", inputs=("frozen",))
    names = tuple(tuned) if tuned else DEFAULT_TUNED_FOR[controller]
    return TuneSpec(
        tuned=tuple(n for n in names if n not in frozen),
        per_arm=per_arm,
        isotropic=isotropic,
        schedule=schedule,
        model_default=not tuned,
        frozen=tuple(frozen),
    )
