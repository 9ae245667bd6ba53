"""The simulation loop: read, update, write, step, once per control period, paced to a
real-time factor. It is controller_manager's loop, batched over worlds.

A fleet of several groups of worlds (batchsim.fleet.groups: each group its own model, one system
each) is one loop per group, joined (`SimLoop.join`): the first runs every group's period in
turn under one clock, and pause, steps and stop are the fleet's.

Participants (controllers, the ROS bridge) plug in through `Participant.update`, called
every control period between `read()` and `write()`, exactly where ros2_control calls
controllers, and its other hooks (after write(), beside the steps, while paused, after a
reset). Nothing here imports rclpy: the bridge is one participant among others.
"""

from __future__ import annotations

import dataclasses
import operator
import os
import threading
import time as wallclock
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from batchsim.contract import Contract
from batchsim.loop import realtime
from batchsim.loop.rates import DEFAULT_CONTROL_RATE, RateError, whole_ratio  # light: the parser's too
from batchsim.types import OptionError, ReturnType, Status, worlds_index


class Participant:
    """Something the loop runs once per control period, on the loop thread, in the order of
    `SimLoop.participants`: the controller manager, the ROS bridge, a recorder, a sensor feed.

    Subclass it and override the hooks you need; every one is a no-op here. One period
    (`SimLoop.run_period`) runs read(), every `update`, write(), every `after_write`, then
    the period's physics steps with every `while_stepping` beside them. While the loop is
    paused, `idle` runs in place of the periods; `on_reset` runs after `SimLoop.reset`;
    `on_stop` once a run() ends.

    A participant that is no subclass works too: an object with `update` and any of the
    other hooks by the same names (duck-typed). The loop keeps `participants` a plain list,
    which the bridge inserts into, and takes each participant as it is: it looks up which
    hooks each one has once, whenever the list changed since the last period (an insert,
    an append, a new list), and then calls them as plain methods, skipping this base's
    no-ops. A change takes effect from the next period.
    """

    def update(self, sim: Contract, time: float, period: float) -> None:
        """Every control period, between read() and write(), where ros2_control runs its
        controllers: read `sim.state` (fresh from this period's read()), write `sim.command`
        (applied by the write() that follows). `time` is the period's start in sim time,
        `period` its length (shorter for a last, partial period of `step_physics`). It may
        call `SimLoop.reset` (the bridge's reset services do)."""

    def after_write(self, sim: Contract, time: float, period: float) -> None:
        """Every period, right after write() and before the physics steps: see what write()
        made of the commands (`sim.status`'s BAD_COMMAND bits; the bridge re-marks the
        commands it rejected). It may call the system; `sim.command` is already applied."""

    def while_stepping(self, sim: Contract, time: float, period: float) -> None:
        """Every period, while the period's physics steps (Contract.step's `meanwhile`):
        on a device (warp, mjx, a fleet of shards) after the steps are launched and before
        they are waited for, elsewhere just before them. Host work only (the bridge's
        snapshot of what read() filled, a controller's work for its next update): it must
        not call the system, and what read() filled and `sim.command` stay as they are
        meanwhile. A participant that does not override it gives the system no `meanwhile`
        to run. Every participant's runs even if one raises; the first error is raised once
        the period is counted."""

    def idle(self, sim: Contract, time: float) -> None:
        """While the loop is paused and no step is pending, about every 2 ms, in place of the
        periods: serve requests (a step, a reset, a resume). `time` is the loop's sim time,
        which does not advance. It may call `SimLoop.reset`."""

    def on_reset(self, sim: Contract, worlds: np.ndarray | None) -> None:
        """Right after `SimLoop.reset` reset worlds, on the loop thread: `worlds` (k,) int64
        indices (a mask's worlds where it was True), None for every world. Drop those
        worlds' goals and per-world state; nothing needs to infer a reset from the state
        (a world whose time goes backwards)."""

    def on_stop(self, sim: Contract, time: float) -> None:
        """Once `SimLoop.run` is over (stop() or its duration), on the loop's thread, before
        run() returns: finish what is still in flight (the sensor sampler hands out its
        renders still rendering, so a recording gets the run's last frames before it closes).
        `time` is the sim time it stopped at. Not after a period that raised."""


