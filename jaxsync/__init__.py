"""jaxsync: differentiable dual-arm contact-force synchronous control with MJX.

The public face; everything else lives in private modules
(docs/architecture.md maps them). In the order the data flows:

- the model and sensing: :func:`load_model`, :func:`put_data`,
  :func:`before_control` (the state's kinematics and dynamics), :func:`sense`,
  :func:`after_control` (apply torques, step);
- the controller: :func:`init`, :func:`step`, :class:`ControllerOptions`,
  :class:`Reference`, :class:`Gains`;
- the task: :class:`Scenario`, :func:`default_scenario`, :func:`short_task`;
- rollouts on MJX (:func:`rollout`, :func:`make_rollout`) and on MuJoCo C
  (:func:`rollout_mujoco`), recorded as a :class:`Trajectory`;
- metrics: :func:`summarize`, :func:`series`, :class:`Metrics`;
- tuning and sweeps (``jaxsync.optimize``, loaded on first use): a tuning
  job is one :class:`TuneConfig` (what is tuned, its training rollouts, the
  scenarios' seeds, the method, the loop); :func:`tune_and_evaluate` runs it
  and returns a :class:`TuneSummary`; :func:`tune` is its loop;
  :class:`TuneSpec`, :class:`CostWeights`,
  :func:`make_loss`, :func:`sample_scenarios`, :func:`make_plan`,
  :func:`run_sweep`;
- the commands' jobs, from what a user names to the files written:
  :func:`run_comparison` (``jaxsync compare``), :func:`run_sensitivity`
  (``jaxsync sensitivity``), :func:`run_study` (``jaxsync study``) and
  :func:`export_gains` (``jaxsync export``), also loaded on first use;
- set-up, first thing in a script: :func:`set_xla_flags` (XLA's CPU settings,
  before the first JAX computation) and :func:`enable_compilation_cache`
  (JAX's persistent compilation cache).

Example:
  >>> import jax
  >>> import jaxsync
  >>> jaxsync.set_xla_flags()  # before the first JAX computation: half the compile memory
  True
  >>> jax.config.update("jax_enable_x64", True)
  >>> jaxsync.enable_compilation_cache()  # later runs skip most compiling
  >>> model = jaxsync.load_model()
  >>> s = jaxsync.short_task()
  >>> traj = jaxsync.rollout(model, jaxsync.default_gains(), s, duration=1.7)
  >>> float(jaxsync.summarize(traj, s).settled_peak_resultant_N)  # doctest: +SKIP
"""

import contextlib
import importlib as _importlib
import io

from jaxsync.runtime.gl import import_mujoco

# mujoco without OpenGL: a MUJOCO_GL backend that is not installed must not
# break commands that do not render (the first Renderer loads it; jaxsync.runtime.gl)
import_mujoco()

# MJX prints "Failed to import warp" to stdout when the optional warp backend is
# absent (harmless: jaxsync uses impl="jax"). Keep it out of users' output.
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx as _mjx  # noqa: F401
del contextlib, io, import_mujoco

from jaxsync._errors import (
    ConfigError,
    JaxsyncError,
    ModelError,
    ModelFileError,
    ModelStructureError,
)
from jaxsync.control.compliance import apparent_stiffness
from jaxsync.control.controller import CONTROLLERS, ControllerOptions, ControllerState, Reference, init, step
from jaxsync.control.gains import Gains, classical_equivalent, default_gains
from jaxsync.physics.model import DualArmModel, RobotScene, default_model_path, identity, load_model
from jaxsync.physics.robot import Robot, load_robot
from jaxsync.physics.sensing import ArmState, ObjectState, Sensed, sense
from jaxsync.physics.step import after_control, before_control, put_data
from jaxsync.runtime.cache import enable_compilation_cache
from jaxsync.runtime.xla import set_xla_flags
from jaxsync.sim.metrics import Metrics, series, summarize
from jaxsync.sim.rollout import make_rollout, rollout
from jaxsync.sim.rollout_mujoco import rollout_mujoco
from jaxsync.sim.scenario import Scenario, default_scenario, short_task
from jaxsync.sim.trajectory import Trajectory

__version__ = "0.1.0"

# The tuning and sweep API lives in jaxsync.optimize, which imports the
# library: it is loaded on first use, so ``import jaxsync`` stays light and
# free of import cycles. Each public name: (module, attribute).
_OPTIMIZE = {
    "tune": ("jaxsync.optimize.tuning.tune", "tune"),
    "TuneConfig": ("jaxsync.optimize.tuning.config", "TuneConfig"),
    "TuneSummary": ("jaxsync.optimize.tuning.pipeline", "TuneSummary"),
    "tune_and_evaluate": ("jaxsync.optimize.tuning.pipeline", "tune_and_evaluate"),
    "TuneResult": ("jaxsync.optimize.tuning.tune", "TuneResult"),
    "make_loss": ("jaxsync.optimize.tuning.loss", "make_loss"),
    "TuneSpec": ("jaxsync.optimize.tuning.params", "TuneSpec"),
    "CostWeights": ("jaxsync.optimize.tuning.cost", "CostWeights"),
    "sample_scenarios": ("jaxsync.optimize.tuning.scenarios", "sample_scenarios"),
    "make_plan": ("jaxsync.optimize.studies.sweep", "make_plan"),
    "run_sweep": ("jaxsync.optimize.studies.sweep", "run"),
    "StudyConfig": ("jaxsync.optimize.studies.study", "StudyConfig"),
    "run_study": ("jaxsync.optimize.studies.study", "run_study"),
    "run_comparison": ("jaxsync.optimize.studies.compare", "run_comparison"),
    "run_sensitivity": ("jaxsync.optimize.studies.sensitivity", "run_sensitivity"),
    # not in jaxsync.optimize, but on first use too: ``import jaxsync`` does not import yaml
    "export_gains": ("jaxsync.io.export_gains", "export_gains"),
}


def __getattr__(name: str):
    if name in _OPTIMIZE:
        module, attribute = _OPTIMIZE[name]
        return getattr(_importlib.import_module(module), attribute)
    raise AttributeError(f"module 'jaxsync' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_OPTIMIZE))


__all__ = [
    # model and sensing
    "ArmState",
    "DualArmModel",
    "RobotScene",
    "identity",
    "ObjectState",
    "Sensed",
    "after_control",
    "before_control",
    "default_model_path",
    "load_model",
    "load_robot",
    "Robot",
    "put_data",
    "sense",
    # controller
    "CONTROLLERS",
    "ControllerOptions",
    "ControllerState",
    "Gains",
    "Reference",
    "apparent_stiffness",
    "classical_equivalent",
    "default_gains",
    "init",
    "step",
    # task
    "Scenario",
    "default_scenario",
    "short_task",
    # rollouts
    "Trajectory",
    "make_rollout",
    "rollout",
    "rollout_mujoco",
    # metrics
    "Metrics",
    "series",
    "summarize",
    # tuning and sweeps (jaxsync.optimize)
    "CostWeights",
    "TuneConfig",
    "TuneSummary",
    "tune_and_evaluate",
    "TuneResult",
    "TuneSpec",
    "make_loss",
    "make_plan",
    "run_study",
    "StudyConfig",
    # the commands' jobs
    "export_gains",
    "run_comparison",
    "run_sensitivity",
    "run_sweep",
    "sample_scenarios",
    "tune",
    # set-up and errors
    "enable_compilation_cache",
    "set_xla_flags",
    "ConfigError",
    "JaxsyncError",
    "ModelError",
    "ModelFileError",
    "ModelStructureError",
]
