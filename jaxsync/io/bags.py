"""Recordings of a position-controlled robot as ROS 2 bags (rosbag2, MCAP or SQLite), without ROS.

What every ros2_control robot can record: the joint states it reached
(``sensor_msgs/msg/JointState`` from ``joint_state_broadcaster``) and the
position commands it was sent, either ``std_msgs/msg/Float64MultiArray`` (what
``forward_command_controller``'s ``JointGroupPositionController`` takes on
``~/commands``, in its ``joints`` parameter's order) or
``trajectory_msgs/msg/JointTrajectory``; optionally each wrist sensor's
``geometry_msgs/msg/WrenchStamped``. Read and written with the ``rosbags``
library (pure Python).

Time: a JointState's header stamp (the bag's receive time where stamps are
zero); a Float64MultiArray has no header, so its receive time; a
JointTrajectory's points at its stamp plus ``time_from_start``.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from jaxsync._errors import JaxsyncError

JOINT_STATE = "sensor_msgs/msg/JointState"
MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"
TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
WRENCH = "geometry_msgs/msg/WrenchStamped"
COMMAND_TYPES = (MULTI_ARRAY, TRAJECTORY)
STATE_TOPIC = "/joint_states"
COMMAND_TOPIC = "/forward_position_controller/commands"
GAP_PERIODS = 5.0  # a step between samples longer than this many median periods: dropped messages
STORAGES = ("mcap", "sqlite3")


class RecordingError(JaxsyncError):
    """A recording that cannot be read or does not hold what calibration needs."""


@dataclasses.dataclass(frozen=True)
class Recording:
    """Joint states and position commands of one run, in ``joints``' order.

    Times are seconds from the recording's first message."""

    joints: tuple[str, ...]
    state_times: np.ndarray  # (S,)
    q: np.ndarray  # (S, J) rad
    dq: np.ndarray | None  # (S, J) rad/s, None where the states carry no velocity
    command_times: np.ndarray  # (C,)
    commands: np.ndarray  # (C, J) rad
    source: str = ""
    wrenches: tuple = ()  # per wrist sensor asked for: (times (W,), values (W, 6) [force N, torque N m])
    effort: np.ndarray | None = None  # (S, J) N m, the joints' torques where every state carries them

    @property
    def duration(self) -> float:
        return float(self.state_times[-1] - self.state_times[0])

    @property
    def command_period(self) -> float:
        return float(np.median(np.diff(self.command_times)))


def _typestore():
    # rosbags is imported here, not at the top: only the commands that read or write bags load it
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _stamp(t: float, store):
    sec = int(np.floor(t))
    return store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)


def _header(t: float, store):
    return store.types["std_msgs/msg/Header"](stamp=_stamp(t, store), frame_id="")


def joint_state(t: float, names, q, dq=None, store=None, effort=None):
    store = store or _typestore()
    empty = np.zeros(0)
    return store.types[JOINT_STATE](
        header=_header(t, store),
        name=list(names),
        position=np.asarray(q, float),
        velocity=np.asarray(dq, float) if dq is not None else empty,
        effort=np.asarray(effort, float) if effort is not None else empty,
    )


def multi_array(values, store=None):
    store = store or _typestore()
    layout = store.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    return store.types[MULTI_ARRAY](layout=layout, data=np.asarray(values, float))


