"""What read() shows: the host arrays it fills, how they are laid out, and what a frozen world
shows instead (the contract's part `Readings`).

One block per fleet, `BatchedSystem.readings` `(nworld, ncolumn)`, in this order:

- the state interfaces (`RobotSpec.state`);
- each floating base's 7 qpos and 6 qvel entries (`base_columns`; none without a base);
- mujoco_ros2_control's actuator states: position, velocity and effort of each joint on
  `RobotSpec.actuator_joints` that has an address (`actuator_columns`), those not already
  among the columns above (`layout`): a motor on a joint reads what the joint's own state
  interfaces read, and read() moves each value once (on a GPU, 63 of a humanoid's 140
  float64 columns a world came down twice);
- the joint positions and velocities the PIDs measure (`Actuation.feedback_columns`).

After each gather, `Finish` negates the columns read negated and maps transmissions' joints.

A world that fails (diverges, or overflows a buffer that cannot grow) is frozen, by one rule on
every backend: until a reset lists it, it reads the noise-free values read() would have shown
just before the step() call in which it failed (state, base_state, sensordata, time).
"""

from __future__ import annotations

import numpy as np

from batchsim.model import RobotSpec, StateColumn
from batchsim.parts.transmissions import StateMap
from batchsim.types import SensorData, StateSource, StepFailures, as_slice


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


class Readings:
    """The host arrays read() fills and the views users see of them, for `nworld` worlds of `spec`.

    Attributes:
      columns: (ncolumn,) what each column of `array` is (`layout`).
      array: (nworld, ncolumn) float64, every column read() fills, in one block.
      state: (nworld, nstate) float64, the state interfaces: the first columns of `array`.
      base_state: (nworld, 13) float64, the floating base (`spec.floating_base`): position (3)
        and orientation quaternion (w, x, y, z) in the world frame, linear velocity (3) in the
        world frame, angular velocity (3) in the body frame; None without a floating base.
      base_states: (nworld, nbase, 13) float64, every floating base so (`spec.floating_bases`).
      feedback: (nworld, nfeedback) float64, the joint values the PIDs measure (the last columns).
      sensordata: SensorData over `sensor_array` (nworld, nsensordata) float64, per sensor.
      time: (nworld,) float64.
      actuator_columns: where `BatchedSystem.actuator_states`' columns are in `array`.
    """

    def __init__(self, spec: RobotSpec, nworld: int, feedback: list[StateColumn]):
        self.spec = spec
        self.columns, self.actuator_columns = layout(spec, feedback)
        self._nfeedback = len(feedback)
        self.finish = Finish(spec, self.columns)
        self.bind(np.zeros((nworld, len(self.columns))), np.zeros((nworld, spec.mjmodel.nsensordata)), np.zeros(nworld))
        # what frozen worlds show until reset: their readings from the start of the failing step()
        self._held = (np.zeros_like(self.array), np.zeros_like(self.sensor_array), np.zeros_like(self.time))
        # whether the host arrays hold the engine's current values (a read since the last step)
        self.current = False

    def bind(self, readings: np.ndarray, sensordata: np.ndarray, time: np.ndarray) -> None:
        """Make these the arrays read() fills; every view follows them."""
        nstate, nbase = len(self.spec.state), 13 * len(self.spec.floating_bases)
        self.array = readings
        self.state = readings[:, :nstate]
        self.base_state = readings[:, nstate : nstate + 13] if self.spec.floating_base is not None else None
        self.base_states = readings[:, nstate : nstate + nbase].reshape(len(readings), -1, 13)
        self.feedback = readings[:, readings.shape[1] - self._nfeedback :]
        self.sensor_array = sensordata
        self.sensordata = SensorData(sensordata, self.spec.sensors)
        self.time = time

    def hold(self, failures: StepFailures) -> None:
        """Keep what the failed worlds read before the failing step, to show until they are reset."""
        if not failures.finished:
            self.finish(failures.readings)  # an engine gather, raw as read()'s is
        for held, value in zip(self._held, (failures.readings, failures.sensordata, failures.time), strict=True):
            held[failures.worlds] = value

    def show_held(self, frozen: np.ndarray) -> None:
        """Frozen worlds' rows (`frozen` (nworld,) bool) of the host arrays: what they hold."""
        if frozen.any():
            for shown, held in zip((self.array, self.sensor_array, self.time), self._held, strict=True):
                shown[frozen] = held[frozen]
