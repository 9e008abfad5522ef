"""The robot file's own names for what the composed scene renames, kept in the scene.

The composed scene (``jaxsync.physics.compose``) renames each arm's joints to
jaxsync's ``r_joint1``, ``r_joint2``, ... and puts a prefix of its own
(``right/``, ``left/`` or ``robot/``) before every name of the robot's MJCF.
What the robot file called each joint, that prefix, and the prefix of the
arm's ROS names (``arms.<side>.ros_prefix``) are written into the scene as one
MuJoCo custom text element, :data:`TEXT`, so that whatever holds the compiled
model (the grasp solver's messages, the ROS export, a scene file written next
to the results) names them as the robot file does. A model without it (an MJCF
in jaxsync's convention, the paper model) keeps its own names.
"""

from __future__ import annotations

import json
import os
import re

import mujoco

from jaxsync._errors import ConfigError
from jaxsync.physics.robot import ARM_NAMES, Robot

TEXT = "jaxsync_robot_names"
SIDES = {"r": "right", "l": "left"}
_JOINT = re.compile(r"([rl])_joint(\d+)")
PREFIXED = "their ROS names are prefixed right_ and left_"  # the model's note where ros_prefixes() chose them


def record(spec: mujoco.MjSpec, arms: dict[str, dict]) -> None:
    """Write ``{arm: {"joints": [...], "prefix": ..., "ros_prefix": ...}}`` into ``spec``."""
    spec.add_text(name=TEXT, data=json.dumps(arms, sort_keys=True))


def read(m: mujoco.MjModel) -> dict[str, dict] | None:
    """What :func:`record` wrote into the model, or ``None``."""
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TEXT, TEXT)
    if i < 0:
        return None
    adr, size = int(m.text_adr[i]), int(m.text_size[i])
    return json.loads(m.text_data[adr : adr + size].rstrip(b"\0").decode())


def joint_name(m: mujoco.MjModel, j: int) -> str:
    """Joint ``j`` as the robot file names it (the model's own name where it names none)."""
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint {j}"
    names, hit = read(m), _JOINT.fullmatch(name)
    if names is None or hit is None:
        return name
    joints = names[SIDES[hit.group(1)]]["joints"]
    k = int(hit.group(2)) - 1
    return joints[k] if k < len(joints) else name


def body_name(m: mujoco.MjModel, arm: str, b: int) -> str:
    """Body ``b`` of ``arm`` ("right" or "left") as its MJCF names it (without the scene's prefix)."""
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or f"body {b}"
    names = read(m)
    return name.removeprefix(names[arm]["prefix"]) if names is not None else name


def ros_prefix(m: mujoco.MjModel, arm: str) -> str:
    """The prefix of ``arm``'s joint and link names in its ROS files ("" when none is given)."""
    names = read(m)
    return names[arm].get("ros_prefix", "") if names is not None else ""


def ros_prefixes(robot: Robot, links: dict, notes: list | None = None) -> dict[str, str]:
    """Each arm's prefix of its ROS joint and link names: the robot file's ``ros_prefix``; where both
    arms give none and name the same joints or links (one arm file used twice), ``right_`` and
    ``left_``, said in ``notes``: one ros2_control system cannot hold two joints of one name.

    Raises:
      ConfigError: prefixes the file gives that still leave both arms a name in common.
    """
    given = {a: arm.ros_prefix for a, arm in zip(ARM_NAMES, robot.arms, strict=True)}

    def names(prefixes):
        return [{prefixes[a] + n for n in (*arm.joints, *(v for v in links[a].values() if v != "world"))}
                for a, arm in zip(ARM_NAMES, robot.arms, strict=True)]  # fmt: skip

    right, left = names(given)
    if not right & left:
        return given
    if not any(given.values()):
        if notes is not None:
            notes.append(f"both arms name the same joints and links ({', '.join(sorted(right & left)[:3])}, ...): "
                         f"{PREFIXED} (arms.<side>.ros_prefix sets others)")  # fmt: skip
        return {"right": "right_", "left": "left_"}
    raise ConfigError(
        f"{os.path.basename(robot.path)}: arms.right.ros_prefix {given['right']!r} and arms.left.ros_prefix "
        f"{given['left']!r} leave both arms the names {sorted(right & left)[:3]}: give the arms different "
        "prefixes (e.g. right_ and left_)"
    )
