"""A recorded world re-run with its controllers (`batchsim resim --controllers`): not only the
physics from the recorded ctrl, but the world's ros2_control controllers again, from the messages
they took (`/batchsim/controller_inputs`: a command topic's rows, a trajectory or a goal's), on a
one-world cpu system of the robot, in a SimLoop as the fleet ran them. It says whether the
controllers' commands and the ctrl they make come out as recorded, and where they part: to debug
a controller rather than the physics.

A controller's own state is not in the file, so a world is re-run from its fresh starts only (the
run's first period, a reset), not from a recording begun mid-run. The interfaces no active
controller claims take the recorded command (the bridge's plain commands); the plugins' inputs
are not re-run here (the physics-only re-run takes them).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from batchsim.controllers.topics import MessageKind, TrajectoryBatch
from batchsim.loop import Participant, SimLoop
from batchsim.resim.physics import Trajectory
from batchsim.resim.recorded import Recorded, ResimError, WorldRecord


@dataclasses.dataclass
class ControllerComparison:
    """The re-run controllers against the recording, in one world.

    Attributes:
      periods: periods re-run. exact: every command and ctrl value equal to the bit.
      first_command: where the controllers' commands first part: (sim time, period, interface,
        |difference|), or None. first_ctrl: where the ctrl first parts (actuator), or None.
      max_command, max_ctrl: the largest differences.
      events: controller inputs applied.
    """

    periods: int
    exact: bool
    first_command: tuple[float, int, str, float] | None
    first_ctrl: tuple[float, int, str, float] | None
    max_command: float
    max_ctrl: float
    events: int
    # per Odometry topic its controller publishes, the re-run's (nperiod, 13) values (NaN: not run)
    odometry: dict[str, np.ndarray] = dataclasses.field(default_factory=dict, repr=False)

    def line(self, world: int) -> str:
        head = f"world {world} (controllers re-run, {self.periods} periods, {self.events} controller inputs)"
        if not self.periods:
            return f"{head}: no fresh start in the recording (it began mid-run): nothing re-run"
        if self.exact:
            return f"{head}: bit-exact (every command and ctrl value equal to the bit)"
        parts = []
        for what, first, worst in (("commands", self.first_command, self.max_command), ("ctrl", self.first_ctrl, self.max_ctrl)):
            if first is not None:
                t, period, name, diff = first
                parts.append(f"the {what} part at t={t:.3f} s (period {period}), {name} first ({diff:.3g}; largest {worst:.3g})")
        return f"{head}: " + "; ".join(parts)


class _Feed(Participant):
    """Before the controller manager: a fresh start's reset and state, this period's inputs."""

    def __init__(self, manager: Any, recorded: Recorded, world: WorldRecord, inputs: dict[str, Any]):
        self.manager, self.recorded, self.world, self.inputs = manager, recorded, world, inputs
        self.starts = {s.period: s for s in world.starts if s.fresh}
        self.events: dict[int, list[dict]] = {}
        for e in recorded.events:
            self.events.setdefault(int(e["period"]), []).append(e)
        self.period = -1  # the recorded period being re-run
        self.applied = 0

    def update(self, sim: Any, time: float, period: float) -> None:
        start = self.starts.get(self.period)
        if start is not None:  # as a reset does it: the PIDs afresh, the world's draws and start, then its controllers
            sim.reset([0])
            sim.set_world_params([0], {f: v[None] for f, v in start.params.items()})
            sim.set_physics_state([0], start.state[None])
            self.manager.on_reset(sim, np.array([0]))
        for event in self.events.get(self.period, ()):
            self._apply(event)

    def _apply(self, event: dict) -> None:
        if "kind" in event:  # the controller_manager's: a switch, a parameter set, a cancel, a gripper goal
            self.applied += self._control(event)
            return
        inp = self.inputs.get(event["topic"])
        if inp is None:
            raise ResimError(f"the recording's controllers took {event['topic']}, which these controllers have no input for")
        w = self.world.world
        if "batch" in event:
            doc = event["batch"]
            keep = np.asarray(doc["worlds"]) == w
            if not keep.any():
                return
            inp.apply(_batch(doc).select(keep))
        else:
            worlds = np.asarray(event["worlds"])
            rows = np.asarray(event["rows"], np.float64)[worlds == w]
            if not len(rows):
                return
            inp.apply(np.zeros(len(rows), np.int64), rows)
        self.applied += 1


    def _control(self, e: dict) -> bool:
        kind, world, manager = e["kind"], np.array([0]), self.manager
        if e["world"] != self.world.world:
            return False
        if kind == "switch":
            manager.switch(world, e["activate"], e["deactivate"], e["strictness"], e["asap"])
        elif kind == "parameters":
            manager[e["controller"]].set_parameters(world, e["values"])
        elif kind == "cancel":
            manager[e["controller"]].cancel(world, np.array([e["goal"]]))
        elif kind == "gripper":
            manager[e["controller"]].set_goals(world, np.array([e["goal"]]), np.array([e["position"]]), np.array([e["max_effort"]]))
        return True


class _Check(Participant):
    """After the controller manager: the unclaimed interfaces' recorded commands in, then the
    commands and (after write) the ctrl measured against the recording's."""

    def __init__(
        self, manager: Any, names: list[str], actuators: list[str], recorded: Recorded, world: WorldRecord, states: list[str]
    ):
        self.manager, self.names, self.actuators, self.world = manager, names, actuators, world
        # per joint with an effort state interface, its column, and the effort shown at each period's start
        self._effort_columns = {n.removesuffix("/effort"): k for k, n in enumerate(states) if n.endswith("/effort")}
        self.effort = {j: np.full(len(recorded.headers), np.nan) for j in self._effort_columns}
        self.starts = {s.period for s in world.starts if s.fresh}
        self.layout, self.headers = recorded.layout, recorded.headers
        self.k = -1
        # per controller, its live active mask (a view that follows switches) and its command columns
        self._claims = [(manager.active(c.name), [names.index(n) for n in c.command_interfaces]) for c in manager]
        self.state: tuple[np.ndarray, np.ndarray] = (np.zeros(0), np.zeros(0))
        self.poses, self.pose = False, (np.zeros(0), np.zeros(0))
        outputs = [o for c in manager for o in c.topics().outputs if o.kind is MessageKind.ODOMETRY]
        self.odometry = [(o.topic, o.read) for o in outputs]
        self.odometry_values = {o.topic: np.full((len(self.headers), 13), np.nan) for o in outputs}
        self.command_diff = np.full((len(self.headers), len(names)), np.nan)
        self.ctrl_diff = np.full((len(self.headers), recorded.layout.nu), np.nan)

    def claimed(self) -> np.ndarray:
        """(ncommand,) bool: the interfaces an active controller claims in the world."""
        out = np.zeros(len(self.names), bool)
        for active, columns in self._claims:
            if active[0]:
                out[columns] = True
        return out

    def update(self, sim: Any, time: float, period: float) -> None:
        self.state = tuple(a[0] for a in sim.qstate([0]))  # the period's start (after a fresh start's reset)
        if int(self.headers[self.k, 0]) not in self.starts:  # read() before a start's reset shows the last run's
            for joint, column in self._effort_columns.items():
                self.effort[joint][self.k] = sim.state[0, column]
        for topic, read in self.odometry:  # what the bridge publishes of this period, after the controllers
            rows = read()
            self.odometry_values[topic][self.k] = np.concatenate([rows[f][0] for f in _ODOMETRY_FIELDS])
        if self.poses:  # what /tf is made from at this period
            self.pose = tuple(np.asarray(a[0], np.float64) for a in sim.body_poses([0]))
        row = self.layout.split_inputs(self.world.inputs[self.k : self.k + 1])
        claimed = self.claimed()
        self.command_diff[self.k] = np.where(claimed, np.abs(sim.command[0] - row["command"][0]), 0.0)
        sim.command[0, ~claimed] = row["command"][0, ~claimed]

    def after_write(self, sim: Any, time: float, period: float) -> None:
        row = self.layout.split_inputs(self.world.inputs[self.k : self.k + 1])
        self.ctrl_diff[self.k] = np.abs(sim.physics_inputs([0])["ctrl"][0] - row["ctrl"][0])

    def comparison(self, ran: np.ndarray, applied: int) -> ControllerComparison:
        def first(diff: np.ndarray, names: list[str]) -> tuple[float, int, str, float] | None:
            parted = np.argwhere(diff[ran] > 0)
            if not parted.size:
                return None
            i, j = parted[0]
            k = np.flatnonzero(ran)[i]
            return float(self.headers[k, 1]), int(self.headers[k, 0]), names[j], float(diff[k, j])

        cmd, ctl = first(self.command_diff, self.names), first(self.ctrl_diff, self.actuators)
        worst = lambda d: float(np.nanmax(d[ran])) if ran.any() and d.size else 0.0  # noqa: E731
        return ControllerComparison(
            int(ran.sum()), bool(ran.any()) and cmd is None and ctl is None, cmd, ctl,
            worst(self.command_diff), worst(self.ctrl_diff), applied,
        )  # fmt: skip


