"""Every world's tf tree and robot description, as the plan carries them. No rclpy here.

ros_bridge/worker/tf.py publishes them; the frame conventions are documented there.
"""

from __future__ import annotations

import dataclasses
import logging
import xml.etree.ElementTree as ET
from collections.abc import Callable, Sequence

import numpy as np

from batchsim.contract import Contract
from batchsim.controllers.topics import Transform
from batchsim.model import RobotPart
from batchsim.model.frames import FrameTree, fixed_frames, frame_tree, initial_transforms, relative_transforms
from batchsim.model.from_urdf import is_urdf
from batchsim.model.urdf import fixed_links, generate_urdf, robot_description

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
      controller_moving: (parent, child) of the transforms controllers move (a diff drive's
        `odom -> base_link`), after the body transforms in `moving`'s order; the channel
        holds them after the bodies' poses, parent-relative already (7 values each).
      anchors: (parent, child) of fixed transforms that differ per world: the world's root to
        a controller's frame that is no frame of the tree (a robot's `odom`, where the robot
        started in that world), so every frame a controller names is in the world's tree.
      anchor_values: (nworld, nanchor, 7) their translation xyz and rotation xyzw.
      source_topic: the topic the description was read from (`/robot_description`), where
        another node publishes it: no robot_description of batchsim's goes there.
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
    controller_moving: tuple[tuple[str, str], ...] = ()
    anchors: tuple[tuple[str, str], ...] = ()
    anchor_values: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0, 7)))
    source_topic: str = ""

    @property
    def all_moving(self) -> tuple[tuple[str, str], ...]:
        """(parent, child) of every moving transform, in `moving_transforms`' order."""
        return self.moving + self.controller_moving

    def moving_transforms(self, poses: np.ndarray) -> np.ndarray:
        """(n, 7 * (nmoving + ncontroller)) parent->child transforms (translation xyz, rotation
        xyzw) of the moving frames from `poses`, rows of the channel, then the controllers'."""
        poses = np.asarray(poses)
        nbody = len(self.bodies)
        p = poses[:, : 7 * nbody].reshape(len(poses), nbody, 7)
        t, r = relative_transforms(self.joins, p[..., :3], p[..., 3:])
        bodies = np.concatenate([t, r], axis=2).reshape(len(poses), -1)
        return np.concatenate([bodies, poses[:, 7 * nbody :]], axis=1) if self.controller_moving else bodies

    @property
    def frames(self) -> set[str]:
        """Every frame of a world's tree (unprefixed), its root and the fleet's frame included."""
        pairs = (*self.moving, *self.static, *self.controller_moving, *self.anchors)
        return {self.root, self.fleet_frame, *(child for _, child in pairs)}

    def unknown_frames(self, stamped: Sequence[tuple[str, str]]) -> list[tuple[str, str]]:
        """Of (topic, frame id) pairs (`{ns}/frame` or `frame`), those whose frame is in no tree."""
        frames = self.frames
        return [(topic, f) for topic, f in stamped if f and _in_world(f) not in frames]

    def static_of(self, worlds) -> list[list[tuple[str, str, np.ndarray]]]:
        """Per world of `worlds` (indices), its fixed transforms as (parent, child, value):
        the tree's, then its anchors."""
        fixed = [(a, b, v) for (a, b), v in zip(self.static, self.static_values, strict=True)]
        if not self.anchors:
            return [fixed for _ in worlds]
        return [fixed + [(a, b, v) for (a, b), v in zip(self.anchors, self.anchor_values[w], strict=True)] for w in worlds]


def tf_spec(
    sim: Contract,
    every: int,
    channel: Callable[[str, int, Callable[[np.ndarray], None]], int],
    source: str | None = None,
    transforms: Sequence[Transform] = (),
    source_topic: str | None = None,
) -> TfSpec:
    """The tf tree of `sim`'s robot, its moving transforms filled from the engine's body
    poses (forward kinematics of every world at once) into one channel. `source`: the
    user's robot description (`--ros2-control`), published when it is a URDF whose links
    are the tree's frames. `transforms`: the controllers' (batchsim.controllers.topics)."""
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

    pairs = list(zip(tree.parents, tree.names, strict=True))
    attached = _sensor_frames(sim, tree)  # sites, camera frames
    description, extra = _description(sim, tree, source, {name for _, name, _, _ in attached})
    extra = [*extra, *(f for f in attached if f[1] not in {link for _, link, _, _ in extra})]
    frames = {tree.root, *tree.names, *(link for _, link, _, _ in extra)}
    moved, anchors, anchor_values = controller_frames(sim, tree.root, frames, transforms)
    width = 7 * len(bodies)

    def fill_tf(out: np.ndarray) -> None:  # one pass from the engine's rows where it keeps them
        v = out[:, :width].reshape(nworld, len(bodies), 7)
        sim.body_poses_into(v[:, :, :3], v[:, :, 3:], bodies)
        for k, t in enumerate(moved):  # the controllers' own, after the bodies'
            out[:, width + 7 * k : width + 7 * k + 7] = t.read()

    fill_tf.reads_engine = True  # type: ignore[attr-defined]  # the bridge writes it before the steps, never beside them

    static = [pairs[k] for k in fixed] + [(body, link) for body, link, _, _ in extra]
    values = [np.concatenate([t0[fixed], r0[fixed]], axis=1)]
    values += [np.concatenate([pos, quat[[1, 2, 3, 0]]])[None] for _, _, pos, quat in extra]
    return TfSpec(
        moving=tuple(pairs[k] for k in moving),
        static=tuple(static),
        static_values=np.concatenate(values, axis=0),
        channel=channel("tf", width + 7 * len(moved), fill_tf),
        joins=joins,
        root=tree.root,
        fleet_frame=FLEET_FRAME,
        description=description,
        every=every,
        mjcf=sim.spec.xml,
        bodies=tuple(int(b) for b in bodies),
        robot_descriptions=tuple(_robot_description(r) for r in sim.spec.robots),
        controller_moving=tuple((_in_world(t.parent), _in_world(t.child)) for t in moved),
        anchors=anchors,
        anchor_values=anchor_values,
        source_topic="/" + source_topic.strip("/") if source_topic else "",
    )


