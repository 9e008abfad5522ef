"""Golden files for a port of a controller: N control periods of a rollout on
position-controlled arms, what the controller read and what it wrote, as CSV
that a port's unit test replays row by row (docs/golden.md).

The rollout is MuJoCo C's (``jaxsync.sim.rollout_mujoco``), the controller
jaxsync's own jitted step. Each row k of ``inputs.csv`` holds what the step
read in period k: both arms' joint positions and velocities, pad poses,
twists, Jacobians and pad wrenches (the sensing a port computes from its own
kinematics and F/T sensor), the reference (plan, desired wrench, rest
posture), the last joint command and the controller's state before the step;
the same row of ``outputs.csv`` what it wrote: the integrated joint
commands, the commands sent to the servo (with the plan's feed-forward)
and the state after. ``golden.json`` names the columns, units and frames, the gains
(``jaxsync.io.export.document``'s form), the period and the stack.
:func:`replay` runs jaxsync's step on the recorded inputs and returns how far
its outputs are from the recorded ones, which is what a port's test does.

Example:
  >>> model = jaxsync.load_model()
  >>> paths = export_golden(model, jaxsync.default_gains(model, "position"), "results/golden")  # doctest: +SKIP
  >>> replay("results/golden")  # doctest: +SKIP
  0.0
"""

from __future__ import annotations

import csv
import json
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxsync._errors import ConfigError
from jaxsync.control import controller as _controller
from jaxsync.control import coupling as _coupling
from jaxsync.control.gains import Gains
from jaxsync.control.joint_space import COMMAND_ALPHA
from jaxsync.control.names import ALL_CONTROLLERS, FAMILY
from jaxsync.io import export as _export
from jaxsync.io import gains_file
from jaxsync.io import results as _results
from jaxsync.physics import robot_names
from jaxsync.physics.model import as_model
from jaxsync.physics.sensing import ArmState
from jaxsync.sim import actuation as _actuation
from jaxsync.sim.rollout_mujoco import rollout_mujoco
from jaxsync.sim.scenario import default_scenario

