"""Every world's tf tree and robot description, as the plan carries them. No rclpy here.

ros_bridge/worker/tf.py publishes them; the frame conventions are documented there.
"""

from __future__ import annotations

import dataclasses
import logging
import xml.etree.ElementTree as ET
from collections.abc import Callable

import numpy as np

from batchsim.hardware import BatchedSystem
from batchsim.model import RobotPart
from batchsim.model.frames import FrameTree, frame_tree, initial_transforms, relative_transforms
from batchsim.model.from_urdf import is_urdf
from batchsim.model.urdf import generate_urdf, robot_description

FLEET_FRAME = "world"  # the fixed frame every world's tf tree hangs from
log = logging.getLogger("batchsim.ros_bridge")


@dataclasses.dataclass(frozen=True)
class TfSpec:
    """Every world's tf tree and robot description (ros_bridge/worker/tf.py publishes them).

    Frame names are unprefixed here; the workers prefix them with `<ns>/`.

    Attributes:
      moving: (parent, child) of each transform that moves, in channel order.
      static: (parent, child) of each fixed transform.
      static_values: (nstatic, 7) translation xyz and rotation xyzw of the fixed ones.
      channel: the snapshot channel the moving ones are computed from, (nworld, 7 * nbody):
        the world poses of the bodies they join (position xyz, MuJoCo's quaternion wxyz),
        copied as the engine gives them; each worker computes its own worlds' parent-relative
        transforms from them (`moving_transforms`), so the loop's period pays a copy, not
        the math for every world.
      joins: the moving transforms' (child, parent) body rows in that channel, as a FrameTree
        whose `body` and `parent_body` index the channel's bodies.
      root: each world's root frame (`world`, or `odom` for a floating base).
      fleet_frame: the frame every world's root hangs from in the fleet's tree.
      description: the robot's URDF (robot_description).
      every: control periods between two tf messages.
      mjcf: the MJCF the simulation compiled (mujoco_robot_description, as mujoco_ros2_control
        publishes the one it generates from a URDF).
      bodies: the body ids whose poses the channel holds, in its order (the view draws from them).
      robot_descriptions: in a world of several robots (batchsim.fleet), each robot's URDF as
        (prefix, text), published at `<ns>/<robot>/robot_description`; its links are the robot's
        own body names, which tf carries as `<ns>/<robot>/<body>` (robot_state_publisher's
        frame_prefix `<ns>/<robot>/`).
    """

    moving: tuple[tuple[str, str], ...]
    static: tuple[tuple[str, str], ...]
    static_values: np.ndarray
    channel: int
    joins: FrameTree
    root: str
    fleet_frame: str
    description: str
    every: int = 1
    mjcf: str = ""
    bodies: tuple[int, ...] = ()
    robot_descriptions: tuple[tuple[str, str], ...] = ()

    def moving_transforms(self, poses: np.ndarray) -> np.ndarray:
        """(n, 7 * nmoving) parent->child transforms (translation xyz, rotation xyzw) of the
        moving frames from `poses`, rows of the channel (n, 7 * nbody)."""
        p = np.asarray(poses).reshape(len(poses), -1, 7)
        t, r = relative_transforms(self.joins, p[..., :3], p[..., 3:])
        return np.concatenate([t, r], axis=2).reshape(len(poses), -1)


def tf_spec(
    sim: BatchedSystem,
    every: int,
    channel: Callable[[str, int, Callable[[np.ndarray], None]], int],
    source: str | None = None,
) -> TfSpec:
    """The tf tree of `sim`'s robot, its moving transforms filled from the engine's body
    poses (forward kinematics of every world at once) into one channel. `source`: the
    user's robot description (`--ros2-control`), published when it is a URDF whose links
    are the tree's frames."""
    tree = frame_tree(sim.spec)
    sim.body_poses()  # the engine's kinematics bound now: the first tf is the current state
    moving = np.flatnonzero(~tree.static)
    fixed = np.flatnonzero(tree.static)
    t0, r0 = initial_transforms(tree, sim.spec)
    nworld = sim.nworld

    bodies = np.union1d(tree.body[moving], tree.parent_body[moving])  # the moving frames' ends only
    joins = dataclasses.replace(
        tree,
        body=np.searchsorted(bodies, tree.body[moving]),
        parent_body=np.searchsorted(bodies, tree.parent_body[moving]),
    )

    def fill_tf(out: np.ndarray) -> None:  # one pass from the engine's rows where it keeps them
        v = out.reshape(nworld, len(bodies), 7)
        sim.body_poses_into(v[:, :, :3], v[:, :, 3:], bodies)

    fill_tf.reads_engine = True  # type: ignore[attr-defined]  # the bridge writes it before the steps, never beside them

    pairs = list(zip(tree.parents, tree.names, strict=True))
    description, extra = _description(sim, tree, source)
    static = [pairs[k] for k in fixed] + [(body, link) for body, link, _, _ in extra]
    values = [np.concatenate([t0[fixed], r0[fixed]], axis=1)]
    values += [np.concatenate([pos, quat[[1, 2, 3, 0]]])[None] for _, _, pos, quat in extra]
    return TfSpec(
        moving=tuple(pairs[k] for k in moving),
        static=tuple(static),
        static_values=np.concatenate(values, axis=0),
        channel=channel("tf", 7 * len(bodies), fill_tf),
        joins=joins,
        root=tree.root,
        fleet_frame=FLEET_FRAME,
        description=description,
        every=every,
        mjcf=sim.spec.xml,
        bodies=tuple(int(b) for b in bodies),
        robot_descriptions=tuple(_robot_description(r) for r in sim.spec.robots),
    )


def _robot_description(robot: RobotPart) -> tuple[str, str]:
    """A fleet robot's URDF: its own file where it is one, else the one generated from its MJCF."""
    spec = robot.spec
    assert spec is not None
    if spec.path is not None and is_urdf(str(spec.path)):
        return robot.prefix, robot_description(spec, robot.model)
    urdf = generate_urdf(spec)
    for line in urdf.warnings:
        log.warning("batchsim: %srobot_description: %s", robot.prefix, line)
    return robot.prefix, urdf.text




def _description(sim: BatchedSystem, tree, source: str | None) -> tuple[str, list]:
    """The user's URDF if its links are frames of the tree (so RViz finds a transform for
    each), else the one generated from the MJCF (with a warning saying why), and the
    generated one's links that are no body (Urdf.extra_frames: tf_static carries them)."""
    if source is not None:
        text = robot_description(sim.spec, source)
        links = {link.get("name") for link in ET.fromstring(text).iter("link")}
        unknown = sorted(links - set(tree.names) - {tree.root})
        if not unknown:
            return text, []
        more = f" and {len(unknown) - 3} more" if len(unknown) > 3 else ""
        log.warning(
            "batchsim: robot_description: the links %s%s of %s are no bodies of the MJCF (tf's frames are "
            "its body names): publishing the URDF generated from the MJCF instead",
            ", ".join(unknown[:3]), more, str(source).split()[0],
        )
    urdf = generate_urdf(sim.spec)
    for line in urdf.warnings:
        log.warning("batchsim: robot_description: %s", line)
    return urdf.text, urdf.extra_frames
