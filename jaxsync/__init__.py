"""jaxsync: differentiable dual-arm contact-force synchronous control with MJX.

The public face; everything else lives in private modules.
"""

import contextlib
import io

# MJX prints "Failed to import warp" to stdout when the optional warp backend is
# absent (harmless: jaxsync uses impl="jax"). Keep it out of users' output.
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx as _mjx  # noqa: F401
del contextlib, io

from jaxsync._errors import (
    ConfigError,
    JaxsyncError,
    ModelError,
    ModelFileError,
    ModelStructureError,
)
from jaxsync._gains import Gains, classical_equivalent, default_gains
from jaxsync._metrics import Metrics, summarize
from jaxsync._model import (
    SOLVERS,
    DualArmModel,
    ModelIndex,
    default_model_path,
    load_model,
)
from jaxsync._physics import after_control, before_control, put_data
from jaxsync._rollout import Trajectory, make_rollout, rollout
from jaxsync._scenario import Scenario, default_scenario
from jaxsync._sensing import ArmState, ObjectState, Sensed, sense

__version__ = "0.1.0"

__all__ = [
    "SOLVERS",
    "ArmState",
    "Gains",
    "Metrics",
    "Scenario",
    "Trajectory",
    "classical_equivalent",
    "default_gains",
    "default_scenario",
    "make_rollout",
    "rollout",
    "summarize",
    "ConfigError",
    "DualArmModel",
    "JaxsyncError",
    "ModelError",
    "ModelFileError",
    "ModelIndex",
    "ModelStructureError",
    "ObjectState",
    "Sensed",
    "after_control",
    "before_control",
    "default_model_path",
    "load_model",
    "put_data",
    "sense",
]
