"""A sweep's plan: the parsed parameters, the points and everything that fixes the results.

Its ``fingerprint`` names the sweep in ``plan.json``: a re-run with the same
plan continues with ``--resume``, a different one needs ``--restart``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math

import jax
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import gains as _gains
from jaxsync.control.gains import Gains
from jaxsync.control.names import ALL_CONTROLLERS, check_actuation
from jaxsync.optimize.studies.sweep_spec import (
    PHASE_FIELDS,
    POSITION_FIELDS,
    Param,
    check_overlaps,
    make_points,
    parse_param,
    validate_values,
)
from jaxsync.physics.model import identity, load_model
from jaxsync.sim import scenario as _scenario
from jaxsync.sim.actuation import TORQUE, Stack
from jaxsync.sim.scenario import Scenario, min_duration

PLAN_VERSION = 1


@functools.lru_cache(maxsize=4)  # a loaded model, not a program: clear() keeps it
def loaded_model(solver: str, model: str | None = None, visual: bool = True):
    """The sweep's model (the plan's defaults come from it, the evaluation runs it), loaded once."""
    return load_model(model, solver=solver, visual=visual)


@dataclasses.dataclass
class Plan:
    params: list[Param]
    points: np.ndarray
    samples: int | None
    seed: int
    duration: float
    controller: str
    solver: str
    base_gains: Gains
    base_scenario: Scenario
    x64: bool
    model: str | None = None  # an MJCF or robot file; None: the paper model
    visual: bool = True  # a robot's meshes loaded (False: --no-visual)
    model_identity: dict | None = None  # jaxsync.physics.model.identity of the model loaded
    stack: Stack = TORQUE  # the arms' stack every point runs (its one delay is the base scenario's)

    @property
    def stack_options(self) -> tuple[str, int, str]:
        """(actuation, control_substeps, distro) of the evaluator's rollouts."""
        o = self.stack.rollout_options(loaded_model(self.solver, self.model, self.visual))
        return o["actuation"], o["control_substeps"], o["distro"]

    @property
    def spec(self) -> dict:
        return {
            "version": PLAN_VERSION,
            "params": [p.describe() for p in self.params],
            "mode": "grid" if self.samples is None else "samples",
            "samples": self.samples,
            "seed": self.seed,
            "duration_s": self.duration,
            "controller": self.controller,
            "solver": self.solver,
            "model": self.model,
            "x64": self.x64,
            "base_gains": _gains.to_dict(self.base_gains),
            "base_scenario": _scenario.to_dict(self.base_scenario),
            "model_identity": self.model_identity,
            "stack": self.stack.to_dict(loaded_model(self.solver, self.model, self.visual)),
            "n_points": len(self.points),
            "points_sha256": hashlib.sha256(np.ascontiguousarray(self.points).tobytes()).hexdigest(),
        }

    @property
    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps(self.spec, sort_keys=True).encode()).hexdigest()[:16]


def make_plan(
    param_texts: list[str],
    *,
    samples: int | None = None,
    seed: int = 0,
    duration: float = 4.0,
    controller: str = "synchronous",
    solver: str = "accurate",
    base_gains: Gains | None = None,
    base_scenario: Scenario | None = None,
    model: str | None = None,
    visual: bool = True,
    stack: Stack = TORQUE,
) -> Plan:
    """Parse and check everything that can be checked without compiling.
    ``stack``: the arms' stack (one delay: the base scenario's; on a position
    stack ``delay`` and ``servo_scale`` may be swept).

    Example:
      >>> plan = make_plan(["k_rk=-1:1:5", "object_mass=0.5,1"], duration=4.0)
      >>> plan.points.shape
      (10, 2)
    """

    if not param_texts:
        raise ConfigError("give at least one --param NAME=VALUES")
    if samples is not None and samples < 1:
        raise ConfigError(f"--samples must be a positive number of points, got {samples}")
    if controller not in ALL_CONTROLLERS:
        raise ConfigError(f"--controller must be one of {', '.join(ALL_CONTROLLERS)}, got {controller!r}")
    check_actuation(controller, stack.actuation)  # ros2_admittance: position-controlled arms
    if not (isinstance(duration, (int, float)) and math.isfinite(duration) and duration > 0):
        raise ConfigError(f"--duration must be a positive number of seconds, got {duration}")
    params = [parse_param(t, random=samples is not None) for t in param_texts]
    names = [p.name for p in params]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"parameter(s) {dup} given more than once")
    # the model's own defaults (a robot file's raised gains and its object), and which model it is
    position_only = sorted({p.target.field for p in params if p.target.field in POSITION_FIELDS})
    if position_only and stack.actuation != "position":
        raise ConfigError(
            f"parameter(s) {position_only} apply to position-controlled arms (actuation='position'), got "
            f"actuation={stack.actuation!r}",
            inputs=("param", "actuation"),
        )
    loaded = loaded_model(solver, model, visual)
    stack.substeps(loaded)  # a control rate that divides the physics rate
    base_gains = base_gains if base_gains is not None else _gains.default_gains(loaded, stack.actuation, controller)
    if base_scenario is None:
        base_scenario = _scenario.default_scenario(loaded)._replace(delay=np.float64(stack.scenario_delay()))
    check_overlaps(params, base_gains, base_scenario)
    validate_values(params, base_gains, base_scenario)
    points = make_points(params, samples, seed)
    # the longest phases of any point need the longest rollout
    worst = {f: float(np.asarray(getattr(base_scenario, f))) for f in PHASE_FIELDS}
    for j, p in enumerate(params):
        if p.target.kind == "scenario" and p.target.field in PHASE_FIELDS:
            worst[p.target.field] = float(points[:, j].max())
    need = min_duration(base_scenario._replace(**{k: np.float64(v) for k, v in worst.items()}))
    if duration < need - 1e-9:
        raise ConfigError(
            f"--duration must be at least {need:.2f} s for this sweep (hold start + settling time + 0.2 s "
            f"of settled window for its longest phases), got {duration:g}"
        )
    return Plan(
        params,
        points,
        samples,
        int(seed),
        float(duration),
        controller,
        solver,
        base_gains,
        base_scenario,
        bool(jax.config.jax_enable_x64),
        model,
        visual,
        identity(loaded),
        stack,
    )
