"""How to tune: :class:`TuneConfig`, a tuning job as one value.

A job has five parts, each a frozen dataclass:

- :class:`Problem`: what is tuned (the controller, its parameters, the cost
  and the compliance bounds);
- :class:`Training`: the training rollouts (task, durations, start, scenario
  base, batch size, gradient truncation, how the arms are driven);
- :class:`Data`: the seeds and draws of the training, validation and
  held-out scenarios (with the command delay and servo gains they draw);
- :class:`Method`: the optimiser;
- :class:`Loop`: iterations, checkpoints and validation.

The training loss's compiled program depends on exactly ``problem`` and
``training`` (:meth:`TuneConfig.program`): ``make_loss`` reads nothing else,
so a traced program is keyed by those two values and nothing is listed by
hand. The robot is the ``model`` the job functions take beside the
configuration.
"""

from __future__ import annotations

import dataclasses
import json
import math

import optax

from jaxsync._errors import ConfigError
from jaxsync.control.names import ALL_CONTROLLERS, check_actuation
from jaxsync.optimize.tuning import methods as _methods
from jaxsync.optimize.tuning.cost import CostWeights
from jaxsync.optimize.tuning.loop import make_optimizer
from jaxsync.optimize.tuning.params import DEFAULT_TUNED_FOR, TuneSpec
from jaxsync.sim import actuation as _actuation