GOLDEN_FORMAT = 3  # 2: jaxsync's own laws carry the F/T filter's state (wrench_filter); 3: the command sent
FILES = ("inputs.csv", "outputs.csv", "golden.json")
MAX_STEPS = 100_000
ARMS = ("right", "left")
# the parts of the controller state each controller reads and writes
STATE_PARTS = {
    "classical": ("impedance", "wrench_filter"),
    "synchronous": ("impedance", "wrench_filter"),
    "object_impedance": ("impedance", "object", "wrench_filter"),
    "task_space": ("force_integral", "wrench_filter"),
    "ros2_admittance": ("ros2",),
    "ros2_synchronous": ("ros2",),
    "ros2_coupled": ("ros2", "coupling"),
    "ros2_coupled_direct": ("ros2", "coupling"),
}
# each state part's columns (``state.<path>[arm][k]``, rows right then left): meaning, frame, unit
STATE_FIELDS = {
    "impedance.offset": "each arm's admittance offset e_i, world frame (the filter runs in the planned pad "
    "frame, docs/deploy.md step 4), [m; rad] (rotation vector)",
    "impedance.rate": "its rate de_i, world frame, [m/s; rad/s]",
    "wrench_filter": "f_i - f_id through the F/T filter, world frame, [N; N m]",
    "object.offset": "object_impedance's compliant object frame dx_o, object frame, [m; rad]",
    "object.rate": "its rate, object frame, [m/s; rad/s]",
    "force_integral": "task_space's integral of the internal wrench, world frame, [N s; N m s]",
    "ros2.q_ref": "each arm's reference joints, rad: advanced one period by the CLIK toward the plan "
    "(ros2_synchronous: toward the coupled target, from the rules' last offsets; ros2_coupled: toward the plan "
    "plus the coupling offset o_i) before the rule runs on them (docs/ros2-rule.md, docs/coupling.md)",
    "ros2.rule.joint_pos": "the rule's offset in joint space (the C++ AdmittanceState), rad",
    "ros2.rule.joint_vel": "its rate, rad/s",
    "ros2.rule.joint_acc": "its acceleration, rad/s^2",
    "ros2.rule.admittance_velocity": "J joint_vel at the pad (the F/T frame), base frame (the world), [m/s; rad/s]",
    "ros2.rule.admittance_acceleration": "J joint_acc at the pad, base frame (the world), [m/s^2; rad/s^2]",
    "ros2.rule.wrench_world": "the rule's filtered wrench (measurement plus set-point), world frame, [N; N m]",
    "coupling.value": "ros2_coupled's filtered channel inputs [channel][arm][axis], channels rel, own, other, force "
    "(docs/coupling.md), each arm's planned pad frame, [m; rad] (force: over the arm's admittance, docs/coupling.md)",
    "coupling.rate": "their rates (own, other; rel and force 0), [m/s; rad/s]",
}
# what a controller's step writes besides its state: column prefix, meaning, frame, unit
OUTPUT_FIELDS = {
    "command": "the integrated joint position commands, rad, right arm's joints then left's",
    "sent": "what the servo gets: command plus the plan's feed-forward (0 for the rule), rad",
}
# the coupling family's offset, a function of its state after the step (``jaxsync.control.coupling.offset``)
FAMILY_OUTPUT_FIELDS = {
    "coupling_offset": "the coupling offset o_i [arm][axis] from state.coupling, world frame, [m; rad] "
    "(docs/coupling.md, 'One period, in order'; ros2_coupled: the target of q_ref is the plan plus o_i, "
    "ros2_coupled_direct: J# o_i is added to q_ref for the rule)",
    "coupling_offset_rate": "its rate, world frame, [m/s; rad/s]",
}
_family_offset = jax.jit(_coupling.offset)  # one program for the recording and the replay: the same digits
# what a controller's step reads of each arm: (field, meaning)
ARM_FIELDS = (
    ("q", "joint positions, rad"),
    ("qd", "joint velocities, rad/s"),
    ("pad_pos", "pad origin, world frame, m"),
    ("pad_rot", "pad rotation (columns: pad axes in the world; z the outward normal), row-major"),
    ("pad_vel", "pad twist J qd, world frame, [m/s; rad/s]"),
    ("jac", "pad Jacobian, world frame, reference point the pad origin, rows [v; w], row-major"),
    ("wrench", "compensated pad wrench (object on arm, about the pad origin), world frame, [N; N m]"),
)
REF_FIELDS = (
    ("pad_pos", "planned pad origin, world, m"),
    ("pad_rot", "planned pad rotation, row-major"),
    ("pad_vel", "planned pad twist, world, [m/s; rad/s]"),
    ("pad_acc", "planned pad acceleration, world"),
    ("wrench", "desired pad wrench f_id, world, [N; N m]"),
    ("q_rest", "rest posture of the null-space term, rad"),
)


def _flat(prefix: str, x) -> dict:
    """Columns ``prefix[i][j]`` of an array, row-major (a scalar: ``prefix``)."""
    a = np.asarray(x, dtype=float)
    return {prefix + _index(i): float(a[i]) for i in np.ndindex(a.shape)}


def _index(i: tuple) -> str:
    return "".join(f"[{j}]" for j in i)


def _output_fields(controller: str) -> dict:
    return {**OUTPUT_FIELDS, **(FAMILY_OUTPUT_FIELDS if controller in FAMILY else {})}


def _family_columns(gains, state, ref) -> dict:
    """The coupling family's offset and its rate as output columns."""
    o, o_dot = _family_offset(gains, state.coupling, jnp.asarray(ref.pad_rot))
    return {**_flat("coupling_offset", o), **_flat("coupling_offset_rate", o_dot)}


def _state_columns(prefix: str, state, parts) -> dict:
    out = {}
    for part in parts:
        leaves, _ = jax.tree_util.tree_flatten_with_path(getattr(state, part))
        for path, leaf in leaves:
            out.update(_flat(f"{prefix}{part}{jax.tree_util.keystr(path)}", leaf))
    return out