def _sensor_frames(sim: Contract, tree) -> list:
    """Sites, camera image frames and sensors' own frame names (batchsim.model.frames.fixed_frames):
    every frame id a sensor's message names is in the world's tree."""
    suite = sim.sensors
    cameras = [(c.id, c.frame_id) for c in suite.cameras.values()]
    lidars = [(ld.site_id, ld.frame_id) for ld in suite.lidars.values() if ld.frame_id != ld.site]
    return fixed_frames(sim.spec.mjmodel, tree, cameras, lidars)


def _in_world(frame_id: str) -> str:
    """A controller's frame id (`{ns}/amr_2/odom`) as TfSpec names frames (`amr_2/odom`)."""
    return frame_id.removeprefix("{ns}/")


def controller_frames(
    sim: Contract, root: str, frames: set[str], transforms: Sequence[Transform]
) -> tuple[list[Transform], tuple[tuple[str, str], ...], np.ndarray]:
    """Which controller transforms tf carries, and the anchors their parents hang from.

    A transform whose child is a frame of the tree already (a diff drive's base_frame_id
    naming the robot's base body, which the simulation's ground truth moves) is left out
    with a warning: a frame has one parent in tf. A parent that is no frame of the tree
    (`amr_2/odom`) is anchored to the world's root where the robot's floating base stands
    now (its start pose in each world: x, y and yaw, at the height it was placed at), or at
    the root itself for a robot without one."""
    moved: list[Transform] = []
    children: set[str] = set()
    for t in transforms:
        parent, child = _in_world(t.parent), _in_world(t.child)
        if "{ns}" in parent or "{ns}" in child:
            log.warning("batchsim: tf: %s -> %s: a frame id with {ns} inside it: not put on tf", t.parent, t.child)
        elif child in frames or child in children:
            log.warning(
                "batchsim: tf: %s -> %s is left out: %s has a parent in tf already (the simulation's "
                "ground truth moves the robot's bodies): give the controller's child frame "
                "(base_frame_id) a name of its own, e.g. base_link",
                parent, child, child,
            )  # fmt: skip
        else:
            moved.append(t)
            children.add(child)
    anchored = sorted({_in_world(t.parent) for t in moved} - frames - children)
    bases = {b.joint: k for k, b in enumerate(sim.spec.floating_bases)}
    values = np.zeros((sim.nworld, len(anchored), 7))
    values[..., 6] = 1.0  # identity
    for k, frame_name in enumerate(anchored):
        robot = next((r for r in sim.spec.robots if frame_name.startswith(r.prefix)), None)
        base = robot.floating_base if robot is not None else sim.spec.floating_base
        if base is not None and base.joint in bases:  # level, on the ground the robot was placed on
            state = sim.base_states[:, bases[base.joint]]
            w, x, y, z = state[:, 3], state[:, 4], state[:, 5], state[:, 6]
            yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
            values[:, k, :2] = state[:, :2]
            values[:, k, 2] = robot.pose[2] if robot is not None else 0.0
            values[:, k, 5], values[:, k, 6] = np.sin(yaw / 2), np.cos(yaw / 2)
    return moved, tuple((root, a) for a in anchored), values


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




def _description(sim: Contract, tree, source: str | None, fixed: set[str]) -> tuple[str, list]:
    """The user's URDF if each of its links is a frame of the tree (a body, or one of `fixed`:
    a site, a camera frame) or hangs from one by fixed joints (placed as the URDF places it),
    so RViz finds a transform for each; else the one generated from the MJCF (with a warning
    saying why). With it, the frames tf_static adds for it: the URDF's placed links, or the
    generated one's links that are no body (Urdf.extra_frames)."""
    if source is not None:
        text = robot_description(sim.spec, source)
        urdf = ET.fromstring(text)
        links = {link.get("name") for link in urdf.iter("link")}
        placed = fixed_links(urdf, {tree.root, *tree.names, *fixed})
        unknown = sorted(links - set(tree.names) - {tree.root} - fixed - {link for _, link, _, _ in placed})
        if not unknown:
            return text, placed
        more = f" and {len(unknown) - 3} more" if len(unknown) > 3 else ""
        log.warning(
            "batchsim: robot_description: the links %s%s of %s are no bodies or sites of the MJCF, nor fixed to "
            "one (tf's frames are their names): publishing the URDF generated from the MJCF instead",
            ", ".join(unknown[:3]), more, str(source).split()[0],
        )
    urdf = generate_urdf(sim.spec)
    for line in urdf.warnings:
        log.warning("batchsim: robot_description: %s", line)
    return urdf.text, urdf.extra_frames
