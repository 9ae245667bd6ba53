"""What a worker hands the loop through its ring: trajectory batches and service requests,
as flat records. No rclpy here.

A trajectory record is a whole TrajectoryBatch (every trajectory a worker received since
its last record), so the loop reads NumPy views of it, one record per worker and flush,
never one Python object per world. A service request carries a ticket; the loop writes
the last ticket it carried out back to shared memory, and the worker answers then.
"""

from __future__ import annotations

import enum
import json
import struct
from typing import Any

import numpy as np

from batchsim.controllers.topics import TrajectoryBatch
from batchsim.memory import Memory


class Kind(enum.IntEnum):
    """Record kinds in a worker's ring (0 is the ring's padding)."""

    TRAJECTORY = 1
    RESET = 2
    PAUSE = 3
    STEP = 4
    SWITCH = 5  # controller_manager's switch_controller in one world
    CANCEL = 6  # an action goal canceled (ros_bridge/action_plan.py)
    GRIPPER_GOAL = 7  # a GripperCommand goal (ros_bridge/action_plan.py)
    STEP_N = 8  # mujoco_ros2_control's step_simulation: N physics steps, aborted by a resume
    RESET_WORLD = 9  # mujoco_ros2_control's reset_world: a keyframe, joint and free-joint overrides
    SET_FREE_JOINTS = 10  # mujoco_ros2_control's set_free_joint_state
    APPLY_WRENCH = 11  # the ExternalWrenchPlugin's apply_wrench: answered at once, marked done when run
    RESET_ROBOT = 12  # `<ns>/<robot>/reset`: one robot of a world of several back at its start
    SET_PARAMETERS = 13  # a controller node's set_parameters in one world (a document: controller, values)


_TRAJ = struct.Struct("<iiiiiiii")  # input, trajectories, points, joints, has velocities, accelerations, goals, 0
_TICKET = struct.Struct("<qq")  # ticket, argument