def _overrides(p: object, hook: str) -> bool:
    """Whether participant `p` has `hook` (a method, or an attribute of its own) other than
    Participant's no-op."""
    found = getattr(p, hook, None)
    return found is not None and getattr(found, "__func__", None) is not getattr(Participant, hook)


class _Hooks:
    """Which participants run which hook, in the participants' order (SimLoop._hooks)."""

    __slots__ = ("participants", "after_write", "while_stepping", "idle", "on_reset", "on_stop", "_by_identity")

    def __init__(self, participants: Sequence[Any]):
        self.participants = list(participants)  # a copy of the list it was made from; update() runs on each
        self.after_write = tuple(p for p in self.participants if _overrides(p, "after_write"))
        self.while_stepping = tuple(p for p in self.participants if _overrides(p, "while_stepping"))
        self.idle = tuple(p for p in self.participants if _overrides(p, "idle"))
        self.on_reset = tuple(p for p in self.participants if _overrides(p, "on_reset"))
        self.on_stop = tuple(p for p in self.participants if _overrides(p, "on_stop"))
        # list == tests each pair for identity first, then with __eq__: an identity test, in
        # C, unless a participant has an __eq__ of its own
        self._by_identity = any(type(p).__eq__ is not object.__eq__ for p in self.participants)

    def made_from(self, participants: list[Any]) -> bool:
        """Whether `participants` holds the same objects, in the same order, as when made."""
        if self._by_identity:
            ps = self.participants
            return len(ps) == len(participants) and all(map(operator.is_, ps, participants))
        return participants == self.participants


class _Control:
    """What a loop and the loops joined to it share: stop, pause, and the physics steps asked for
    while paused (from other threads: signal handlers, ROS services)."""

    def __init__(self) -> None:
        self.stop = threading.Event()
        self.paused = threading.Event()
        self.pending_steps = 0
        self.lock = threading.Lock()


@dataclasses.dataclass
class LoopStats:
    """What the status line shows, over the last reporting window."""

    sim_time: float = 0.0
    rtf: float = 0.0
    steps_per_second: float = 0.0
    diverged: int = 0
    overflow: int = 0
    bad_command: int = 0
    periods: int = 0
    paused: bool = False  # the status line shows `paused` instead of the rate


