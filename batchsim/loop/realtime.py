"""The loop thread's scheduling, as ros2_control's controller_manager sets its own.

controller_manager's main thread asks for `SCHED_FIFO` at priority 50 whatever the kernel
(its `thread_priority` parameter) and may be pinned to cores (`cpu_affinity`): on a loaded
host a thread of the normal policy shares its core with every other runnable one, and a
control period then waits for the scheduler, not for its own work. SimLoop does the same
for the thread that runs it, while it paces a real-time factor (a loop run flat out has no
deadline to protect), and only for that thread: `SCHED_RESET_ON_FORK` keeps every thread
and process it starts (a restarted bridge worker, a render thread) at the normal policy.
Cores are inherited, though: a thread the pinned loop starts shares its core (the bridge
workers are placed off it, batchsim's render threads start before the loop does).

Without the permission (`rtprio` in limits.conf, or `--cap-add=sys_nice --ulimit
rtprio=99` for a container) the loop runs as before and says so once.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import os
from collections.abc import Sequence

log = logging.getLogger("batchsim")

#: controller_manager's default (ros2_control_node's kSchedPriority)
DEFAULT_THREAD_PRIORITY = 50
HOW_TO = (
    "give the user rtprio (limits.conf: '@realtime hard rtprio 99', as ros2_control's docs say) or run the "
    "container with --cap-add=sys_nice --ulimit rtprio=99; --thread-priority 0 does not ask"
)


@dataclasses.dataclass(frozen=True)
class Saved:
    """A thread's scheduling before `elevate`, for `restore`."""

    policy: int
    priority: int
    cpus: frozenset[int] | None  # None: not changed
    fifo: bool  # SCHED_FIFO granted


def elevate(priority: int, cpus: Sequence[int] = ()) -> tuple[Saved | None, list[str]]:
    """The calling thread to SCHED_FIFO at `priority` (1-99) and onto `cpus` (none: any).

    Returns what to restore (None: nothing changed) and a line per part that could not be
    done, naming why."""
    problems: list[str] = []
    if not hasattr(os, "sched_setscheduler"):  # not Linux
        return None, [f"SCHED_FIFO priority {priority}: not available on this system"]
    policy, old_priority = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
    old_cpus = None
    if cpus:
        try:
            old_cpus = frozenset(os.sched_getaffinity(0))
            os.sched_setaffinity(0, set(cpus))
        except OSError as e:
            old_cpus = None
            problems.append(f"cpu_affinity {','.join(map(str, cpus))}: {e.strerror}")
    fifo = False
    if priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
            fifo = True
        except OSError as e:
            problems.append(f"SCHED_FIFO priority {priority}: {e.strerror}; {HOW_TO}")
    changed = fifo or old_cpus is not None
    return (Saved(policy, old_priority, old_cpus, fifo) if changed else None), problems


def lower(saved: Saved) -> None:
    """The calling thread's policy and priority as before `elevate` (its cores stay)."""
    if not saved.fifo:
        return
    try:
        os.sched_setscheduler(0, saved.policy, os.sched_param(saved.priority))
    except OSError:  # clearing SCHED_RESET_ON_FORK needs CAP_SYS_NICE (rtprio alone allowed the rest)
        os.sched_setscheduler(0, saved.policy | os.SCHED_RESET_ON_FORK, os.sched_param(saved.priority))


def restore(saved: Saved | None) -> None:
    """The calling thread's scheduling as before `elevate`: policy, priority and cores."""
    if saved is None:
        return
    lower(saved)
    if saved.cpus is not None:
        os.sched_setaffinity(0, saved.cpus)


def current() -> tuple[int, int]:
    """The calling thread's (policy, priority)."""
    return os.sched_getscheduler(0), os.sched_getparam(0).sched_priority


def with_siblings(cpus: Sequence[int], sysfs: str = "/sys/devices/system/cpu") -> frozenset[int]:
    """`cpus` and the other hardware threads of their cores (SMT siblings, as sysfs lists
    them): a sibling shares its core's execution units and caches, so a process kept off the
    loop's cores keeps off their siblings too. Where sysfs does not say, `cpus` alone."""
    out = set(cpus)
    for cpu in cpus:
        try:
            with open(f"{sysfs}/cpu{int(cpu)}/topology/thread_siblings_list") as f:
                text = f.read().strip()
        except OSError:
            continue
        for part in filter(None, text.split(",")):
            lo, _, hi = part.partition("-")
            out.update(range(int(lo), int(hi or lo) + 1))
    return frozenset(out)


RETRY = 5.0  # s after a stall before the loop thread asks for SCHED_FIFO again; doubled each stall
RETRY_MAX = 60.0  # s, at most


class Scheduling:
    """The loop thread's scheduling over one SimLoop.run(): asked for after the first period
    (which may compile), given up while the loop is behind and asked for again once it has kept
    up for RETRY s (doubled after each stall, up to RETRY_MAX: a loop that cannot keep up at all
    starves its core for a moment a minute at most), restored when the run is over.

    Args:
      thread_priority: SCHED_FIFO's priority while pacing (0: do not ask).
      cpu_affinity: the cores to pin the thread to (empty: as it is).
      rtf: the loop's real-time factor (0, flat out: never SCHED_FIFO).
    """

    def __init__(self, thread_priority: int, cpu_affinity: Sequence[int], rtf: float):
        self.thread_priority = thread_priority
        self.cpu_affinity = tuple(cpu_affinity)
        self.rtf = rtf
        self.asked = False
        self.saved: Saved | None = None
        self._retry = RETRY
        self._retry_at: float | None = None  # when to ask for SCHED_FIFO again (None: not given up)
        self._said = False

    def elevate(self) -> None:
        self.asked = True
        # what start-up made is never scanned again: a full collection of a large fleet's
        # objects took 160-190 ms of one period (1024 arms with the bridge, H100 host)
        gc.collect()
        gc.freeze()
        priority = self.thread_priority if self.rtf > 0 else 0
        self.saved, problems = elevate(priority, self.cpu_affinity)
        for line in problems:
            log.warning("batchsim: warning: the loop thread runs without %s (its periods may run late under load)", line)

    def fell_behind(self, seconds: float, now: float) -> None:
        """A thread of SCHED_FIFO running flat out would starve its core: give it up (its cores
        stay) until the loop has kept up for a while, and say so the first time."""
        if self._retry_at is not None:  # given up already: the wait starts again from now
            self._retry_at = now + self._retry
            return
        if self.saved is None or not self.saved.fifo:
            return
        lower(self.saved)
        self.saved = dataclasses.replace(self.saved, fifo=False)
        self._retry_at = now + self._retry
        self._retry = min(RETRY_MAX, 2 * self._retry)
        if not self._said:
            self._said = True
            log.warning(
                "batchsim: warning: the loop fell %.1f s behind rtf %g: its thread gives up SCHED_FIFO until it has "
                "kept up for %g s, then asks again (after each stall, waiting twice as long, up to %g s; said once)",
                seconds, self.rtf, RETRY, RETRY_MAX,
            )  # fmt: skip

    def kept_up(self, now: float) -> None:
        """A period on time: SCHED_FIFO again once the wait after the last stall is over."""
        if self._retry_at is None or now < self._retry_at or self.saved is None:
            return
        self._retry_at = None
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(self.thread_priority))
            self.saved = dataclasses.replace(self.saved, fifo=True)
        except OSError:
            pass  # as it was: the normal policy

    def finish(self) -> None:
        """run() is over: scheduling and the collector as they were."""
        restore(self.saved)
        self.saved = None
        if self.asked:
            gc.unfreeze()