def trajectory(t: float, names, q, store=None):
    """A one-point JointTrajectory at ``t`` (what a streaming command sends)."""
    store = store or _typestore()
    point = store.types["trajectory_msgs/msg/JointTrajectoryPoint"](
        positions=np.asarray(q, float),
        velocities=np.zeros(0),
        accelerations=np.zeros(0),
        effort=np.zeros(0),
        time_from_start=store.types["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
    )
    return store.types[TRAJECTORY](header=_header(t, store), joint_names=list(names), points=[point])


def wrench(t: float, values, store=None):
    """A WrenchStamped at ``t``: ``values`` [fx, fy, fz, tx, ty, tz] (N, N m)."""
    store = store or _typestore()
    vec = store.types["geometry_msgs/msg/Vector3"]
    f, tq = np.asarray(values, float)[:3], np.asarray(values, float)[3:]
    body = store.types["geometry_msgs/msg/Wrench"](force=vec(*f), torque=vec(*tq))
    return store.types[WRENCH](header=_header(t, store), wrench=body)


def write_bag(path, messages, storage: str = "mcap") -> Path:
    """Write ``messages``, (topic, msgtype, time s, message) in time order, as a new rosbag2 folder.

    Written beside ``path`` first and moved there complete: an interrupted
    write leaves nothing behind."""
    # rosbags is imported here, not at the top: only the commands that read or write bags load it
    from rosbags.rosbag2 import StoragePlugin, Writer

    if storage not in STORAGES:
        raise RecordingError(f"storage must be one of {list(STORAGES)}, got {storage!r}", inputs=("storage",))
    path = Path(path)
    if path.exists():
        raise RecordingError(f"{path} exists already: a bag is written to a new folder", inputs=("path",))
    store = _typestore()
    parent = path.parent if str(path.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=parent))
    work = tmp / path.name
    try:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        with Writer(work, version=9, storage_plugin=plugin) as writer:
            conns = {}
            for topic, msgtype, t, msg in messages:
                if (topic, msgtype) not in conns:
                    conns[topic, msgtype] = writer.add_connection(topic, msgtype, typestore=store)
                writer.write(conns[topic, msgtype], int(round(t * 1e9)), store.serialize_cdr(msg, msgtype))
        os.replace(work, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def write_recording(
    path,
    rec: Recording,
    state_topic: str = STATE_TOPIC,
    command_topic: str | tuple[str, str] = COMMAND_TOPIC,
    command_type: str = MULTI_ARRAY,
    state_order=None,
    storage: str = "mcap",
    start: float = 1.0e9,
    wrench_topics=(),
    left_lag: float = 0.0,
) -> Path:
    """``rec`` as a bag: joint states (names in ``state_order``, default ``rec.joints``) and commands
    (Float64MultiArray in ``rec.joints``' order, or one-point JointTrajectories), and ``rec.wrenches``
    on ``wrench_topics`` (one each). ``command_topic`` (right's, left's): one controller per arm, each
    topic its arm's half of ``rec.joints``, the left's messages ``left_lag`` s after the right's.
    ``start``: the first message's time (s since the epoch)."""
    store = _typestore()
    order = list(state_order or rec.joints)
    cols = [rec.joints.index(j) for j in order]
    msgs = []
    for i, t in enumerate(rec.state_times):
        dq = rec.dq[i, cols] if rec.dq is not None else None
        tau = rec.effort[i, cols] if rec.effort is not None else None
        state = joint_state(start + t, order, rec.q[i, cols], dq, store, tau)
        msgs.append((state_topic, JOINT_STATE, start + t, state))
    half = len(rec.joints) // 2
    if isinstance(command_topic, str):
        streams = [(command_topic, slice(None), 0.0)]
    else:
        streams = [(command_topic[0], slice(0, half), 0.0), (command_topic[1], slice(half, None), left_lag)]
    for topic, part, lag in streams:
        for i, t in enumerate(rec.command_times):
            t = start + t + lag
            if command_type == MULTI_ARRAY:
                msg = multi_array(rec.commands[i, part], store)
            else:
                msg = trajectory(t, rec.joints[part], rec.commands[i, part], store)
            msgs.append((topic, command_type, t, msg))
    for topic, (times, values) in zip(wrench_topics, rec.wrenches if wrench_topics else (), strict=True):
        msgs.extend((topic, WRENCH, start + t, wrench(start + t, w, store)) for t, w in zip(times, values, strict=True))
    msgs.sort(key=lambda m: m[2])
    return write_bag(path, msgs, storage)


def _times_ok(times: np.ndarray, topic: str, min_samples: int) -> None:
    if len(times) < min_samples:
        raise RecordingError(f"{topic}: {len(times)} messages, calibration needs at least {min_samples}")
    step = np.diff(times)
    back = np.flatnonzero(step <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise RecordingError(
            f"{topic}: time stamps out of order at message {i} ({times[i] - times[0]:.4f} s after the first, "
            f"not after the one before it)"
        )
    period = float(np.median(step))
    gaps = np.flatnonzero(step > GAP_PERIODS * period)
    if gaps.size:
        i = int(gaps[0])
        raise RecordingError(
            f"{topic}: a gap of {step[i]:.4f} s at {times[i] - times[0]:.3f} s (the period is {period:.4f} s): "
            f"{gaps.size} gap(s) longer than {GAP_PERIODS:g} periods, messages were dropped"
        )


def read_recording(
    path,
    joints,
    state_topic: str = STATE_TOPIC,
    command_topic: str | tuple[str, str] = COMMAND_TOPIC,
    command_joints=None,
    min_samples: int = 500,
    wrench_topics=(),
) -> Recording:
    """The joint states and commands of ``joints`` in the bag at ``path``, and the wrenches on
    ``wrench_topics`` (WrenchStamped, one topic per sensor).

    ``command_topic``: one topic for both arms, or (right arm's, left arm's):
    one position controller per arm, each message in its own arm's joint
    order (``joints``: the right arm's half first). Both topics must run at
    one rate, each right message with a left one within a quarter period
    (controllers of one controller manager publish in the same cycle); the
    commands are paired on the right topic's times.
    ``command_joints``: the joints a Float64MultiArray's entries are, in
    order (the command controller's ``joints`` parameter; default
    ``joints``; per-arm topics: each arm's entries among them). Every
    problem is a one-line :class:`RecordingError`."""
    # rosbags is imported here, not at the top: only the commands that read or write bags load it
    from rosbags.highlevel import AnyReader, AnyReaderError

    path = Path(path)
    joints = tuple(joints)
    command_topics = (command_topic,) if isinstance(command_topic, str) else tuple(command_topic)
    if len(command_topics) not in (1, 2) or len(set(command_topics)) != len(command_topics):
        raise RecordingError(
            f"command_topic: one topic, or two different ones (right arm's, left arm's), got {list(command_topics)}",
            inputs=("command_topic",),
        )
    if not path.exists():
        raise RecordingError(f"{path}: no such bag (a rosbag2 folder, or its .mcap or .db3 file)", inputs=("bag",))
    try:
        reader = AnyReader([path], default_typestore=_typestore())
        reader.open()
    except (AnyReaderError, Exception) as err:  # rosbags raises several kinds for a file it cannot parse
        msg = f"{path}: not a readable rosbag2 recording (MCAP or SQLite): {err}"
        raise RecordingError(msg, inputs=("bag",)) from None
    try:
        kinds = {c.topic: c.msgtype for c in reader.connections}
        listed = ", ".join(f"{t} ({k})" for t, k in sorted(kinds.items())) or "none"
        wanted = [(state_topic, (JOINT_STATE,), "state_topic")]
        wanted += [(topic, COMMAND_TYPES, "command_topic") for topic in command_topics]
        wanted += [(topic, (WRENCH,), "wrench_topics") for topic in wrench_topics]
        for topic, allowed, flag in wanted:
            if topic not in kinds:
                raise RecordingError(f"{path}: no topic {topic}; its topics: {listed}", inputs=(flag,))
            if kinds[topic] not in allowed:
                raise RecordingError(
                    f"{path}: topic {topic} is {kinds[topic]}, expected {' or '.join(allowed)}", inputs=(flag,)
                )
        states, wrenches = [], {topic: [] for topic in wrench_topics}
        commands = {topic: [] for topic in command_topics}
        topics = (state_topic, *command_topics, *wrench_topics)
        for conn, t_bag, raw in reader.messages(connections=[c for c in reader.connections if c.topic in topics]):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == state_topic:
                states.append((t_bag, msg))
            elif conn.topic in commands:
                commands[conn.topic].append((t_bag, conn.msgtype, msg))
            else:
                f, tq = msg.wrench.force, msg.wrench.torque
                wrenches[conn.topic].append((_stamp_ns(msg.header, t_bag), (f.x, f.y, f.z, tq.x, tq.y, tq.z)))
    finally:
        reader.close()
    if not states:
        raise RecordingError(f"{path}: topic {state_topic} holds no messages", inputs=("state_topic",))
    t_s, q, dq, effort = _states(states, joints, state_topic)
    if len(command_topics) == 1:
        t_c, cmd = _commands(commands[command_topic], joints, tuple(command_joints or joints), command_topic)
        t0 = min(t_s[0], t_c[0])  # integer nanoseconds until here: seconds since the epoch lose them in a double
        _times_ok((t_c - t0) * 1e-9, command_topic, min_samples)
    else:
        half = len(joints) // 2
        arms = []
        for topic, arm_joints in zip(command_topics, (joints[:half], joints[half:]), strict=True):
            own = tuple(j for j in command_joints if j in arm_joints) if command_joints else arm_joints
            t_arm, cmd_arm = _commands(commands[topic], arm_joints, own, topic)
            t0 = min(t_s[0], t_arm[0])
            _times_ok((t_arm - t0) * 1e-9, topic, min_samples)
            arms.append((t_arm, cmd_arm))
        t_c, cmd = _paired(arms, command_topics)
        t0 = min(t_s[0], t_c[0], arms[1][0][0])
    t_s, t_c = (t_s - t0) * 1e-9, (t_c - t0) * 1e-9
    _times_ok(t_s, state_topic, min_samples)
    sensed = []
    for topic in wrench_topics:
        if not wrenches[topic]:
            raise RecordingError(f"{path}: topic {topic} holds no messages", inputs=("wrench_topics",))
        t_w = (np.array([t for t, _ in wrenches[topic]], dtype=np.int64) - t0) * 1e-9
        _times_ok(t_w, topic, min_samples)
        sensed.append((t_w, np.array([w for _, w in wrenches[topic]], float)))
    return Recording(joints, t_s, q, dq, t_c, cmd, str(path), tuple(sensed), effort)


def _paired(arms, topics):
    """Two arms' command streams as one: each right command with the left one nearest in time, which must
    lie within a quarter period; the streams at one rate. Returns (the right topic's times, (C, J) commands)."""
    (t_r, c_r), (t_l, c_l) = arms
    period_r, period_l = float(np.median(np.diff(t_r))), float(np.median(np.diff(t_l)))
    if abs(period_r - period_l) > 0.01 * period_r:
        raise RecordingError(
            f"command topics {topics[0]} and {topics[1]} run at {1e9 / period_r:.4g} Hz and {1e9 / period_l:.4g} Hz: "
            "the two arms' position controllers must run at one rate",
            inputs=("command_topic",),
        )
    k = np.clip(np.searchsorted(t_l, t_r), 1, len(t_l) - 1)
    k = np.where(np.abs(t_l[k - 1] - t_r) <= np.abs(t_l[k] - t_r), k - 1, k)
    off = np.abs(t_l[k] - t_r)
    inside = off <= 0.25 * period_r
    if not inside[1:-1].all() or inside.sum() < 0.99 * min(len(t_r), len(t_l)):
        worst = float(np.max(off[1:-1])) if len(off) > 2 else float(np.max(off))
        raise RecordingError(
            f"command topics {topics[0]} and {topics[1]}: {int((~inside).sum())} right commands have no left one "
            f"within a quarter period ({0.25e-6 * period_r:.3g} ms; the farthest {worst * 1e-6:.3g} ms): the two "
            "arms' controllers must publish in the same control cycle",
            inputs=("command_topic",),
        )
    return t_r[inside], np.concatenate([c_r[inside], c_l[k[inside]]], axis=1)


def _stamp_ns(header, t_bag: int) -> int:
    t = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return t if t > 0 else int(t_bag)


def _states(states, joints, topic):
    names = list(states[0][1].name)
    missing = [j for j in joints if j not in names]
    if missing:
        raise RecordingError(
            f"{topic}: joint(s) {', '.join(missing)} not in its messages (they name {', '.join(names)})",
            inputs=("joints",),
        )
    times = np.zeros(len(states), dtype=np.int64)
    q, dq = np.zeros((len(states), len(joints))), np.zeros((len(states), len(joints)))
    effort = np.zeros_like(q)
    has_vel = has_effort = True
    for i, (t_bag, msg) in enumerate(states):
        order = list(msg.name)
        try:
            cols = [order.index(j) for j in joints]
        except ValueError:
            absent = [j for j in joints if j not in order]
            msg_text = f"{topic}: message {i} lacks joint(s) {', '.join(absent)}"
            raise RecordingError(msg_text, inputs=("joints",)) from None
        if len(msg.position) != len(order):
            raise RecordingError(f"{topic}: message {i} has {len(order)} names but {len(msg.position)} positions")
        times[i] = _stamp_ns(msg.header, t_bag)
        q[i] = np.asarray(msg.position)[cols]
        if len(msg.velocity) == len(order):
            dq[i] = np.asarray(msg.velocity)[cols]
        else:
            has_vel = False
        if len(msg.effort) == len(order):
            effort[i] = np.asarray(msg.effort)[cols]
        else:
            has_effort = False
    return times, q, (dq if has_vel else None), (effort if has_effort else None)


def _commands(commands, joints, command_joints, topic):
    if not commands:
        raise RecordingError(f"topic {topic} holds no messages", inputs=("command_topic",))
    missing = [j for j in joints if j not in command_joints]
    times, rows = [], []
    for i, (t_bag, kind, msg) in enumerate(commands):
        if kind == MULTI_ARRAY:
            if missing:
                raise RecordingError(
                    f"{topic}: the command joints ({', '.join(command_joints)}) lack {', '.join(missing)}",
                    inputs=("command_joints",),
                )
            if len(msg.data) != len(command_joints):
                raise RecordingError(
                    f"{topic}: message {i} holds {len(msg.data)} commands, the command joints are "
                    f"{len(command_joints)} ({', '.join(command_joints)})",
                    inputs=("command_joints",),
                )
            cols = [command_joints.index(j) for j in joints]
            times.append(t_bag)
            rows.append(np.asarray(msg.data)[cols])
        else:
            names = list(msg.joint_names)
            absent = [j for j in joints if j not in names]
            if absent:
                raise RecordingError(f"{topic}: message {i} lacks joint(s) {', '.join(absent)}", inputs=("joints",))
            cols = [names.index(j) for j in joints]
            t0 = _stamp_ns(msg.header, t_bag)
            for p in msg.points:
                times.append(t0 + int(p.time_from_start.sec) * 1_000_000_000 + int(p.time_from_start.nanosec))
                rows.append(np.asarray(p.positions)[cols])
    return np.asarray(times, dtype=np.int64), np.asarray(rows)
