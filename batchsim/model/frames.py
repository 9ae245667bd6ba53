"""The tf tree of a model: one frame per body, and the parent->child transforms of every world.

    tree = frame_tree(spec)                          # or of a mujoco.MjModel
    xpos, xquat = sim.body_poses()                   # (n, nbody, 3), (n, nbody, 4) w, x, y, z
    t, r = relative_transforms(tree, xpos, xquat)    # (n, nframe, 3), (n, nframe, 4) x, y, z, w
    moving = ~tree.static                            # tf; the static ones once, on tf_static:
    t0, r0 = initial_transforms(tree, spec)          # (nframe, 3), (nframe, 4) x, y, z, w

Frame names are body names (an unnamed body is `body_<id>`). The world body is no frame of
its own: the bodies that hang from it hang from the tree's root frame, `odom` for a robot with
a floating base (REP 105: the simulation's world is the odometry frame, continuous, with no
jumps; `map -> odom` is a localization node's to publish) and `world` for a fixed-base robot.
A transform is static iff its child body has no joint and is not a mocap body; the joints of
the bodies above it move the parent and the child together.

Frames fixed to a body that are no body (`fixed_frames`): every named site, at its pose in its
body, so that a frame id naming a site (an IMU's, a lidar's, a pose broadcaster's `ee_link`) is
in the tree; a camera's image frame, in REP 103's optical convention (z forward, x right, y
down: MuJoCo's camera frame turned half a turn about x, as its images are rows top down); a
sensor's frame named apart from its site, at the site.

No rclpy here: the ROS bridge turns the arrays into tf2_msgs/TFMessage.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import mujoco
import numpy as np

from batchsim.model.interfaces import floating_base
from batchsim.model.spec import RobotSpec

ODOM = "odom"  # REP 105's frame for a floating base's pose
WORLD = "world"  # a fixed-base robot's root frame


@dataclasses.dataclass(frozen=True)
class FrameTree:
    """The tf frames of a model: one per body but the world body, in body order.

    Attributes:
      root: the frame the world body's children hang from: "odom" (floating base) or "world".
      names: (nframe,) the frames (child frames), body names or `body_<id>`.
      parents: (nframe,) each frame's parent frame: its parent body's frame, or `root`.
      body: (nframe,) int64, the body id of each frame (1..nbody-1).
      parent_body: (nframe,) int64, the parent body's id (0, the world body, for `root`).
      static: (nframe,) bool, whether parent->child never changes (the body has no joint and
        is not a mocap body).
    """

    root: str
    names: tuple[str, ...]
    parents: tuple[str, ...]
    body: np.ndarray
    parent_body: np.ndarray
    static: np.ndarray

    @property
    def nframe(self) -> int:
        return len(self.names)

    def frame(self, body: int) -> str:
        """The frame name of body id `body` (the root frame for the world body)."""
        return self.root if body == 0 else self.names[body - 1]


def body_frame_names(m: mujoco.MjModel) -> list[str]:
    """Every body's frame name, world body included (index = body id)."""
    names = []
    for b in range(m.nbody):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)
        names.append(name if name else f"body_{b}")
    return names


def frame_tree(model: RobotSpec | mujoco.MjModel) -> FrameTree:
    """The frame tree of a RobotSpec (its `floating_base` decides the root) or of an MjModel."""
    if isinstance(model, RobotSpec):
        m, base = model.mjmodel, model.floating_base
    else:
        m, base = model, floating_base(model)
    root = ODOM if base is not None else WORLD
    names = body_frame_names(m)
    taken = set(names[1:])
    if root in taken:
        raise ValueError(f"a body is named {root!r}, the name of the root frame: rename the body")
    if len(taken) < m.nbody - 1:
        raise ValueError("two bodies share a frame name; tf needs one name per frame")
    body = np.arange(1, m.nbody, dtype=np.int64)
    parent_body = m.body_parentid[1:].astype(np.int64)
    static = (m.body_jntnum[1:] == 0) & (m.body_mocapid[1:] < 0)
    parents = tuple(root if p == 0 else names[p] for p in parent_body)
    return FrameTree(root, tuple(names[1:]), parents, body, parent_body, static)


