"""What read() gathers beyond the state interfaces, and how it is laid out.

One block per fleet, `BatchedSystem.readings` `(nworld, ncolumn)`, in this order:

- the state interfaces (`RobotSpec.state`);
- each floating base's 7 qpos and 6 qvel entries (`base_columns`; none without a base);
- mujoco_ros2_control's actuator states: position, velocity and effort of each joint on
  `RobotSpec.actuator_joints` that has an address (`actuator_columns`), those not already
  among the columns above (`layout`): a motor on a joint reads what the joint's own state
  interfaces read, and read() moves each value once (on a GPU, 63 of a humanoid's 140
  float64 columns a world came down twice);
- the joint positions and velocities the PIDs measure (`Actuation.feedback_columns`).

After each gather, `finish` negates the columns read negated and maps transmissions' joints.
"""

from __future__ import annotations

import numpy as np

from batchsim.model import RobotSpec, StateColumn
from batchsim.transmissions import StateMap
from batchsim.types import StateSource


def base_columns(spec: RobotSpec) -> list[StateColumn]:
    """Each floating base's 7 qpos and 6 qvel entries as read columns, 13 a base (none
    without one; a fleet's world: each robot's that has one, `spec.floating_bases`)."""
    out = []
    for base in spec.floating_bases:
        out += [StateColumn(f"{base.joint}/qpos{k}", StateSource.QPOS, base.qposadr + k) for k in range(7)]
        out += [StateColumn(f"{base.joint}/qvel{k}", StateSource.QVEL, base.dofadr + k) for k in range(6)]
    return out


def actuator_columns(spec: RobotSpec) -> list[StateColumn]:
    """Position, velocity, effort (qfrc_actuator) of each actuator joint with an address,
    as blocks of positions, then velocities, then efforts."""
    found = [(name, q, v) for name, q, v in spec.actuator_joints if q >= 0]
    return (
        [StateColumn(f"{n}/actuator_position", StateSource.QPOS, q) for n, q, _ in found]
        + [StateColumn(f"{n}/actuator_velocity", StateSource.QVEL, v) for n, _, v in found]
        + [StateColumn(f"{n}/actuator_effort", StateSource.QFRC_ACTUATOR, v) for n, _, v in found]
    )


def layout(spec: RobotSpec, feedback: list[StateColumn]) -> tuple[list[StateColumn], slice | np.ndarray]:
    """read()'s columns (state, base, the actuator states not read already, `feedback`), and
    where `BatchedSystem.actuator_states`' columns are among them (a slice where it can be).

    An actuator state is read already where an earlier column has its source, index and sign
    and nothing changes that column after the gather: not a transmission's joint, whose state
    interfaces are mapped to the joint side, where mujoco_ros2_control's actuator states stay.
    """
    mapped = {joint for t in spec.transmissions for joint in t.joints}
    columns = list(spec.state) + base_columns(spec)
    read: dict[tuple[StateSource, int, float], int] = {}
    for k, c in enumerate(columns):
        if c.name.rsplit("/", 1)[0] not in mapped:
            read.setdefault((c.source, c.index, c.sign), k)
    where = []
    for c in actuator_columns(spec):
        k = read.get((c.source, c.index, c.sign))
        if k is None:
            k = len(columns)
            columns.append(c)
        where.append(k)
    return columns + list(feedback), as_slice(where)


def actuator_state_index(spec: RobotSpec) -> np.ndarray:
    """(3 * n,) per kind (position, velocity, effort) and entry of `spec.actuator_joints`,
    its column in `BatchedSystem.actuator_states`, or -1 for an entry with no address."""
    found = np.array([q >= 0 for _, q, _ in spec.actuator_joints], dtype=bool)
    rank = np.cumsum(found) - 1
    nfound = int(found.sum())
    return np.concatenate([np.where(found, k * nfound + rank, -1) for k in range(3)]).astype(np.intp)


def as_slice(index: list[int]) -> slice | np.ndarray:
    """An index list as a slice when it is an arithmetic progression (a view, not a gather)."""
    if not index:
        return np.array(index, dtype=np.intp)
    step = index[1] - index[0] if len(index) > 1 else 1
    if step > 0 and all(b - a == step for a, b in zip(index, index[1:], strict=False)):
        return slice(index[0], index[-1] + 1, step)
    return np.array(index, dtype=np.intp)


class Finish:
    """What every gather from the engine needs before it is shown: signs, then transmissions."""

    def __init__(self, spec: RobotSpec, columns: list[StateColumn]):
        self._negated = np.array([i for i, c in enumerate(columns) if c.sign < 0], dtype=np.intp)
        self._transmissions = StateMap(spec, columns)

    def __call__(self, readings: np.ndarray) -> None:
        if self._negated.size:
            readings[:, self._negated] *= -1.0
        if self._transmissions:
            self._transmissions.apply(readings)
