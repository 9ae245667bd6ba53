"""A "real" bag made honestly without a real robot: batchsim runs the robot with hidden
parameter changes (a `randomize:` block whose draws are fixed values), drives it through its
controllers with seeded commands, and writes what `ros2 bag record` would have: a rosbag2 MCAP
with `<ns>/joint_states` (sensor_msgs/JointState) and the command topic (a JointTrajectory for
a joint_trajectory_controller, else a Float64MultiArray for a forward command controller).

    write_bag("real.mcap", "arm", HIDDEN_ARM, seconds=6.0, seed=1)

The calibration is told none of it: it gets the file, the model, the controllers and ranges.
Stamps are a robot's clock (`stamp0` + sim time), log times the recorder's, `latency` later.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from batchsim.calibration.bag import JOINT_STATE
from batchsim.calibration.replay import controller_inputs
from batchsim.controllers.topics import Input, MessageKind, trajectory_batch
from batchsim.loop import Participant, SimLoop

#: the hidden changes of the shipped arm the test and the benchmark recover (factors of nominal)
HIDDEN_ARM: dict[str, Any] = {
    "fields": [
        {"field": "body_mass", "names": ["link2"], "also": ["body_inertia"], "scale": {"uniform": [1.3, 1.3]}},
        {"field": "body_mass", "names": ["link3"], "also": ["body_inertia"], "scale": {"uniform": [0.75, 0.75]}},
        {"field": "dof_damping", "names": ["joint2"], "scale": {"uniform": [2.5, 2.5]}},
        {"field": "actuator_kp", "names": ["joint1"], "scale": {"uniform": [0.8, 0.8]}},
    ]
}
#: the ranges the calibration searches for them (it is told these, not the values)
RANGES_ARM: dict[str, Any] = {
    "seed": 0,
    "fields": [
        {"field": "body_mass", "names": ["link2", "link3"], "also": ["body_inertia"], "scale": {"uniform": [0.5, 1.5]}},
        {"field": "dof_damping", "names": ["joint2"], "scale": {"uniform": [0.5, 4.0]}},
        {"field": "actuator_kp", "names": ["joint1"], "scale": {"uniform": [0.6, 1.4]}},
    ],
}
#: the hidden values as the calibration's --json names them: field -> object -> factor
HIDDEN_ARM_FITTED = {
    "body_mass": {"link2": 1.3, "link3": 0.75},
    "dof_damping": {"joint2": 2.5},
    "actuator_kp": {"joint1": 0.8},
}

_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
_SCHEMAS = {
    JOINT_STATE: "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n",
    MessageKind.FLOAT64_MULTI_ARRAY.value: "MultiArrayLayout layout\nfloat64[] data\n",
    MessageKind.JOINT_TRAJECTORY.value: "std_msgs/Header header\nstring[] joint_names\nJointTrajectoryPoint[] points\n",
}
_DEPENDENCIES = {
    JOINT_STATE: [("std_msgs/msg/Header", _HEADER), ("builtin_interfaces/msg/Time", _TIME)],
    MessageKind.FLOAT64_MULTI_ARRAY.value: [
        ("std_msgs/msg/MultiArrayLayout", "MultiArrayDimension[] dim\nuint32 data_offset\n"),
        ("std_msgs/msg/MultiArrayDimension", "string label\nuint32 size\nuint32 stride\n"),
    ],
    MessageKind.JOINT_TRAJECTORY.value: [
        ("std_msgs/msg/Header", _HEADER),
        ("builtin_interfaces/msg/Time", _TIME),
        (
            "trajectory_msgs/msg/JointTrajectoryPoint",
            "float64[] positions\nfloat64[] velocities\nfloat64[] accelerations\nfloat64[] effort\n"
            "builtin_interfaces/Duration time_from_start\n",
        ),
        ("builtin_interfaces/msg/Duration", _TIME),
    ],
}


def schema_text(type_name: str) -> str:
    """The ros2msg definition rosbag2 stores for one of the three types written here."""
    parts = [_SCHEMAS[type_name].rstrip("\n")]
    parts += [f"{'=' * 80}\nMSG: {name}\n{text.rstrip()}" for name, text in _DEPENDENCIES[type_name]]
    return "\n".join(parts) + "\n"


def _time(seconds: float, base: float = 0.0) -> dict[str, int]:
    ns = int(round(base * 1e9)) + int(round(seconds * 1e9))  # base apart: a float64 of 1.7e9 s keeps 0.2 us
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def motions(joints: int, seconds: float, seed: int, every: float = 1.5, reach: float = 0.9) -> list[tuple[float, np.ndarray]]:
    """Seeded targets (time, (joints,) rad) every `every` s: within +-reach of zero, the wrist
    joints at half of it."""
    rng = np.random.default_rng(seed)
    scale = np.where(np.arange(joints) < 3, reach, 0.5 * reach)
    return [(t, scale * rng.uniform(-1.0, 1.0, joints)) for t in np.arange(0.0, seconds - 0.5, every)]


class _Driver(Participant):
    """Hands each target to the controller when due and records the joint states, as a real
    robot's recorder sees both."""

    def __init__(self, inp: Input, joints: list[str], state_names: list[str], targets: list[tuple[float, np.ndarray]], every: float):
        self.inp, self.joints, self.targets, self.every = inp, joints, list(targets), every
        self._pos = [state_names.index(f"{j}/position") for j in joints]
        self._vel = [state_names.index(f"{j}/velocity") for j in joints]
        self._eff = [state_names.index(f"{j}/effort") if f"{j}/effort" in state_names else None for j in joints]
        self.states: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []
        self.sent: list[tuple[float, Any]] = []

    def update(self, sim: Any, time: float, period: float) -> None:
        row = sim.state[0]
        effort = np.array([row[c] if c is not None else np.nan for c in self._eff])
        self.states.append((time, row[self._pos].copy(), row[self._vel].copy(), effort))
        while self.targets and self.targets[0][0] <= time + 1e-9:
            _, target = self.targets.pop(0)
            if self.inp.kind is MessageKind.JOINT_TRAJECTORY:
                # through a midpoint at rest-to-rest pace: a move of `every` s, like a planner's
                start = self.states[-1][1]
                times = np.array([0.4 * self.every, 0.8 * self.every])
                positions = np.stack([0.5 * (start + target), target])
                batch, _, bad = trajectory_batch(self.inp.joints, [(0, self.joints, times, positions, None, None, 0.0)])
                rejected = bad or self.inp.apply(batch)
                self.sent.append((time, (times, positions)))
            else:
                rejected = self.inp.apply(np.zeros(1, np.int64), target[None, :])
                self.sent.append((time, target))
            if rejected:
                raise ValueError(f"the synthetic command was refused: {rejected[0][1]}")