_ODOMETRY_FIELDS = ("position", "orientation", "linear", "angular")  # nav_msgs/Odometry's, as the bridge fills it


def odometry_topics(spec: Any, controllers: str | Path | None) -> list[str]:
    """The nav_msgs/Odometry topics `controllers` publish (a diff drive's `odom`) on the robot
    `spec` (a system's), namespace-relative."""
    manager = _manager(controllers, spec)
    return [o.topic for c in manager for o in c.topics().outputs if o.kind is MessageKind.ODOMETRY]


def _manager(controllers: str | Path | None, spec: Any) -> Any:
    """One world's controller manager: `controllers` (a controller_manager YAML), or in a world of
    several robots (a fleet file's model) each robot's own, as the fleet ran them."""
    from batchsim.controllers import load_controllers
    from batchsim.controllers.robots import load_fleet_controllers

    if spec.robots and not controllers:
        manager = load_fleet_controllers(spec, 1)
        if manager is None:
            raise ResimError("--controllers: no robot of the fleet has controllers")
        return manager
    if controllers is None:
        raise ResimError("--controllers: name the controller_manager YAML the run used")
    return load_controllers(controllers, spec, 1)


def rerun_controllers(
    model: str | Path, controllers: str | Path | None, recorded: Recorded, world: WorldRecord, poses: bool = False
) -> tuple[Trajectory, ControllerComparison]:
    """Re-run `world` of `recorded` with `controllers` (a controller_manager YAML; None: a fleet
    file's robots' own) on `model` (a model, or a fleet file of several robots per world); with
    `poses`, keep the body poses the system shows at each period's start (/tf's)."""
    import batchsim

    layout = recorded.layout
    if layout.base_velocity or layout.nbody:
        raise ResimError(
            "--controllers: the recording holds the plugins' inputs (base velocity, wrenches), which a re-run "
            "with controllers does not take; re-run without --controllers"
        )
    if not layout.ncommand:
        raise ResimError("--controllers: the recording holds no command interfaces (recorded by an older batchsim)")
    sim = batchsim.make(model, 1, "cpu")
    sim.configure()
    sim.activate()
    manager = _manager(controllers, sim.spec)
    inputs = {inp.topic: inp for c in manager for inp in c.topics().inputs}
    headers = recorded.headers
    nstep0 = int(headers[0, 2])
    loop = SimLoop(sim, control_rate=1.0 / (nstep0 * sim.dt), rtf=0)
    feed = _Feed(manager, recorded, world, inputs)
    names = list(sim.export_command_interfaces())
    m = sim.model
    actuators = [m.actuator(i).name or f"actuator {i}" for i in range(m.nu)]
    check = _Check(manager, names, actuators, recorded, world, list(sim.export_state_interfaces()))
    loop.participants[:] = [feed, manager, check]
    n = len(headers)
    qpos, qvel, since = np.full((n, m.nq), np.nan), np.full((n, m.nv), np.nan), np.full(n, np.nan)
    xpos = np.full((n, m.nbody, 3), np.nan) if poses else None
    xquat = np.full((n, m.nbody, 4), np.nan) if poses else None
    check.poses = poses
    ran = np.zeros(n, bool)
    running, t0 = False, np.nan
    for k in range(n):
        number = int(headers[k, 0])
        if number in feed.starts:
            running, t0 = True, float(headers[k, 1])
        if not running:
            continue
        if world.inputs[k, 0]:  # frozen: held until its next reset
            running = False
            continue
        feed.period, check.k, loop.sim_time = number, k, float(headers[k, 1])
        loop.run_period(int(headers[k, 2]))
        ran[k] = True
        qpos[k], qvel[k], since[k] = check.state[0], check.state[1], t0
        if poses:
            xpos[k], xquat[k] = check.pose
    verdict = check.comparison(ran, feed.applied)
    verdict.odometry = {t: v for t, v in check.odometry_values.items()}
    return Trajectory(qpos, qvel, since, xpos, xquat, check.effort or None), verdict


def _batch(doc: dict) -> TrajectoryBatch:
    """A TrajectoryBatch from its JSON document (ros_bridge/input_recording.py's), its worlds 0."""
    fields = {}
    for f in dataclasses.fields(TrajectoryBatch):
        value = doc.get(f.name)
        fields[f.name] = None if value is None else np.asarray(value)
    fields["worlds"] = np.zeros(len(doc["worlds"]), np.int64)  # the one world of the re-run
    return TrajectoryBatch(**fields)
