"""The physics side of the bridge: a loop participant that owns the shared memory and the
bridge workers. No rclpy here (with workers in processes, the physics process never imports it).

Per control period, in the loop thread:

    update      the workers' requests (resets, pause, step; trajectory batches), new commands from their
                slots, command timeouts, BAD_COMMAND bookkeeping (then the controllers, write())
    after_write BAD_COMMAND re-marked; a snapshot (time, status, the channels a worker publishes) to shared memory,
                workers woken: here if a channel due reads the engine (tf), else beside the device's steps
    gate        with lockstep: publish the state the period starts from, wait until every world's command arrived
    idle        while paused: requests, resets published at once, steps answered

The workers are ros_bridge/supervisor.py's: one that dies is noticed within a quarter second, its worlds hold
their last commands (or go safe under a command timeout), the log names them; it restarts on the same memory."""

from __future__ import annotations

import os
import select
import sys
import time as wallclock
from collections.abc import Sequence
from typing import Any

import numpy as np

from batchsim.contract import Contract
from batchsim.controllers import ControllerManager
from batchsim.controllers.topics import Input, MessageKind
from batchsim.loop import Participant, SimLoop
from batchsim.loop.realtime import with_siblings
from batchsim.memory import Memory, Ring
from batchsim.types import FROZEN, Status
from ros_bridge.action_plan import decode_cancel, decode_gripper_goal
from ros_bridge.manager_link import ManagerLink
from ros_bridge.naming import topic_name
from ros_bridge.plan import FLAG_BAD, FLAG_FROZEN, FLAG_TIMED_OUT, ChannelFill, FleetPlan, describe
from ros_bridge.protocol.commands import RejectionWriter, SlotReader
from ros_bridge.protocol.demand import demanded
from ros_bridge.protocol.goals import Refusal, RefusalWriter
from ros_bridge.protocol.requests import (
    Kind,
    decode_document,
    decode_reset,
    decode_ticket,
    decode_trajectories,
)
from ros_bridge.protocol.services import put_answer
from ros_bridge.protocol.snapshot import reset_snapshots, write_snapshot
from ros_bridge.protocol.world_params import ParamWriter
from ros_bridge.simulation import SimulationRequests
from ros_bridge.supervisor import Supervisor
from ros_bridge.throttle import LogThrottle
from ros_bridge.timeouts import CommandTimeouts
from ros_bridge.trajectory_inputs import TrajectoryInputs

IDLE_TICK = 0.02  # s between two in-process worker ticks while paused
_BAD = np.uint8(Status.BAD_COMMAND)
_FROZEN = np.uint8(FROZEN)