def record(model, gains: Gains, scenario, *, controller: str, steps: int, stack: _actuation.Stack) -> tuple:
    """The rows (inputs, outputs) of ``steps`` control periods of a MuJoCo C rollout."""
    parts = STATE_PARTS[controller]
    inputs, outputs = [], []
    dt = float(model.mj_model.opt.timestep) * stack.substeps(model)

    def on_control(k, arms, ref, command_in, state_in, command, state, sent):
        row = {"t": k * dt}
        for a, arm in zip(ARMS, arms, strict=True):
            for field, _ in ARM_FIELDS:
                row.update(_flat(f"{a}.{field}", getattr(arm, field)))
        for field, _ in REF_FIELDS:
            for i, a in enumerate(ARMS):
                row.update(_flat(f"ref.{a}.{field}", np.asarray(getattr(ref, field))[i]))
        row.update(_flat("command_in", command_in))
        row.update(_state_columns("state_in.", state_in, parts))
        inputs.append(row)
        outputs.append(
            {
                "t": k * dt,
                **_flat("command", command),
                **_flat("sent", sent),
                **_state_columns("state.", state, parts),
                **(_family_columns(gains, state, ref) if controller in FAMILY else {}),
            }
        )

    rollout_mujoco(
        model,
        gains,
        scenario,
        controller=controller,
        duration=steps * dt,
        control_substeps=stack.substeps(model),
        actuation="position",
        distro=stack.distro,
        on_control=on_control,
    )
    return inputs[:steps], outputs[:steps], dt


def export_golden(
    model, gains, out: str, *, controller: str = "synchronous", steps: int = 1000, stack=None, scenario=None
) -> list[str]:
    """Write ``steps`` control periods of ``controller`` with constant ``gains`` on
    ``model``'s position-controlled arms (``stack``: its delay, rate and
    release; ``scenario``: the comparison scenario by default) to folder
    ``out``: ``inputs.csv``, ``outputs.csv``, ``golden.json``. Every input is
    checked before the rollout; the files appear together at the end."""
    stack = stack if stack is not None else _actuation.Stack("position")
    if controller not in ALL_CONTROLLERS:
        raise ConfigError(f"controller must be one of {list(ALL_CONTROLLERS)}, got {controller!r}")
    if stack.actuation != "position":
        raise ConfigError(
            "golden files record joint position commands: they need position-controlled arms "
            f"(actuation='position'), got actuation={stack.actuation!r}",
            inputs=("actuation",),
        )
    if not isinstance(gains, Gains):
        raise ConfigError("golden files take constant gains, not a gain schedule", inputs=("gains",))
    if not (isinstance(steps, int) and 1 <= steps <= MAX_STEPS):
        raise ConfigError(f"steps must be a whole number in 1..{MAX_STEPS}, got {steps!r}", inputs=("steps",))
    if scenario is None:
        scenario = default_scenario(model)._replace(delay=np.float64(stack.scenario_delay()))
    _results.ensure_writable_dir(out)
    inputs, outputs, dt = record(model, gains, scenario, controller=controller, steps=steps, stack=stack)
    names = _joint_names(model)
    meta = {
        "format": GOLDEN_FORMAT,
        "controller": controller,
        "dt_s": dt,
        "steps": len(inputs),
        "stack": stack.to_dict(model),
        "ft_filter": float(scenario.ft_filter),  # the F/T filter coefficient every controller's wrench goes through
        "joints": names,
        "arm_fields": dict(ARM_FIELDS),
        "reference_fields": dict(REF_FIELDS),
        "state_parts": list(STATE_PARTS[controller]),
        "state_fields": {
            k: v for k, v in STATE_FIELDS.items() if any(k.split(".")[0] == p for p in STATE_PARTS[controller])
        },
        "output_fields": _output_fields(controller),
        "alpha": COMMAND_ALPHA,  # the damped least squares' alpha: J# = (J^T J + alpha I)^-1 J^T
        "columns": {"inputs": list(inputs[0]), "outputs": list(outputs[0])},
        "replay": "each row alone: the controller's step on the row's inputs (state_in, command_in) gives the "
        "row's outputs; or from row 0 on, carrying state and command from row to row",
        **_export.document(gains),
    }
    for name, rows in (("inputs.csv", inputs), ("outputs.csv", outputs)):
        _results.atomic_write_text(os.path.join(out, name), _csv_text(rows))
    _results.write_json(os.path.join(out, "golden.json"), meta)
    return [os.path.join(out, f) for f in FILES]