def _pad8(n: int) -> int:
    return -(-n // 8) * 8


def encode_trajectories(input_index: int, batch: TrajectoryBatch) -> bytes:
    """One record holding a whole batch."""
    n, nj = batch.joint_mask.shape
    npoint = int(batch.offsets[-1])
    has_v = batch.velocities is not None
    has_a = batch.accelerations is not None
    has_g = batch.goals is not None
    parts = [
        _TRAJ.pack(input_index, n, npoint, nj, int(has_v), int(has_a), int(has_g), 0),
        np.asarray(batch.worlds, np.int64).tobytes(),
        np.asarray(batch.start_time, np.float64).tobytes(),
        np.asarray(batch.offsets, np.int64).tobytes(),
        np.asarray(batch.times, np.float64).tobytes(),
        np.ascontiguousarray(batch.positions, np.float64).tobytes(),
    ]
    flags = np.zeros((3, n), np.uint8)
    flags[1] = batch.has_velocities if batch.has_velocities is not None else False
    flags[2] = batch.has_accelerations if batch.has_accelerations is not None else False
    mask = np.asarray(batch.joint_mask, np.uint8).tobytes()
    parts.append(mask + bytes(_pad8(len(mask)) - len(mask)))
    flag_bytes = flags[1:].tobytes()
    parts.append(flag_bytes + bytes(_pad8(len(flag_bytes)) - len(flag_bytes)))
    if has_v:
        parts.append(np.ascontiguousarray(batch.velocities, np.float64).tobytes())
    if has_a:
        parts.append(np.ascontiguousarray(batch.accelerations, np.float64).tobytes())
    if has_g:  # FollowJointTrajectory goals: their tags and tolerances
        path, goal, goal_time = _tolerances(batch)
        parts += [np.asarray(batch.goals, np.int64).tobytes(), path.tobytes(), goal.tobytes(), goal_time.tobytes()]
    head = parts[0]
    return head + bytes(_pad8(len(head)) - len(head)) + b"".join(parts[1:])


def decode_trajectories(payload: np.ndarray) -> tuple[int, TrajectoryBatch]:
    """(input index, the batch) of a TRAJECTORY record's payload (views of it)."""
    index, n, npoint, nj, has_v, has_a, has_g, _ = _TRAJ.unpack_from(payload, 0)
    at = _pad8(_TRAJ.size)

    def take(count: int, dtype: str, pad: bool = False) -> np.ndarray:
        nonlocal at
        size = count * np.dtype(dtype).itemsize
        out = payload[at : at + size].view(dtype)
        at += _pad8(size) if pad else size
        return out

    worlds = take(n, "i8")
    start = take(n, "f8")
    offsets = take(n + 1, "i8")
    times = take(npoint, "f8")
    positions = take(npoint * nj, "f8").reshape(npoint, nj)
    mask = take(n * nj, "u1", pad=True).reshape(n, nj).astype(bool)
    flags = take(2 * n, "u1", pad=True).reshape(2, n).astype(bool)
    velocities = take(npoint * nj, "f8").reshape(npoint, nj) if has_v else None
    accelerations = take(npoint * nj, "f8").reshape(npoint, nj) if has_a else None
    goals = take(n, "i8") if has_g else None
    path = take(n * nj * 3, "f8").reshape(n, nj, 3) if has_g else None
    goal = take(n * nj * 3, "f8").reshape(n, nj, 3) if has_g else None
    goal_time = take(n, "f8") if has_g else None
    batch = TrajectoryBatch(
        worlds=worlds,
        start_time=start,
        joint_mask=mask,
        offsets=offsets,
        times=times,
        positions=positions,
        velocities=velocities,
        has_velocities=flags[0],
        accelerations=accelerations,
        has_accelerations=flags[1],
        goals=goals,
        path_tolerance=path,
        goal_tolerance=goal,
        goal_time_tolerance=goal_time,
    )
    return index, batch


def _tolerances(batch: TrajectoryBatch) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A batch's (path, goal, goal time) tolerances, the defaults (0) where it has none."""
    n, nj = batch.joint_mask.shape

    def per_joint(value: np.ndarray | None) -> np.ndarray:
        return np.zeros((n, nj, 3)) if value is None else np.ascontiguousarray(value, np.float64).reshape(n, nj, 3)

    goal_time = np.zeros(n) if batch.goal_time_tolerance is None else np.asarray(batch.goal_time_tolerance, np.float64)
    return per_joint(batch.path_tolerance), per_joint(batch.goal_tolerance), np.ascontiguousarray(goal_time)


def concatenate(batches: list[TrajectoryBatch]) -> TrajectoryBatch:
    """One batch of several, in order (a later trajectory for a world replaces an earlier one)."""
    if len(batches) == 1:
        return batches[0]
    offsets = [np.zeros(1, np.int64)]
    base = 0
    for b in batches:
        offsets.append(np.asarray(b.offsets[1:], np.int64) + base)
        base += int(b.offsets[-1])
    npoint, nj = base, batches[0].joint_mask.shape[1]

    def points(attr: str) -> np.ndarray | None:
        if all(getattr(b, attr) is None for b in batches):
            return None
        out = np.full((npoint, nj), np.nan)
        at = 0
        for b in batches:
            size = int(b.offsets[-1])
            if getattr(b, attr) is not None:
                out[at : at + size] = getattr(b, attr)
            at += size
        return out

    def flags(attr: str) -> np.ndarray:
        return np.concatenate(
            [getattr(b, attr) if getattr(b, attr) is not None else np.zeros(len(b), bool) for b in batches]
        )

    goals: dict[str, np.ndarray | None] = {}
    if any(b.goals is not None for b in batches):
        parts = [_tolerances(b) for b in batches]
        goals = {
            "goals": np.concatenate([b.goals if b.goals is not None else np.zeros(len(b), np.int64) for b in batches]),
            "path_tolerance": np.concatenate([p[0] for p in parts]),
            "goal_tolerance": np.concatenate([p[1] for p in parts]),
            "goal_time_tolerance": np.concatenate([p[2] for p in parts]),
        }
    return TrajectoryBatch(
        **goals,
        worlds=np.concatenate([b.worlds for b in batches]),
        start_time=np.concatenate([b.start_time for b in batches]),
        joint_mask=np.concatenate([b.joint_mask for b in batches]),
        offsets=np.concatenate(offsets),
        times=np.concatenate([b.times for b in batches]),
        positions=np.concatenate([b.positions for b in batches]),
        velocities=points("velocities"),
        has_velocities=flags("has_velocities"),
        accelerations=points("accelerations"),
        has_accelerations=flags("has_accelerations"),
    )


def encode_reset(ticket: int, worlds: list[int] | None) -> bytes:
    """Reset the listed worlds (local indices), or every world (None)."""
    if worlds is None:
        return _TICKET.pack(ticket, -1)
    return _TICKET.pack(ticket, len(worlds)) + np.asarray(worlds, np.int64).tobytes()


def encode_ticket(ticket: int, argument: int = 0) -> bytes:
    """A PAUSE (argument 1: pause, 0: run) or STEP request."""
    return _TICKET.pack(ticket, argument)


def decode_ticket(payload: np.ndarray) -> tuple[int, int]:
    return _TICKET.unpack_from(payload, 0)


def decode_reset(payload: np.ndarray) -> tuple[int, np.ndarray | None]:
    """(ticket, the worlds to reset or None for all)."""
    ticket, n = _TICKET.unpack_from(payload, 0)
    if n < 0:
        return ticket, None
    return ticket, payload[_TICKET.size : _TICKET.size + 8 * n].view(np.int64).copy()


_SWITCH = struct.Struct("<qqii")  # ticket, world, strictness, activate_asap


def encode_switch(ticket: int, world: int, activate: list[str], deactivate: list[str], strictness: int, asap: bool) -> bytes:
    """switch_controller in one world (a local index)."""
    names = json.dumps([list(activate), list(deactivate)]).encode()
    return _SWITCH.pack(ticket, world, strictness, int(asap)) + names


def decode_switch(payload: np.ndarray) -> tuple[int, int, list[str], list[str], int, bool]:
    """(ticket, world, activate, deactivate, strictness, activate_asap)."""
    ticket, world, strictness, asap = _SWITCH.unpack_from(payload, 0)
    activate, deactivate = _json(payload[_SWITCH.size :])
    return ticket, world, activate, deactivate, strictness, bool(asap)


def _json(payload: np.ndarray) -> Any:
    """The JSON document at the start of a record's payload: what follows it (the record's padding
    to 8 bytes) is not read (raw_decode), whatever it holds."""
    return json.JSONDecoder().raw_decode(payload.tobytes().decode(errors="replace"))[0]


_DOC = struct.Struct("<qq")  # ticket, world (-1: every world)


def encode_document(ticket: int, world: int, document: dict) -> bytes:
    """A request whose arguments are a small JSON document (RESET_WORLD, SET_FREE_JOINTS, APPLY_WRENCH,
    RESET_ROBOT: {"robot": its index among the world's robots}, SET_PARAMETERS: {"controller": its
    name in the world, "values": {key: value}})."""
    return _DOC.pack(ticket, world) + json.dumps(document).encode()


def decode_document(payload: np.ndarray) -> tuple[int, int, dict]:
    """(ticket, world or -1, the document)."""
    ticket, world = _DOC.unpack_from(payload, 0)
    return ticket, world, _json(payload[_DOC.size :])


# An apply_wrench request is answered like any other (accepted, or why not) as soon as the loop
# takes it, and marked done once its wrenches have run: the host writes its ticket into the
# worker's slot ticket % WRENCH_SLOTS of `wrench.done`, never lowering it (a later ticket sharing
# the slot may land first); the worker's service answers when the slot holds its ticket or more.
WRENCH_SLOTS = 1024  # per worker: a request's slot is reused only WRENCH_SLOTS tickets later


def wrench_arrays(nworker: int) -> list[tuple[str, tuple[int, ...], str]]:
    """The shared arrays of the done marks (plan.py adds them where the plugin runs)."""
    return [("wrench.done", (nworker, WRENCH_SLOTS), "i8")]


def mark_wrench_done(memory: Memory, worker: int, ticket: int) -> None:
    """The host: worker `worker`'s apply_wrench request `ticket` has run."""
    done = memory["wrench.done"][worker]
    done[ticket % WRENCH_SLOTS] = max(int(done[ticket % WRENCH_SLOTS]), ticket)


def wrench_done(memory: Memory, worker: int, ticket: int) -> bool:
    """The worker: whether the host marked its request `ticket` done."""
    return int(memory["wrench.done"][worker, ticket % WRENCH_SLOTS]) >= ticket


def trajectory_bytes(points: int, joints: int) -> int:
    """The ring record of one trajectory of `points` points (positions, velocities and
    accelerations of every joint, times), with its batch's fixed parts and tolerances."""
    return points * (3 * joints + 1) * 8 + (6 * joints + 64) * 8 + 4096