class SimLoop:
    """Runs a configured, active system period after period.

    Args:
      sim: the system, ACTIVE (or INACTIVE: it then steps without applying commands).
      control_rate: Hz at which commands are applied and state read; it must be a whole
        number of physics steps. None: the nearest to DEFAULT_CONTROL_RATE.
      rtf: real-time factor to hold; 0 runs as fast as possible.
      duration: stop after this much simulated time (seconds); None runs until stop().
      participants: run every period (Participant: `update` between read() and write(),
        and the other hooks); `self.participants` is a plain list of them, which may change
        between periods (the bridge inserts itself first).
      thread_priority: while it paces a real-time factor, the thread running the loop asks
        for SCHED_FIFO at this priority (1-99) from its second period on, as ros2_control's
        controller_manager does (batchsim/loop/realtime.py); 0 (the default here; the command's
        is 50) leaves its scheduling alone. A loop that falls half a second behind gives it
        up (a thread of that policy running flat out would starve its core).
      cpu_affinity: likewise, the cores the loop's thread is pinned to (none: any).
      With either, the objects start-up made are frozen out of the garbage collector
      (`gc.freeze`) for the run: a full collection would cost one period its deadline.
    """

    def __init__(
        self,
        sim: Contract,
        *,
        control_rate: float | None = None,
        rtf: float = 1.0,
        duration: float | None = None,
        participants: Sequence[Participant] = (),
        thread_priority: int = 0,
        cpu_affinity: Sequence[int] = (),
    ):
        if not rtf >= 0:
            raise OptionError("rtf", f"must be >= 0, got {rtf:g}")
        if not 0 <= thread_priority <= 99:
            raise OptionError("thread_priority", f"must be 0-99 (0: the normal policy), got {thread_priority}")
        # the cores this process may run on (a container's cpuset may be fewer than the machine's)
        allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else list(range(os.cpu_count() or 1))
        bad = [c for c in cpu_affinity if c not in allowed]
        if bad:
            cores = f"{allowed[0]}-{allowed[-1]}" if allowed == list(range(allowed[0], allowed[-1] + 1)) else ",".join(map(str, allowed))
            raise OptionError("cpu_affinity", f"names no core of this machine that this process may run on ({cores}): {bad[0]}")
        self.sim = sim
        dt = sim.dt
        if control_rate is None:
            self.substeps = max(1, round(1.0 / (DEFAULT_CONTROL_RATE * dt)))
        else:
            if not control_rate > 0:
                raise OptionError("control_rate", f"must be > 0 Hz, got {control_rate:g}")
            try:
                self.substeps = whole_ratio(1.0 / dt, control_rate)
            except RateError as e:
                raise OptionError(
                    "control_rate",
                    f"{control_rate:g} Hz is not a whole number of physics steps of {dt:g} s "
                    f"(the model's timestep): {e.hint}",
                ) from None
        self.period = self.substeps * dt
        self.control_rate = 1.0 / self.period
        self.rtf = float(rtf)
        self.duration = duration
        self.participants: list[Any] = list(participants)  # Participant or duck-typed alike
        self._plan = _Hooks(())  # which participants run which hook (_hooks)
        self.thread_priority = int(thread_priority)
        self.cpu_affinity = tuple(int(c) for c in cpu_affinity)
        self.sim_time = 0.0
        self.stats = LoopStats()
        self._control = _Control()
        self.gate: Callable[[float], bool] | None = None  # lockstep: wait for commands
        #: the loops this one runs, itself first (`join`); `leader` is the one that runs it
        self.members: list[SimLoop] = [self]
        self.leader: SimLoop = self

    def join(self, other: SimLoop) -> None:
        """Run `other` (a loop over another group's system, made alike: the same control rate) in
        this loop's periods from now on: every period runs this loop's, then each joined one's, at
        one sim time; pause, steps and stop are shared (any of them pausing pauses all), and a
        `reset()` of every world here resets every joined loop's too. `other` then never runs on
        its own (`run()` is this loop's)."""
        if other is self or other.leader is not other or len(other.members) > 1 or self.leader is not self:
            raise ValueError("join() takes a loop of its own into a loop that runs itself")
        if abs(other.period - self.period) > 1e-12:
            raise OptionError(
                "control_rate",
                f"the groups of one fleet run at one control rate: {self.control_rate:g} Hz and {other.control_rate:g} Hz",
            )
        other._control, other.leader, other.sim_time = self._control, self, self.sim_time
        self.members.append(other)

    @property
    def nworld(self) -> int:
        """The worlds every member's system holds."""
        return sum(m.sim.nworld for m in self.members)

    # --- control from other threads (signal handlers, ROS services) ---
    def stop(self) -> None:
        self._control.stop.set()

    @property
    def stopped(self) -> bool:
        return self._control.stop.is_set()

    def pause(self, paused: bool) -> None:
        if paused:
            self._control.paused.set()
        else:
            self._control.paused.clear()

    @property
    def paused(self) -> bool:
        return self._control.paused.is_set()

    def single_step(self) -> None:
        """While paused, advance one control period."""
        self.step_physics(self.substeps)

    def step_physics(self, nstep: int) -> None:
        """While paused, advance `nstep` physics steps (added to any still pending): whole control
        periods, and a last, shorter one for a remainder (controllers then see its shorter period)."""
        if nstep < 1:
            raise ValueError(f"step count must be >= 1, got {nstep}")
        control = self._control
        with control.lock:
            control.pending_steps += int(nstep)

    @property
    def pending_steps(self) -> int:
        """Physics steps asked for (step_physics, single_step) and not yet run."""
        return self._control.pending_steps

    def abort_steps(self) -> int:
        """Forget the pending physics steps (a resume interrupts them, as mujoco_ros2_control's
        does); how many there were."""
        control = self._control
        with control.lock:
            pending, control.pending_steps = control.pending_steps, 0
        return pending

    def reset(self, worlds: Sequence[int] | np.ndarray | None = None) -> None:
        """Reset all or the listed worlds and tell every participant (`on_reset`).

        Call it from the loop thread (a participant's update or idle), as the bridge does
        for its services; the system is never touched from another thread. `worlds` as
        `sim.reset` takes it (indices, or a (nworld,) bool mask); participants get (k,) int64 indices.
        Every world (None) of the loop that runs the others is every world of every joined loop.
        """
        if worlds is None and len(self.members) > 1:
            for member in self.members[1:]:
                member.reset(None)
        self.sim.reset(worlds)
        rows = worlds_index(worlds, self.sim.nworld)  # as reset read them: a mask's True worlds
        for p in self._hooks().on_reset:
            p.on_reset(self.sim, rows)

    def _hooks(self) -> _Hooks:
        """Which participants run which hook: looked up again only when `participants`
        changed since (by identity), so that a period calls each hook as a plain method."""
        if not self._plan.made_from(self.participants):
            self._plan = _Hooks(self.participants)
        return self._plan

    # --- the loop ---
    def run_period(self, nstep: int | None = None) -> None:
        """One control period: read, participants, write, step (`nstep` physics steps: a shorter
        period; default a whole one); then each joined loop's, at the same sim time."""
        nstep = self.substeps if nstep is None else nstep
        for member in self.members:
            member._period(nstep)

    def _period(self, nstep: int) -> None:
        """This loop's own system and participants, one period of `nstep` physics steps."""
        sim = self.sim
        t, period = self.sim_time, self.period if nstep == self.substeps else nstep * sim.dt
        plan = self._hooks()
        if sim.read(t, period) is ReturnType.ERROR:
            raise RuntimeError("read() failed")
        for p in plan.participants:
            p.update(sim, t, period)
        sim.write(t, period)
        for p in plan.after_write:  # e.g. the bridge re-marks commands it rejected
            p.after_write(sim, t, period)
        errors: list[Exception] = []
        meanwhile = plan.while_stepping
        if meanwhile:  # e.g. the bridge's snapshot, under the device's steps

            def hooks() -> None:
                for p in meanwhile:  # every one runs; the first error is raised once the period is counted
                    try:
                        p.while_stepping(sim, t, period)
                    except Exception as e:
                        errors.append(e)

            sim.step(nstep, meanwhile=hooks)
        else:
            sim.step(nstep)
        self.sim_time += period
        self.stats.periods += 1
        if errors:
            raise errors[0]

    def run(self, report: Callable[[LoopStats], None] | None = None, report_every: float = 1.0) -> LoopStats:
        """Run until stop() or `duration`; call `report` about every `report_every` wall seconds.
        Every joined loop runs in it (`join`); a joined loop's own run() is refused."""
        if self.leader is not self:
            raise RuntimeError("this loop is joined to another: that one's run() runs it")
        # flat out (rtf 0) the thread keeps its cores but never asks for SCHED_FIFO (it would starve them)
        scheduling = realtime.Scheduling(self.thread_priority, self.cpu_affinity, self.rtf) if self.cpu_affinity or (self.rtf > 0 and self.thread_priority) else None
        try:
            return self._run(report, report_every, scheduling)
        finally:
            if scheduling is not None:
                scheduling.finish()

    def _run(self, report: Callable[[LoopStats], None] | None, report_every: float, scheduling: realtime.Scheduling | None) -> LoopStats:
        start = wallclock.perf_counter()
        anchor_wall, anchor_sim = start, self.sim_time
        window_wall, window_sim, window_steps = start, self.sim_time, 0
        nworld = self.nworld
        control = self._control
        while not control.stop.is_set():
            if self.duration is not None and self.sim_time >= self.duration - 1e-9:
                break
            nstep = None
            if control.paused.is_set():
                with control.lock:
                    if control.pending_steps > 0:
                        nstep = min(self.substeps, control.pending_steps)
                if nstep is None:
                    self._idle_participants()
                    wallclock.sleep(0.002)
                    anchor_wall, anchor_sim = wallclock.perf_counter(), self.sim_time
                    continue
            if not all(m.gate is None or m.gate(self.sim_time) for m in self.members):
                continue
            self.run_period(nstep)
            if scheduling is not None and not scheduling.asked:  # after the first period, which may compile
                scheduling.elevate()
                anchor_wall, anchor_sim = wallclock.perf_counter(), self.sim_time
            if nstep is not None:  # counted down once they ran (a resume may have dropped them meanwhile)
                with control.lock:
                    control.pending_steps = max(0, control.pending_steps - nstep)
            window_steps += (nstep or self.substeps) * nworld
            now = wallclock.perf_counter()
            if self.rtf > 0:
                target = anchor_wall + (self.sim_time - anchor_sim) / self.rtf
                if target > now:
                    if scheduling is not None:
                        scheduling.kept_up(now)
                    wallclock.sleep(target - now)
                elif now - target > 0.5:  # fell behind: hold the rate from here, don't sprint
                    anchor_wall, anchor_sim = now, self.sim_time
                    if scheduling is not None:
                        scheduling.fell_behind(now - target, now)
            now = wallclock.perf_counter()
            if now - window_wall >= report_every:
                self._update_stats(now - window_wall, self.sim_time - window_sim, window_steps)
                if report is not None:
                    report(self.stats)
                window_wall, window_sim, window_steps = now, self.sim_time, 0
        for member in self.members:
            for p in member._hooks().on_stop:
                p.on_stop(member.sim, member.sim_time)
        now = wallclock.perf_counter()
        if now > window_wall and window_steps:
            self._update_stats(now - window_wall, self.sim_time - window_sim, window_steps)
        return self.stats

    def _idle_participants(self) -> None:
        for member in self.members:
            for p in member._hooks().idle:
                p.idle(member.sim, member.sim_time)

    def _update_stats(self, wall: float, sim_elapsed: float, steps: int) -> None:
        status = np.concatenate([m.sim.status for m in self.members]) if len(self.members) > 1 else self.sim.status
        s = self.stats
        s.sim_time = self.sim_time
        s.rtf = sim_elapsed / wall if wall > 0 else 0.0
        s.steps_per_second = steps / wall if wall > 0 else 0.0
        s.diverged = int(np.count_nonzero(status & np.uint8(Status.DIVERGED)))
        s.overflow = int(np.count_nonzero(status & np.uint8(Status.OVERFLOW)))
        s.bad_command = int(np.count_nonzero(status & np.uint8(Status.BAD_COMMAND)))


def format_stats(stats: LoopStats, nworld: int, backend: str) -> str:
    """The live status line: sim time, rtf and steps/s (or `paused`), diverged worlds, backend."""
    sps = stats.steps_per_second
    rate = f"{sps / 1e6:.2f}M" if sps >= 1e6 else f"{sps / 1e3:.1f}k"
    speed = "paused" if stats.paused else f"rtf {stats.rtf:5.2f} | {rate} steps/s"
    line = f"sim {stats.sim_time:8.2f} s | {speed} | diverged {stats.diverged}/{nworld}"
    if stats.overflow:
        line += f" | overflow {stats.overflow}"
    if stats.bad_command:
        line += f" | bad command {stats.bad_command}"
    return line + f" | {backend}"