def _joint_names(model) -> dict:
    robot = getattr(model, "robot", None)
    if robot is not None:  # as the ros2-admittance files name them: each arm's ros_prefix before them
        return {a: [robot_names.ros_prefix(model.mj_model, a) + j for j in robot.joint_names[a]] for a in ARMS}
    import mujoco  # noqa: PLC0415 -- the names only

    m = model.mj_model
    return {
        a: [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, int(m.dof_jntid[i])) for i in arm.dof_adr]
        for a, arm in zip(ARMS, model.index.arms, strict=True)
    }


def _csv_text(rows: list[dict]) -> str:
    head = list(rows[0])
    lines = [",".join(head)]
    lines += [",".join(repr(float(r[h])) for h in head) for r in rows]
    return "\n".join(lines) + "\n"


def read(folder: str) -> tuple[dict, dict, dict]:
    """(inputs, outputs, meta): each CSV's columns as float64 arrays by name, and golden.json."""
    try:
        with open(os.path.join(folder, "golden.json")) as f:
            meta = json.load(f)
    except (OSError, ValueError) as err:
        raise ConfigError(f"{folder}: not a golden export (golden.json: {err})") from None
    if meta.get("format") != GOLDEN_FORMAT:
        raise ConfigError(
            f"{folder}: golden format {meta.get('format')!r}, this jaxsync reads {GOLDEN_FORMAT} "
            "(write it again with `jaxsync export --format golden`)"
        )
    tables = []
    for name in ("inputs.csv", "outputs.csv"):
        path = os.path.join(folder, name)
        try:
            with open(path, newline="") as f:
                rows = list(csv.reader(f))
            data = np.asarray(rows[1:], dtype=float).reshape(len(rows) - 1, len(rows[0]))
        except (OSError, ValueError, IndexError) as err:
            raise ConfigError(f"{path}: not a golden table ({err})") from None
        tables.append({h: data[:, i] for i, h in enumerate(rows[0])})
    return tables[0], tables[1], meta


def _array(table: dict, prefix: str, shape: tuple, k: int) -> np.ndarray:
    return np.array([table[prefix + _index(i)][k] for i in np.ndindex(shape)]).reshape(shape)


