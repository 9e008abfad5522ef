"""Reading a gains file, whatever wrote it.

:func:`jaxsync.control.gains.to_dict` and ``jaxsync tune`` write JSON (plain
gains, ``{"gains": ...}`` or ``{"schedule": ...}``); ``jaxsync export`` writes
``gains.yaml``, ``gains.json`` and ros2-admittance folders. :func:`load` reads
all of them, so every command's ``--gains`` takes any of them.
"""

from __future__ import annotations

import json
import os

import jax
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import gains as _gains
from jaxsync.control import schedule as _schedule
from jaxsync.control.gains import Gains
from jaxsync.io import export as _export
from jaxsync.physics import model as _model


def load(path: str | os.PathLike):
    """Read a gains file: :class:`~jaxsync.control.gains.Gains`, or a
    :class:`~jaxsync.control.schedule.Schedule` when the file holds
    ``{"schedule": ...}``; also what ``jaxsync export`` writes (``gains.yaml``,
    ``gains.json``, a ros2-admittance folder)."""
    if os.path.isdir(path) or str(path).endswith((".yaml", ".yml")):
        return _export.load(str(path))
    try:
        with open(path) as f:
            data = json.load(f)
    except FileNotFoundError:
        raise ConfigError(f"gains file {path}: no such file") from None
    except (OSError, json.JSONDecodeError) as err:
        raise ConfigError(f"gains file {path}: cannot read JSON: {err}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"gains file {path}: expected a JSON object of gains")
    if _export.HEADER in data:  # written by jaxsync export --format json
        return _export.from_document(data, str(path))
    data = data.get("gains", data)
    try:
        if isinstance(data, dict) and "schedule" in data:  # per-phase gains
            if set(data) != {"schedule"}:
                raise ConfigError(f"a schedule file holds only 'schedule', got also {sorted(set(data) - {'schedule'})}")
            return _schedule.from_dict(data["schedule"])
        return _gains.from_dict(data)
    except ConfigError as err:
        raise ConfigError(f"gains file {path}: {err}") from None


def _recorded(path: str | os.PathLike, key: str):
    """What a JSON gains file records beside the gains under ``key`` (None when it does not say)."""
    if os.path.isdir(path) or not str(path).endswith(".json"):
        return None
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, json.JSONDecodeError):
        return None
    return data.get(key) if isinstance(data, dict) else None


def controller_of(path: str | os.PathLike) -> str | None:
    """The controller a gains file was tuned for (``jaxsync tune`` records it
    beside the gains; a ros2-admittance export names the one it configures),
    None when the file does not say."""
    if os.path.isdir(path):
        return _export.controller_of(str(path))
    return _recorded(path, "controller")


def deployed_period_of(path: str | os.PathLike) -> float | None:
    """The control period, s, a gains file was tuned at through ros2_controllers'
    rule (``jaxsync tune`` records it with the tuned set,
    ``optimize.tuning.params.TuneSpec.describe``), None when the file does not say."""
    tune = _recorded(path, "tune")
    rule = tune.get("deployed_rule") if isinstance(tune, dict) else None
    period = rule.get("control_period_s") if isinstance(rule, dict) else None
    return float(period) if isinstance(period, int | float) else None


def model_of(path: str | os.PathLike) -> dict | None:
    """The model a gains file was tuned on (``jaxsync tune`` records it beside the
    gains: ``jaxsync.physics.model.identity``), None when the file does not say."""
    recorded = _recorded(path, "model")
    return recorded if isinstance(recorded, dict) else None


def check_model(path: str | os.PathLike, model, any_model: bool = False) -> None:
    """Refuse gains tuned on another model than ``model`` (by its fingerprint: an
    edited robot file is another robot), naming both; ``any_model`` lets them through."""
    recorded = model_of(path)
    if any_model or _model.same_model(recorded, model):
        return
    here = _model.describe_identity(_model.identity(model))
    raise ConfigError(
        f"gains file {path} was tuned on {_model.describe_identity(recorded)}, not on {here}: "
        f"load that model ({recorded.get('file')}: --robot for a robot file, --model for an MJCF), or pass "
        "--any-model to use the gains anyway"
    )


def load_for(path: str | os.PathLike, model, any_model: bool = False):
    """:func:`load`, refusing gains tuned on another model (:func:`check_model`)."""
    check_model(path, model, any_model)
    return load(path)


def load_or_default(gains, model, any_model: bool = False, actuation: str = "torque", controller=None):
    """The gains a job runs: ``model``'s defaults for None (``actuation``'s
    stack's, ``controller``'s: ``jaxsync.control.gains.default_gains``), a
    gains file (:func:`load_for`: refused when tuned on another model), or
    gains or a schedule as given."""
    if gains is None:
        return _gains.default_gains(model, actuation, controller)
    if isinstance(gains, str | os.PathLike):
        return load_for(gains, model, any_model)
    return gains


def load_constant(path: str | os.PathLike, command: str) -> Gains:
    """:func:`load`, for a command that takes constant gains only (a schedule is a ConfigError naming it)."""
    g = load(path)
    if not isinstance(g, Gains):
        raise ConfigError(
            f"gains file {path} holds a gain schedule; {command} takes constant gains "
            "(compare and tune --per-phase take schedules)"
        )
    return g


def same_gains(a, b, rtol: float = 1e-12) -> bool:
    """Whether ``a`` and ``b`` (gains or schedules of one shape) hold the same
    values to ``rtol`` (what an export read back is checked against)."""
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    if len(la) != len(lb):
        return False
    for x, y in zip(la, lb, strict=True):
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        if x.shape != y.shape or not bool((abs(x - y) <= rtol * abs(y) + 1e-300).all()):
            return False
    return True