class BridgeHost(Participant):
    """The bridge's loop participant: shared memory, workers, and the loop's hooks.

    Args:
      sim: the system, configured.
      loop: the loop that runs it.
      plan: what the workers serve (ros_bridge/plan.py).
      fills: per channel, `fill(out (nworld, width))` from the system or a controller.
      inputs: per plan input, the controller's Input (its `apply`).
      processes: run the workers as processes (False: one worker inside this process).
      command_timeout, lockstep_timeout: see BridgeOptions.
      readers: controllers that only read the state (broadcasters): after a reset while
        paused they are updated once, so what is published at once shows the reset state.
      manager: the controllers, for the controller_manager services and the actions.
    """

    def __init__(
        self,
        sim: Contract,
        loop: SimLoop,
        plan: FleetPlan,
        fills: Sequence[ChannelFill],
        inputs: Sequence[Input],
        *,
        processes: bool,
        command_timeout: float | None = None,
        lockstep_timeout: float = 1.0,
        readers: Sequence[Any] = (),
        manager: ControllerManager | None = None,
    ):
        self.sim = sim
        self.loop = loop
        self.plan = plan
        self.nworld = n = plan.nworld
        self.fills = list(fills)
        self.inputs = list(inputs)
        self.processes = processes
        self.lockstep = plan.lockstep
        self.lockstep_timeout = lockstep_timeout
        self.namespaces = plan.namespaces
        self.readers = list(readers)
        self.on_close: list[Any] = []  # called first by close(): a recording finishes its file
        self.throttle = LogThrottle(_stderr)
        self.memory = Memory.create(plan.layout, shared=processes or plan.recording is not None)  # a recorder attaches
        plan.memory_name = self.memory.name
        m = self.memory
        reset_snapshots(m)
        self.commands = SlotReader(m, "cmd")
        self._input_readers = [
            SlotReader(m, spec.slots) if spec.kind is not MessageKind.JOINT_TRAJECTORY else None for spec in plan.inputs
        ]
        # trajectory inputs: handed to their controllers while the device steps (ros_bridge/trajectory_inputs.py)
        kinds, slots = [spec.kind for spec in plan.inputs], [spec.slots for spec in plan.inputs]
        self.trajectories = TrajectoryInputs(m, kinds, slots, self.inputs, self._refused, n)
        self.rejections = RejectionWriter(m, "hrej")
        self.refusals = RefusalWriter(m) if "goal.refused" in m else None  # action goals (protocol/goals.py)
        self.params = ParamWriter.start(m, plan, sim)  # each world's draw, for /diagnostics; again after resets
        self._worker_rejections = m["rej.count"]
        self._worker_rejections_seen = self._worker_rejections.copy()
        # controller_manager's services and the actions' goals (switch, cancel, gripper goals)
        self.manager_link = ManagerLink(manager, m, plan.namespaces) if manager is not None and plan.manager else None
        self._rings = [Ring(m, f"ring{j}") for j in range(plan.nworker)]
        self.free = np.array([not o for o in plan.owners], dtype=bool)
        self.all_claimed = bool(plan.interfaces) and not self.free.any()

        # per channel: the decimations of the outputs that read it
        self._channel_every: list[set[int]] = [set() for _ in plan.channels]
        for out in plan.outputs:
            for c in out.channels:
                self._channel_every[c].add(out.every)
        if plan.tf is not None:
            self._channel_every[plan.tf.channel].add(plan.tf.every)
        for action in plan.actions:
            self._channel_every[action.channel].add(action.every)

        self.bad = np.zeros(n, dtype=bool)
        self.timeouts = CommandTimeouts(sim, command_timeout, self.free, self.namespaces, self.throttle.warn)
        # channels whose fill reads the engine itself (tf's poses): written before the steps
        self._engine_channels = [c for c, fill in enumerate(self.fills) if getattr(fill, "reads_engine", False)]
        self._deferred: tuple[float, bool] | None = None  # a snapshot for while_stepping (time, force)
        self._period = 0  # control periods run, for the outputs' decimation
        self._n = -1  # snapshots written
        self._published_time: float | None = None
        self._force = False
        self._gate_since: float | None = None
        # pause, steps, state writes, wrenches (their done marks wake a worker)
        self.simulation = SimulationRequests(sim, loop, self._done, m, lambda worker: self.workers.wake(worker))
        self._next_idle_tick = 0.0
        self._closed = False
        # the workers: started, woken, watched and restarted (ros_bridge/supervisor.py)
        # ... off the loop thread's cores (SimLoop.cpu_affinity): a woken worker would take its core
        avoid = with_siblings(loop.cpu_affinity)  # the loop's cores, and their other hardware threads
        self.workers = Supervisor(plan, m, processes=processes, throttle=self.throttle, command_timeout=command_timeout, avoid_cpus=avoid)

    # --- start and stop ---
    def start(self) -> None:
        """Bring the workers up. FleetConflict or WorkerError if they cannot serve (then
        the shared memory is gone too)."""
        try:
            self.workers.start()
        except BaseException:
            self.close()
            raise

    @property
    def worker_pids(self) -> list[int]:
        """The worker processes' ids (empty when the bridge runs in this process)."""
        return self.workers.pids

    def close(self) -> None:
        """Stop every worker and unlink the shared memory. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        if self.loop.gate == self.gate:
            self.loop.gate = None
        for hook in self.on_close:
            hook()
        self.workers.close()
        self.memory.close()

    def attach(self) -> None:
        """Join the loop: first participant (controllers after it see this period's
        commands), and its gate with lockstep."""
        self.loop.participants.insert(0, self)
        if self.lockstep:
            self.loop.gate = self.gate

    def describe(self) -> str:
        text = describe(self.plan)
        workers = f"{self.plan.nworker} bridge worker{'s' if self.plan.nworker > 1 else ''}" if self.processes else ""
        return text[:-1] + f", {workers})" if workers else text

    # --- the loop thread ---
    def update(self, sim: Contract, time: float, period: float) -> None:
        """Requests, commands, timeouts, BAD_COMMAND; the controllers run after this."""
        self._flush(write=False)  # a step that failed before while_stepping: read() has moved on since
        self.workers.supervise()
        good = np.zeros(self.nworld, dtype=bool)
        rejected = np.zeros(self.nworld, dtype=bool)
        self._serve_requests(sim, good, rejected, later=not self.lockstep)
        self.trajectories.verdicts(good, rejected)  # of the trajectories handed over beside the last steps
        self.simulation.poll()

        new, values = self.commands.take()
        if new.any():
            np.copyto(sim.command, values, where=new)
            got = new.any(axis=1)
            self.timeouts.heard(got, time)
            good |= got
        for i, reader in enumerate(self._input_readers):
            if reader is None:
                continue
            new, values = reader.take()
            worlds = np.flatnonzero(new)
            if worlds.size:
                refused = self.inputs[i].apply(worlds.astype(np.int64), values[worlds].copy())
                good[worlds] = True
                self._refused(i, worlds, refused, good, rejected)
        counts = self._worker_rejections.copy()
        rejected |= counts != self._worker_rejections_seen
        self._worker_rejections_seen = counts
        self.trajectories.period_starts()
        self.timeouts.check(sim, time)
        # a rejection sets BAD_COMMAND until the world's next good command; when controllers
        # hold every interface, every period applies theirs
        self.bad = rejected | (np.zeros_like(self.bad) if self.all_claimed else self.bad & ~good)

    def after_write(self, sim: Contract, time: float, period: float) -> None:
        """write() clears BAD_COMMAND for the rows it applied: keep the bridge's; publish: now
        if a channel due reads the engine (tf), else while the device steps (while_stepping)."""
        if self.bad.any():
            sim.status[self.bad] |= _BAD
        if self._published_time != time or self._force:
            if self._engine_channels and self._engine_due():
                self._snapshot(time, force=self._force)
            else:  # decided now, with this moment's status (a fleet's shards write theirs while they step)
                self._deferred = (time, self._force, sim.status.copy())
                return
        self._period += 1

    def while_stepping(self, sim: Contract, time: float, period: float) -> None:
        """The period's snapshot, from host copies only, then the trajectories its update took
        to their controllers, while the device steps (SimLoop)."""
        self._flush(write=True)
        self.trajectories.hand_over(beside_steps=True)

    def _flush(self, write: bool) -> None:
        """The snapshot after_write left for while_stepping, if it is still pending: written
        (`write`: before any read() since), or else dropped, the period counted either way."""
        if self._deferred is not None:
            (time, force, status), self._deferred = self._deferred, None
            if write:
                self._snapshot(time, force=force, status=status, engine=False)
            self._period += 1

    def _engine_due(self) -> bool:
        """Whether this period's snapshot writes a channel whose fill reads the engine."""
        k, wanted = self._period, demanded(self.memory)
        return any(
            wanted[c] and (self._force or any(k % e == 0 for e in self._channel_every[c])) for c in self._engine_channels
        )

    def idle(self, sim: Contract, time: float) -> None:
        """While paused: requests; a reset or a finished step is published at once."""
        self._flush(write=True)
        refused = np.zeros(self.nworld, dtype=bool)  # trajectories refused beside the last steps: shown now
        self.trajectories.verdicts(np.zeros(self.nworld, dtype=bool), refused)
        self.bad |= refused
        self._gate_since = None
        self.workers.supervise()
        if self._serve_requests(sim, None, None) and self._force:
            for c in self.readers:  # the controllers' copies of the state, for what is published now
                c.update(sim, time, 0.0)
        if self._published_time != time:  # a step ran: publish what it left (read now) before the answer
            sim.read(time, 0.0)
            for c in self.readers:
                c.update(sim, time, 0.0)
            self._snapshot(time, force=True)
        self.simulation.poll()
        if self._force or self._published_time != time:
            self._snapshot(time, force=True)
        elif self.workers.worker is not None and wallclock.monotonic() >= self._next_idle_tick:
            self._next_idle_tick = wallclock.monotonic() + IDLE_TICK
            self.workers.worker.tick()

    def gate(self, sim_time: float) -> bool:
        """Lockstep: True when every world's command for this period has arrived (or the
        wait timed out); False to be asked again, so stop() and pause() stay responsive."""
        if self._closed:
            return True
        self._flush(write=True)
        self.workers.supervise()
        self._serve_requests(self.sim, None, None)
        now = wallclock.monotonic()
        if self._gate_since is None:
            # show the state this period starts from, so commands can be computed from it
            self._gate_since = now
            self.sim.read(sim_time, self.loop.period)
            self._snapshot(sim_time, force=self._force, every_channel=True)
        ready = self._ready()
        if ready.all():
            self._gate_since = None
            return True
        left = self._gate_since + self.lockstep_timeout - now
        if left > 0:
            select.select([self.workers.notify_r], [], [], min(left, 0.05))
            try:
                os.read(self.workers.notify_r, 65536)
            except BlockingIOError:
                pass
            if self.workers.worker is not None:
                self.workers.worker.tick()  # in-process: services and housekeeping while we wait
            ready = self._ready()
            if ready.all():
                self._gate_since = None
                return True
            if wallclock.monotonic() - self._gate_since < self.lockstep_timeout:
                return False
        self._gate_since = None
        silent = np.flatnonzero(~ready)
        names = ", ".join(self.namespaces[w] for w in silent[:8]) + (" ..." if silent.size > 8 else "")
        self.throttle.warn(
            "lockstep",
            f"lockstep: no command within {self.lockstep_timeout:g} s from {names} at sim time {sim_time:.3f} s; "
            "going on with their last command",
        )
        return True

    def on_reset(self, sim: Contract, worlds: np.ndarray | None) -> None:
        """Worlds were reset (SimLoop.reset): forget their pending commands and timeouts;
        publish at once."""
        self.commands.drop(worlds)
        for reader in self._input_readers:
            if reader is not None:
                reader.drop(worlds)
        sel = slice(None) if worlds is None else worlds
        self.trajectories.forget(sel)
        self.timeouts.forget(sel)
        self.bad[sel] = False
        self._force = True
        self.params.refresh(sim)  # worlds drawn anew (a variation that redraws): their /diagnostics lines

    def _forget_robot(self, world: int, robot: Any) -> None:
        """One robot of `world` was reset: its commands, its controllers' inputs and goals dropped."""
        rows = np.array([world])
        self.commands.drop(rows, np.asarray(robot.commands))
        mine = {i for i, spec in enumerate(self.plan.inputs) if spec.controller.startswith(robot.prefix)}
        for reader in (self._input_readers[i] for i in mine if self._input_readers[i] is not None):
            reader.drop(rows)
        self.trajectories.forget(rows, mine)
        if self.manager_link is not None:
            self.manager_link.manager.reset_robot(self.sim, robot.name, rows)

    # --- requests through the rings ---
    def _serve_requests(
        self, sim: Contract, good: np.ndarray | None, rejected: np.ndarray | None, later: bool = False
    ) -> bool:
        """Carry out what the workers' rings hold; True if there was anything. Trajectories go to
        their controllers now, or `later`: while the device steps (now if a switch or a cancel came
        with them); cancels go after them, so a goal canceled in the read that brought it is canceled."""
        self.trajectories.hand_over(good, rejected)  # what an earlier period left waiting (its steps failed), first
        anything = False
        resets: list[tuple[int, int]] = []
        reset_all = False
        reset_worlds: list[np.ndarray] = []
        trajectories: dict[int, list] = {}
        cancels: list[tuple[int, int, int]] = []  # after this read's goals, which they may cancel
        for j, ring in enumerate(self._rings):
            for kind, payload in ring.take():
                anything = True
                if kind == Kind.TRAJECTORY:
                    index, batch = decode_trajectories(payload)
                    trajectories.setdefault(index, []).append(batch)
                elif kind == Kind.RESET:
                    ticket, worlds = decode_reset(payload)
                    resets.append((j, ticket))
                    if worlds is None:
                        reset_all = True
                    else:
                        reset_worlds.append(worlds)
                elif kind == Kind.PAUSE:
                    ticket, value = decode_ticket(payload)
                    self.simulation.pause(j, ticket, bool(value))
                elif kind in (Kind.STEP, Kind.STEP_N):
                    ticket, value = decode_ticket(payload)
                    self.simulation.step(j, ticket, value if kind == Kind.STEP_N else None)
                elif kind == Kind.RESET_WORLD:
                    self.simulation.reset_world(j, *decode_document(payload))
                elif kind == Kind.SET_FREE_JOINTS:
                    self.simulation.set_free_joints(j, *decode_document(payload))
                    self._force = True  # published at once, paused or not
                elif kind == Kind.APPLY_WRENCH:
                    self.simulation.apply_wrench(j, *decode_document(payload))
                elif kind == Kind.RESET_ROBOT:
                    self.simulation.reset_robot(j, *decode_document(payload), forget=self._forget_robot)
                    self._force = True  # published at once, paused or not
                elif kind == Kind.CANCEL and self.manager_link is not None:
                    cancels.append(decode_cancel(payload))
                    later = False
                elif kind == Kind.GRIPPER_GOAL and self.manager_link is not None:
                    self._gripper_goal(payload)
                elif kind == Kind.SWITCH and self.manager_link is not None:
                    later = False  # the switch resets its controllers in this period: trajectories go first, as ever
                    ticket, _, ok, message = self.manager_link.switch(payload)
                    self._done(j, ticket, self.loop.sim_time, ok=ok, message=message)
                elif kind == Kind.SET_PARAMETERS and self.manager_link is not None:
                    ticket, ok, message = self.manager_link.set_parameters(payload)
                    self._done(j, ticket, self.loop.sim_time, ok=ok, message=message)
        reset_rows: np.ndarray | None = None
        if resets:
            reset_rows = None if reset_all else np.unique(np.concatenate(reset_worlds))
            self.loop.reset(reset_rows)  # every participant hears of it (on_reset), this one too
            for j, ticket in resets:
                self._done(j, ticket, self.loop.sim_time, ok=True)
        self.trajectories.take(trajectories, reset_rows, bool(resets), good, rejected, later=later)
        for index, world, goal in cancels:
            self.manager_link.cancel(self.plan.actions[index].controller, world, goal)
        return anything

    def _refused(
        self, index: int, worlds: np.ndarray, refused: list[tuple[int, str]], good: np.ndarray | None, rejected: np.ndarray | None
    ) -> None:
        """Rejections a controller's apply returned: counted, logged, BAD_COMMAND."""
        topic = self.plan.inputs[index].topic
        for k, reason in refused:
            w = int(worlds[k])
            where = topic_name(self.namespaces[w], topic)
            self.rejections.put(w, self._period, where, reason)
            self.throttle.warn((where, "refused"), f"rejected command on {where}: {reason}")
            if good is not None and rejected is not None:
                good[w] = False
                rejected[w] = True
            else:
                self.bad[w] = True

    def _gripper_goal(self, payload: np.ndarray) -> None:
        """A GripperCommand goal to its controller; a refused one is marked for its worker."""
        index, world, goal, position, max_effort = decode_gripper_goal(payload)
        name = self.plan.actions[index].controller
        refused = self.manager_link.gripper_goal(name, world, goal, position, max_effort)
        for _, reason in refused:
            self.rejections.put(world, self._period, f"{name}/gripper_cmd", reason)
            self.refusals.refuse([world], [goal], Refusal.INVALID, [reason])

    def _done(self, worker: int, ticket: int, time: float, ok: bool, message: str = "") -> None:
        """Answer `worker`'s request `ticket` (protocol/services.py) and wake it."""
        put_answer(self.memory, worker, ticket, time, ok, message)
        self.workers.wake(worker)

    # --- publishing ---
    def _snapshot(
        self, time: float, force: bool, every_channel: bool = False, status: np.ndarray | None = None, engine: bool = True
    ) -> None:
        """Copy what is due into the next snapshot (protocol/snapshot.py), wake the workers. `every_channel`:
        every channel, wanted or not (the lockstep's wait: a subscriber that comes during it gets it at once);
        `status`: the one to show (default the system's now); `engine` False: not the channels whose fill
        reads the engine (beside the device's steps)."""
        flags = np.zeros(self.nworld, np.uint8)
        status = self.sim.status.copy() if status is None else status
        if self.bad.any():
            status[self.bad] |= _BAD
            flags[self.bad] |= FLAG_BAD
        timed_out = self.timeouts.timed_out
        if timed_out.any():
            flags[timed_out] |= FLAG_TIMED_OUT
        if status.any():
            flags[(status & _FROZEN) != 0] |= FLAG_FROZEN
        k = self._period
        due = [every_channel or force or any(k % e == 0 for e in every) for every in self._channel_every]
        if not engine:
            for c in self._engine_channels:
                due[c] = False
        self._n = write_snapshot(self.memory, self._n + 1, k, time, force, status, flags, self.fills, due, every_channel)
        self._published_time = time
        self._force = False
        self.workers.wake_all()

    # --- lockstep and timeouts ---
    def _ready(self) -> np.ndarray:
        """(nworld,) bool: the worlds whose command for this period arrived: a command on
        every free interface, and an input on every controller topic that takes one."""
        ready = np.ones(self.nworld, dtype=bool)
        if self.free.any():
            ready &= self.commands.fresh()[:, self.free].all(axis=1)
        ready &= self.trajectories.ready()
        for reader in self._input_readers:
            if reader is not None:
                ready &= reader.fresh()
        return ready


def _stderr(line: str) -> None:
    print(f"batchsim: warning: {line}", file=sys.stderr, flush=True)