def replay(folder: str) -> float:
    """Run jaxsync's step on every recorded row's inputs (each row alone) and
    return the largest absolute difference from the recorded outputs."""
    inputs, outputs, meta = read(folder)
    gains = _export.from_document(meta, folder)
    controller = meta["controller"]
    options = _controller.ControllerOptions(kind=controller, distro=meta["stack"].get("ros_distro", "jazzy"))
    n = len(meta["joints"]["right"])
    parts = meta["state_parts"]
    template = _controller.init(jnp.zeros(2 * n))

    def state_at(table, prefix, k):
        state = template
        for part in parts:
            leaves, tree = jax.tree_util.tree_flatten_with_path(getattr(template, part))
            values = [
                _array(table, f"{prefix}{part}{jax.tree_util.keystr(p)}", np.shape(leaf), k) for p, leaf in leaves
            ]
            state = state._replace(**{part: jax.tree_util.tree_unflatten(tree, [jnp.asarray(v) for v in values])})
        return state

    a = meta.get("ft_filter", 1.0)

    def step(g, s, arms, ref, c):
        command, state, info = _controller.step_position(options, g, s, arms, ref, meta["dt_s"], c, a)
        return command, _controller.sent_command(options, g, arms, ref, command), state, info

    step = jax.jit(step)
    worst = 0.0
    for k in range(int(meta["steps"])):
        arms = tuple(
            ArmState(
                **{f: _array(inputs, f"{a}.{f}", shape, k) for f, shape in _arm_shapes(n).items()},
                jac_dot_qd=np.zeros(6),
                mass=np.zeros((n, n)),
                bias=np.zeros(n),
                wrist_raw=np.zeros(6),
            )
            for a in ARMS
        )
        ref = _controller.Reference(
            **{
                f: np.stack([_array(inputs, f"ref.{a}.{f}", shape, k) for a in ARMS])
                for f, shape in _ref_shapes(n).items()
            }
        )
        command, sent, state, _ = step(
            gains, state_at(inputs, "state_in.", k), arms, ref, _array(inputs, "command_in", (2 * n,), k)
        )
        want_state = state_at(outputs, "state.", k)
        got = [command, sent, *(getattr(state, p) for p in parts)]
        want = [
            _array(outputs, "command", (2 * n,), k),
            _array(outputs, "sent", (2 * n,), k),
            *(getattr(want_state, p) for p in parts),
        ]
        if "coupling_offset[0][0]" in outputs:  # the family's offset (files of the family controllers)
            got += list(_family_offset(gains, state.coupling, jnp.asarray(ref.pad_rot)))
            want += [_array(outputs, f, (2, 6), k) for f in FAMILY_OUTPUT_FIELDS]
        for x, y in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
            worst = max(worst, float(np.max(np.abs(np.asarray(x) - np.asarray(y)), initial=0.0)))
    return worst


def _arm_shapes(n: int) -> dict:
    return {"q": (n,), "qd": (n,), "pad_pos": (3,), "pad_rot": (3, 3), "pad_vel": (6,), "jac": (6, n), "wrench": (6,)}


def _ref_shapes(n: int) -> dict:
    return {"pad_pos": (3,), "pad_rot": (3, 3), "pad_vel": (6,), "pad_acc": (6,), "wrench": (6,), "q_rest": (n,)}


class Golden(NamedTuple):
    """What :func:`golden_job` wrote."""

    paths: list[str]
    controller: str
    delay: int  # control periods
    worst: float  # the replay's largest difference from the recorded outputs
    exact: bool  # worst <= REPLAY_TOLERANCE


REPLAY_TOLERANCE = 1e-9  # rad, and the state's units: XLA may fuse a step differently in another program


def golden_job(
    gains=None,
    out: str = "results/golden",
    *,
    model=None,
    visual: bool = True,
    controller: str | None = None,
    steps: int = 1000,
    actuation: str = "position",
    control_rate: float | None = None,
    delay=0,
    distro: str = "jazzy",
    any_model: bool = False,
    ft_filter: float = 1.0,
) -> Golden:
    """``jaxsync export --format golden``: load ``model`` (a loaded model, an MJCF
    or robot file, None: the paper model) and ``gains`` (a gains file, refused
    when tuned on another model unless ``any_model``; None: the stack's
    defaults), write the golden files of the stack (``actuation``,
    ``control_rate``, ``delay`` one number of periods, ``distro``) and replay
    them. ``controller`` None: the one the gains file was tuned for, else
    synchronous. ``ft_filter``: the rule's F/T filter coefficient in the
    scenario recorded."""
    stack = _actuation.Stack.of(actuation, control_rate, delay, distro)
    lag = stack.scenario_delay()
    coefficient = _actuation.check_ft_filter(ft_filter, one=True)[0]
    from_file = gains is not None and isinstance(gains, str | os.PathLike)
    if controller is None:
        controller = (gains_file.controller_of(gains) if from_file else None) or "synchronous"
    loaded = as_model(model, visual=visual)
    g = gains_file.load_or_default(gains, loaded, any_model, stack.actuation, controller)

    scenario = default_scenario(loaded)._replace(delay=np.float64(lag), ft_filter=np.float64(coefficient))
    paths = export_golden(loaded, g, out, controller=controller, steps=steps, stack=stack, scenario=scenario)
    worst = replay(out)
    return Golden(paths, controller, lag, worst, worst <= REPLAY_TOLERANCE)