def write_bag(
    path: str | Path,
    model: str | Path,
    hidden: Mapping[str, Any] | None,
    *,
    controllers: str | Path | Mapping[str, Any] | None = None,
    seconds: float = 6.0,
    seed: int = 1,
    noise: float = 2e-4,
    namespace: str = "",
    stamp0: float = 1_700_000_000.0,
    latency: float = 0.0005,
    joint_names: list[str] | None = None,
    commands: bool = True,
) -> Path:
    """Run one world of `model` with the `hidden` changes (a randomize block) for `seconds`
    under `controllers` (default: the model's own), command it with seeded targets on the first
    controller that takes a trajectory or a Float64MultiArray, and write the rosbag2 MCAP.

    `noise`: the joint positions' measurement noise (rad, Gaussian, seeded); `joint_names`
    renames the joints in joint_states (a bag of another robot, for tests); `commands=False`
    leaves the command topic out (likewise)."""
    from mcap_ros2.writer import Writer

    import batchsim
    from batchsim.controllers import default_controllers, load_controllers

    sim = batchsim.make(model, 1, "cpu", randomize=dict(hidden) if hidden else None)
    sim.configure()
    sim.activate()
    source = controllers if controllers is not None else default_controllers(str(model))
    if source is None:
        raise ValueError(f"{model}: no default controllers; give controllers=")
    manager = load_controllers(source, sim.spec, 1)
    inputs = controller_inputs(manager)
    if not inputs:
        raise ValueError(f"{source}: no controller takes a trajectory or a Float64MultiArray")
    topic, inp = next(iter(inputs.items()))
    joints = list(inp.joints) if inp.joints else [j.name for j in sim.spec.joints][: inp.width]
    every = 1.5 if inp.kind is MessageKind.JOINT_TRAJECTORY else 0.75
    driver = _Driver(inp, joints, list(sim.export_state_interfaces()), motions(len(joints), seconds, seed, every), every)
    loop = SimLoop(sim, control_rate=manager.update_rate, rtf=0, participants=[driver, manager])
    for _ in range(round(seconds / loop.period) + 1):
        loop.run_period()
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    names = joint_names or joints
    rng = np.random.default_rng([seed, 7])
    path = Path(path)
    with path.open("wb") as f:
        writer = Writer(f)
        schemas = {t: writer.register_msgdef(t, schema_text(t)) for t in _SCHEMAS}
        messages: list[tuple[float, str, str, dict[str, Any]]] = []
        for time, pos, vel, eff in driver.states:
            measured = pos + noise * rng.standard_normal(len(pos))
            msg = {
                "header": {"stamp": _time(time, stamp0), "frame_id": ""},
                "name": names,
                "position": measured.tolist(),
                "velocity": vel.tolist(),
                "effort": [] if np.isnan(eff).any() else eff.tolist(),
            }
            messages.append((time, f"{ns}/joint_states", JOINT_STATE, msg))
        for time, sent in driver.sent if commands else []:
            if inp.kind is MessageKind.JOINT_TRAJECTORY:
                times, positions = sent
                points = [
                    {"positions": p.tolist(), "velocities": [], "accelerations": [], "effort": [], "time_from_start": _time(t)}
                    for t, p in zip(times, positions, strict=True)
                ]
                msg = {"header": {"stamp": _time(0.0), "frame_id": ""}, "joint_names": joints, "points": points}
            else:
                msg = {"layout": {"dim": [], "data_offset": 0}, "data": sent.tolist()}
            messages.append((time - 1e-6, f"{ns}/{topic}", inp.kind.value, msg))  # it arrived just before
        for time, name, kind, msg in sorted(messages, key=lambda m: m[0]):
            stamp = int(round(stamp0 * 1e9)) + int(round((time + latency) * 1e9))
            writer.write_message(name, schemas[kind], msg, log_time=stamp, publish_time=stamp)
        writer.finish()
    return path