def relative_transforms(
    tree: FrameTree, xpos: np.ndarray, xquat: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Parent->child transforms of every frame from world-frame body poses, all worlds at once.

    Args:
      tree: the model's frames.
      xpos: (..., nbody, 3) body positions in the world frame (BatchedSystem.body_poses).
      xquat: (..., nbody, 4) body orientations, MuJoCo's order (w, x, y, z).

    Returns:
      translations (..., nframe, 3): the child's origin in the parent frame, and rotations
      (..., nframe, 4): the child's orientation in the parent frame, ROS order (x, y, z, w);
      float64, as tf2 takes them (geometry_msgs/Transform).
    """
    xpos, xquat = np.asarray(xpos, np.float64), np.asarray(xquat, np.float64)
    # component planes (..., nframe) of parent and child: explicit products, no np.cross or
    # stacking temporaries (4096 worlds' tf each period is the bridge's largest fill)
    pw, px, py, pz = (xquat[..., tree.parent_body, k] for k in range(4))
    cw, cx, cy, cz = (xquat[..., tree.body, k] for k in range(4))
    d = xpos[..., tree.body, :] - xpos[..., tree.parent_body, :]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    translation = np.empty(d.shape)
    rotation = np.empty(d.shape[:-1] + (4,))
    # the parent's inverse rotation (conjugate: w, -x, -y, -z) applied to d: d + 2 u x (u x d + w d)
    ux, uy, uz = -px, -py, -pz
    tx = uy * dz - uz * dy + pw * dx
    ty = uz * dx - ux * dz + pw * dy
    tz = ux * dy - uy * dx + pw * dz
    translation[..., 0] = dx + 2.0 * (uy * tz - uz * ty)
    translation[..., 1] = dy + 2.0 * (uz * tx - ux * tz)
    translation[..., 2] = dz + 2.0 * (ux * ty - uy * tx)
    # conj(parent) * child, written in ROS order (x, y, z, w)
    rotation[..., 3] = pw * cw + px * cx + py * cy + pz * cz
    rotation[..., 0] = pw * cx - px * cw - py * cz + pz * cy
    rotation[..., 1] = pw * cy + px * cz - py * cw - pz * cx
    rotation[..., 2] = pw * cz - px * cy + py * cx - pz * cw
    return translation, rotation


def initial_transforms(tree: FrameTree, model: RobotSpec | mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """Every frame's parent->child transform in the initial state (a spec's `initial`: its
    keyframe; a model's qpos0): translations (nframe, 3), rotations (nframe, 4) x, y, z, w.
    The static frames' (`tree.static`) hold in every state: publish them once, on tf_static."""
    m = model.mjmodel if isinstance(model, RobotSpec) else model
    d = mujoco.MjData(m)
    if isinstance(model, RobotSpec) and model.initial is not None:
        model.initial.apply(m, d)
    else:
        mujoco.mj_kinematics(m, d)
    return relative_transforms(tree, d.xpos, d.xquat)


OPTICAL = np.array([0.0, 1.0, 0.0, 0.0])  # w x y z: half a turn about x, MuJoCo camera -> optical frame


def fixed_frames(
    m: mujoco.MjModel,
    tree: FrameTree,
    cameras: Sequence[tuple[int, str]] = (),
    sensors: Sequence[tuple[int, str]] = (),
) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """The frames fixed to a body that are no frame of `tree` (see the module's docstring), as
    (the body's frame, the frame, position (3,), quaternion w x y z (4,)) in the body's frame.

    Args:
      cameras: (camera id, the frame id its images are stamped with): that frame, optical.
      sensors: (site id, the frame id a sensor is stamped with) where the frame is named apart
        from the site (a lidar's `frame_name`): that frame, at the site.
    A name given twice, or a frame of the tree already, is taken once (the first, the tree's).
    """
    taken = {tree.root, *tree.names}
    out = []

    def add(body: int, name: str, pos: np.ndarray, quat: np.ndarray) -> None:
        if name and name not in taken:
            taken.add(name)
            out.append((tree.frame(int(body)), name, np.array(pos, float), np.array(quat, float)))

    for s in range(m.nsite):
        add(m.site_bodyid[s], mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, s) or "", m.site_pos[s], m.site_quat[s])
    for c, frame in cameras:
        add(m.cam_bodyid[c], frame, m.cam_pos[c], _multiply(m.cam_quat[c], OPTICAL))
    for s, frame in sensors:
        add(m.site_bodyid[s], frame, m.site_pos[s], m.site_quat[s])
    return out


def _multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quaternion products a * b, (w, x, y, z), over any leading shape."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v rotated by the unit quaternions q (w, x, y, z): v + 2 u x (u x v + w v)."""
    w, u = q[..., :1], q[..., 1:]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)
