"""How to tune: :class:`TuneConfig`, ``jaxsync tune``'s options as one value."""

from __future__ import annotations

import dataclasses
import math

import optax

from jaxsync._errors import ConfigError
from jaxsync.control.names import CONTROLLERS
from jaxsync.optimize.tuning import methods as _methods
from jaxsync.optimize.tuning.loop import first_order_problem, make_optimizer


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """How to tune (defaults: ``jaxsync tune``'s).

    Example:
      >>> cfg = TuneConfig(iterations=10, batch=2, task="short").validate()
    """

    iterations: int = 60
    batch: int = 4
    learning_rate: float = 0.05
    optimizer: str = "adam"
    schedule: str = "cosine"  # or "constant"
    clip_norm: float = 1.0
    seed: int = 0
    heldout_seed: int = 1000
    heldout_batch: int = 16
    train_duration: float = 2.0  # of the "short" task; the "full" task runs eval_duration
    eval_duration: float = 4.0
    truncate_every: int | None = None  # exact full-horizon gradient; a window length truncates it
    checkpoint_every: int = 5
    max_bad_steps: int = 3
    train_start: str = "approach"  # keyframe the training rollouts start from
    train_scenario: tuple = ()  # (field, value) overrides of the training scenarios' base
    scenario: tuple = ()  # (field, value) overrides of every scenario's base: a robot file's object
    grip_spread: float = 0.0  # the desired grip force randomised +- this share in every sampled scenario
    task: str = "full"  # "full": the default task, as held out; "short": jaxsync.short_task() (2 s)
    validate_every: int = 5  # iterations between validation evaluations (0: none, keep the last iterate)
    validation_seed: int = 500
    validation_batch: int = 16
    method: str = "lbfgs"  # optimize.methods.METHODS (docs/tuning.md: measured best); "adam" is the optax loop
    popsize: int = 16  # CMA-ES population (methods "cmaes" and "cmaes-lbfgs")
    sampling: str = "stratified"  # training batches: the ranges' ends (optimize.scenarios) or "iid"
    controller: str = "synchronous"  # jaxsync.control.controller.CONTROLLERS
    # compliance bounds (docs/metrics.md; None: unbounded): the mean first-impact peak pad force
    # over a batch, N, and the apparent stiffness along the pad normal, N/m
    max_impact_N: float | None = None
    max_stiffness_N_per_m: float | None = None

    def validate(self) -> TuneConfig:
        if self.learning_rate <= 0 or not math.isfinite(self.learning_rate):
            raise ConfigError(f"learning rate must be positive, got {self.learning_rate}")
        if not self.clip_norm > 0 or not math.isfinite(self.clip_norm):
            raise ConfigError(
                f"clip (the gradient's global-norm bound) must be a positive number, got {self.clip_norm}: "
                "0 would zero every update and a negative bound reverse the gradient"
            )
        for name in ("iterations", "batch", "heldout_batch", "checkpoint_every", "max_bad_steps", "validation_batch"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name.replace('_', ' ')} must be a positive integer, got {getattr(self, name)}")
        if self.validate_every < 0:
            raise ConfigError(f"validate every must be 0 (off) or a positive integer, got {self.validate_every}")
        if len({self.seed, self.heldout_seed, self.validation_seed}) < 3:
            raise ConfigError(
                f"the training, validation and held-out seeds must differ (got {self.seed}, "
                f"{self.validation_seed}, {self.heldout_seed}): held-out scenarios are never trained on or selected on"
            )
        why = first_order_problem(self.optimizer)
        if why is not None:
            raise ConfigError(
                "optimizer must name an optax optimiser that steps from (updates, state, params) alone, a "
                f"first-order one (adam, adamw, sgd, lion, rmsprop, ...), got {self.optimizer!r}: {str(why)[:200]}"
            )
        if self.truncate_every is not None and (
            int(self.truncate_every) != self.truncate_every or self.truncate_every < 1
        ):
            raise ConfigError(
                "truncate every must be a positive number of steps (or none: the exact gradient), "
                f"got {self.truncate_every}"
            )
        if self.task not in ("short", "full"):
            raise ConfigError(f"training task must be 'short' or 'full', got {self.task!r}")
        if self.method not in _methods.METHODS:
            raise ConfigError(f"method must be one of {list(_methods.METHODS)}, got {self.method!r}")
        if self.popsize < 2:
            raise ConfigError(f"popsize must be at least 2, got {self.popsize}")
        if self.sampling not in ("stratified", "iid"):
            raise ConfigError(f"sampling must be 'stratified' or 'iid', got {self.sampling!r}")
        if not 0.0 <= self.grip_spread < 1.0:
            raise ConfigError(f"grip spread must be a share in [0, 1), got {self.grip_spread}")
        if self.controller not in CONTROLLERS:
            raise ConfigError(f"controller must be one of {list(CONTROLLERS)}, got {self.controller!r}")
        for name in ("max_impact_N", "max_stiffness_N_per_m"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise ConfigError(f"{name.replace('_', ' ')} must be a positive number (or none: unbounded), got {v}")
        if self.schedule not in ("cosine", "constant"):
            raise ConfigError(f"schedule must be 'cosine' or 'constant', got {self.schedule!r}")
        return self

    def optimizer_transform(self) -> optax.GradientTransformation:
        """This configuration's optax optimiser (cosine or constant rate, clipped)."""
        return make_optimizer(
            self.learning_rate,
            optimizer=self.optimizer,
            schedule=self.schedule,
            iterations=self.iterations,
            clip_norm=self.clip_norm,
        )