@dataclasses.dataclass(frozen=True)
class Problem:
    """What is tuned: the controller, its parameters, the cost, the compliance bounds."""

    controller: str = "synchronous"  # jaxsync.control.controller.CONTROLLERS
    spec: TuneSpec | None = None  # the tuned parameters; None: the controller's own (params.DEFAULT_TUNED_FOR)
    weights: CostWeights = CostWeights()
    # compliance bounds (docs/metrics.md; None: unbounded): the mean first-impact peak pad force
    # over a batch, N, and the apparent stiffness along the pad normal, N/m
    max_impact_N: float | None = None
    max_stiffness_N_per_m: float | None = None

    @property
    def tuned(self) -> TuneSpec:
        """The tuned parameters: ``spec``, or the controller's own."""
        return (
            self.spec
            if self.spec is not None
            else TuneSpec(tuned=DEFAULT_TUNED_FOR[self.controller], model_default=True)
        )

    def validate(self) -> None:
        if self.controller not in ALL_CONTROLLERS:
            raise ConfigError(
                f"controller must be one of {list(ALL_CONTROLLERS)}, got {self.controller!r}", inputs=("controller",)
            )
        for name in ("max_impact_N", "max_stiffness_N_per_m"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise ConfigError(f"{name} must be a positive number (or None: unbounded), got {v}", inputs=(name,))
        for name, v in self.weights._asdict().items():
            if not (math.isfinite(v) and v >= 0) or (name in ("peak_temperature", "grip_smooth") and v <= 0):
                raise ConfigError(
                    f"cost weight {name} must be a finite number >= 0 (peak_temperature, grip_smooth > 0), got {v}",
                    inputs=("weights",),
                )


@dataclasses.dataclass(frozen=True)
class Training:
    """The training rollouts: every field shapes the gradient's program."""

    task: str = "full"  # "full": the default task, as held out; "short": jaxsync.short_task() (2 s)
    train_duration: float = 2.0  # of the "short" task; the "full" task runs eval_duration
    eval_duration: float = 4.0  # the full task's (validation and held-out scenarios run it too)
    train_start: str = "approach"  # keyframe the training rollouts start from
    scenario: tuple = ()  # (field, value) overrides of every scenario's base: a robot file's object
    train_scenario: tuple = ()  # (field, value) overrides of the training scenarios' base
    batch: int = 4  # training scenarios per iteration (per process in a multi-process run)
    truncate_every: int | None = None  # exact full-horizon gradient; a window length truncates it
    actuation: str = "torque"  # or "position": joint commands through the servo (jaxsync.sim.actuation)
    control_rate: float | None = None  # Hz; None: the controller runs every physics step
    distro: str = "jazzy"  # controller "ros2_admittance": the ros2_controllers release its rule is

    def validate(self) -> None:
        _actuation.check(self.actuation)
        _actuation.check_distro(self.distro)
        r = self.control_rate
        if r is not None and not (r > 0 and math.isfinite(r)):
            raise ConfigError(
                f"control_rate must be a positive number of Hz (or None), got {r}", inputs=("control_rate",)
            )
        if self.task not in ("short", "full"):
            raise ConfigError(f"task must be 'short' or 'full', got {self.task!r}", inputs=("task",))
        if self.batch < 1:
            raise ConfigError(f"batch must be a positive integer, got {self.batch}", inputs=("batch",))
        for name in ("train_duration", "eval_duration"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ConfigError(f"{name} must be a positive number of seconds, got {v}", inputs=(name,))
        t = self.truncate_every
        if t is not None and (int(t) != t or t < 1):
            raise ConfigError(
                f"truncate_every must be a positive number of steps (or None: the exact gradient), got {t}",
                inputs=("truncate_every",),
            )


@dataclasses.dataclass(frozen=True)
class Data:
    """The scenarios' seeds and draws: training (one batch per iteration), validation, held out."""

    seed: int = 0
    sampling: str = "stratified"  # training batches: the ranges' ends (optimize.scenarios) or "iid"
    grip_spread: float = 0.0  # the desired grip force randomised +- this share in every sampled scenario
    validation_seed: int = 500
    validation_batch: int = 16
    heldout_seed: int = 1000
    heldout_batch: int = 16
    delay: tuple[int, int] = (0, 0)  # command delay, control periods: every scenario draws one in [lo, hi]
    servo_spread: float = 0.0  # every scenario's servo gains scaled by 1 +- this share (position arms)
    ft_filter: tuple[float, float] = (1.0, 1.0)  # the rule's F/T filter coefficient, drawn log-uniform in [lo, hi]

    def validate(self) -> None:
        d = self.delay
        if not (isinstance(d, tuple | list) and len(d) == 2):
            raise ConfigError(f"delay must be a range (lo, hi) of control periods, got {d!r}", inputs=("delay",))
        _actuation.check_delay(tuple(d))
        f = self.ft_filter
        if not (isinstance(f, tuple | list) and len(f) == 2 and 1e-3 <= f[0] <= f[1] <= 1.0):
            raise ConfigError(
                f"ft_filter must be a range (lo, hi) of filter coefficients, 0.001 <= lo <= hi <= 1, got {f!r}",
                inputs=("ft_filter",),
            )
        if not 0.0 <= self.servo_spread < 1.0:
            raise ConfigError(
                f"servo_spread must be a share in [0, 1), got {self.servo_spread}", inputs=("servo_spread",)
            )
        for name in ("validation_batch", "heldout_batch"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be a positive integer, got {getattr(self, name)}", inputs=(name,))
        if len({self.seed, self.heldout_seed, self.validation_seed}) < 3:
            raise ConfigError(
                f"the training, validation and held-out seeds must differ (got {self.seed}, "
                f"{self.validation_seed}, {self.heldout_seed}): held-out scenarios are never trained on or selected on",
                inputs=("seed", "validation_seed", "heldout_seed"),
            )
        if self.sampling not in ("stratified", "iid"):
            raise ConfigError(f"sampling must be 'stratified' or 'iid', got {self.sampling!r}", inputs=("sampling",))
        if not 0.0 <= self.grip_spread < 1.0:
            raise ConfigError(f"grip_spread must be a share in [0, 1), got {self.grip_spread}", inputs=("grip_spread",))


@dataclasses.dataclass(frozen=True)
class Method:
    """The optimiser: ``name`` is one of ``optimize.methods.METHODS`` ("lbfgs",
    measured best: docs/tuning.md; "cmaes", "cmaes-lbfgs") or a first-order
    optax optimiser by name ("adam", "sgd", "adamw", ...: a fresh training
    batch every iteration, steered by ``learning_rate``, ``schedule`` and
    ``clip_norm``)."""

    name: str = "lbfgs"
    learning_rate: float = 0.05
    schedule: str = "cosine"  # or "constant"
    clip_norm: float = 1.0
    popsize: int = 16  # CMA-ES population ("cmaes" and "cmaes-lbfgs")

    @property
    def first_order(self) -> bool:
        """Whether this is an optax optimiser stepping on a fresh batch every iteration."""
        return self.name not in _methods.BATCH_METHODS

    def validate(self) -> None:
        if self.first_order:
            why = _methods.first_order_problem(self.name)
            if why is not None:
                raise ConfigError(
                    f"method must be one of {list(_methods.BATCH_METHODS)} or a first-order optax optimiser that "
                    f"steps from (updates, state, params) alone (adam, adamw, sgd, lion, rmsprop, ...), got "
                    f"{self.name!r}: {str(why)[:200]}",
                    inputs=("name",),
                )
        if self.learning_rate <= 0 or not math.isfinite(self.learning_rate):
            raise ConfigError(f"learning_rate must be positive, got {self.learning_rate}", inputs=("learning_rate",))
        if not self.clip_norm > 0 or not math.isfinite(self.clip_norm):
            raise ConfigError(
                f"clip_norm (the gradient's global-norm bound) must be a positive number, got {self.clip_norm}: "
                "0 would zero every update and a negative bound reverse the gradient",
                inputs=("clip_norm",),
            )
        if self.schedule not in ("cosine", "constant"):
            raise ConfigError(f"schedule must be 'cosine' or 'constant', got {self.schedule!r}", inputs=("schedule",))
        if self.popsize < 2:
            raise ConfigError(f"popsize must be at least 2, got {self.popsize}", inputs=("popsize",))


@dataclasses.dataclass(frozen=True)
class Loop:
    """The loop: its length, checkpoints and validation."""

    iterations: int = 300  # the cap: a run stops earlier when it has converged
    checkpoint_every: int = 5
    validate_every: int = 5  # iterations between validation evaluations (0: none, keep the last iterate)
    max_bad_steps: int = 3  # non-finite steps in a row that stop the run
    # also converged: the validation figure moved by less than plateau_tol (relative) over the
    # last plateau_validations validations (0, the default: off; docs/convergence.md says why)
    plateau_tol: float = 0.0
    plateau_validations: int = 4
    # an iterate may be selected when its grip error is no worse than the start's or at most this
    # (relative; 0, the default: the start's); for runs continued from tuned gains
    grip_floor: float = 0.0

    def validate(self) -> None:
        for name in ("iterations", "checkpoint_every", "max_bad_steps", "plateau_validations"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be a positive integer, got {getattr(self, name)}", inputs=(name,))
        if not 0 <= self.plateau_tol < 1:
            raise ConfigError(
                f"plateau_tol must be a relative change in [0, 1) (0: run to the cap), got {self.plateau_tol}",
                inputs=("plateau_tol",),
            )
        if not 0 <= self.grip_floor < 1:
            raise ConfigError(
                f"grip_floor must be a relative grip error in [0, 1) (0: no worse than the start's), "
                f"got {self.grip_floor}",
                inputs=("grip_floor",),
            )
        if self.validate_every < 0:
            raise ConfigError(
                f"validate_every must be 0 (off) or a positive integer, got {self.validate_every}",
                inputs=("validate_every",),
            )


PARTS = {"problem": Problem, "training": Training, "data": Data, "method": Method, "loop": Loop}
# a part's field by its own name, and Method's name also as "method"
_FIELD_PART = {f.name: part for part, cls in PARTS.items() for f in dataclasses.fields(cls)}
_FIELD_PART.pop("name")


@dataclasses.dataclass(frozen=True, init=False)
class TuneConfig:
    """A tuning job (defaults: ``jaxsync tune``'s), its five parts.

    Built from parts, from any part's fields by name (``method`` names the
    method), or both; :meth:`replace` the same way.

    Example:
      >>> cfg = TuneConfig(iterations=10, batch=2, task="short").validate()
      >>> cfg.loop.iterations, cfg.training.batch, cfg.method.name
      (10, 2, 'lbfgs')
      >>> cfg = TuneConfig(problem=Problem(controller="classical"), method=Method("adam", learning_rate=0.02))
    """

    problem: Problem
    training: Training
    data: Data
    method: Method
    loop: Loop

    def __init__(self, problem=None, training=None, data=None, method=None, loop=None, **fields):
        given = {"problem": problem, "training": training, "data": data, "method": method, "loop": loop}
        if isinstance(method, str):  # the method by name
            given["method"], fields["name"] = None, method
        updates: dict[str, dict] = {part: {} for part in PARTS}
        for name, value in fields.items():
            part = "method" if name == "name" else _FIELD_PART.get(name)
            if part is None:
                raise ConfigError(f"TuneConfig has no setting {name!r}; settings: {sorted(_FIELD_PART)}")
            updates[part][name] = value
        for part, cls in PARTS.items():
            value = given[part] if given[part] is not None else cls()
            if not isinstance(value, cls):
                raise ConfigError(f"TuneConfig's {part} must be a {cls.__name__}, got {type(value).__name__}")
            object.__setattr__(self, part, dataclasses.replace(value, **updates[part]))

    def replace(self, **fields) -> TuneConfig:
        """This configuration with some parts or fields changed (as the constructor takes them)."""
        parts = {part: getattr(self, part) for part in PARTS}
        if isinstance(fields.get("method"), str):  # the method by name
            fields["name"] = fields.pop("method")
        for part in PARTS:
            if part in fields:
                parts[part] = fields.pop(part)
        return TuneConfig(**parts, **fields)

    def validate(self) -> TuneConfig:
        for part in PARTS:
            getattr(self, part).validate()
        self.stack()  # a delay or a servo spread needs position-controlled arms
        check_actuation(self.problem.controller, self.training.actuation)  # ros2_admittance: position arms
        if self.data.servo_spread and self.training.actuation != "position":
            raise ConfigError(
                f"servo_spread applies to position-controlled arms (actuation='position'), got "
                f"{self.data.servo_spread} with actuation={self.training.actuation!r}",
                inputs=("servo_spread", "actuation"),
            )
        return self

    def stack(self) -> _actuation.Stack:
        """The arms' stack the job runs: the training's actuation and control
        rate, the data's delay range."""
        t = self.training
        return _actuation.Stack(t.actuation, t.control_rate, tuple(self.data.delay), t.distro)

    def program(self) -> tuple[Problem, Training]:
        """What the training loss's compiled program depends on (and is keyed by)."""
        return self.problem, self.training

    def to_dict(self) -> dict:
        """Every part's fields, by part (JSON-ready: the cost weights as a dict, the spec as its description)."""
        out = {}
        for part in PARTS:
            d = {f.name: getattr(getattr(self, part), f.name) for f in dataclasses.fields(PARTS[part])}
            out[part] = d
        out["problem"]["weights"] = self.problem.weights._asdict()
        out["problem"]["spec"] = self.problem.tuned.describe()
        for k in ("scenario", "train_scenario"):
            out["training"][k] = [list(x) for x in out["training"][k]]
        for k in ("delay", "ft_filter"):
            out["data"][k] = list(out["data"][k])
        return out

    def settings(self) -> dict:
        """Every part's fields in one JSON-ready dict, by name (Method's ``name`` as "method")."""
        flat = {}
        for part, fields in self.to_dict().items():
            flat.update({("method" if (part, k) == ("method", "name") else k): v for k, v in fields.items()})
        return json.loads(json.dumps(flat))

    def optimizer_transform(self) -> optax.GradientTransformation:
        """The first-order method's optax optimiser (cosine or constant rate, clipped)."""
        m = self.method
        return make_optimizer(
            m.learning_rate,
            optimizer=m.name,
            schedule=m.schedule,
            iterations=self.loop.iterations,
            clip_norm=m.clip_norm,
        )
