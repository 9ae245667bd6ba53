"""A world's status in words: the contract's `Status` bits and the bridge's FLAG_* bits (plan.py)
as a diagnostic level and a message, written once for the live /diagnostics
(worker/diagnostics.py), a recording's /diagnostics (worker/recorder.py) and the view's panel
(worker/view.py, view_file.py), and read back from a recorded DiagnosticStatus's key values.
No rclpy here.
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Mapping

from batchsim.types import FROZEN, Status
from ros_bridge.plan import FLAG_BAD, FLAG_FROZEN, FLAG_TIMED_OUT

FROZEN_NOTE = " (frozen until reset: its state topics stopped)"


class Level(enum.IntEnum):
    """diagnostic_msgs/DiagnosticStatus's levels."""

    OK = 0
    WARN = 1
    ERROR = 2


def status_name(namespace: str) -> str:
    """A world's DiagnosticStatus name (its hardware_id is the namespace)."""
    return f"batchsim: {namespace}"


@functools.lru_cache(maxsize=1024)
def problems(bits: int, flags: int) -> tuple[str, ...]:
    """The status bits' names (`diverged`, `bad_command`, ...), and `command_timeout`.
    Cached: /diagnostics asks for every world every 0.5 s, and a walk over the Status enum
    was a third of a 512-world worker's 17 ms there (2-core VM)."""
    out = [s.name.lower() for s in Status if s and bits & s]
    if flags & FLAG_TIMED_OUT:
        out.append("command_timeout")
    return tuple(out)


def level(bits: int, flags: int) -> Level:
    if bits & FROZEN:
        return Level.ERROR
    return Level.WARN if problems(bits, flags) else Level.OK


def message(bits: int, flags: int, last: str = "") -> str:
    """/diagnostics' message for a world: `ok`, or its problems; `last`: its last rejected command."""
    text = ", ".join(problems(bits, flags)) or "ok"
    if flags & FLAG_FROZEN:
        text += FROZEN_NOTE
    if flags & FLAG_BAD and last:
        text += f" ({last})"
    return text


@functools.lru_cache(maxsize=1024)
def values(bits: int, flags: int) -> tuple[tuple[str, str], ...]:
    """The key values a world's DiagnosticStatus starts with (`from_values` reads them back)."""
    return (
        ("status", str(bits)),
        ("frozen", str(bool(flags & FLAG_FROZEN)).lower()),
        ("bad_command", str(bool(flags & FLAG_BAD)).lower()),
        ("command_timeout", str(bool(flags & FLAG_TIMED_OUT)).lower()),
    )


def from_values(kv: Mapping[str, str]) -> tuple[int, int]:
    """(status bits, flags) of a DiagnosticStatus's key values."""
    flags = 0
    for key, flag in (("frozen", FLAG_FROZEN), ("bad_command", FLAG_BAD), ("command_timeout", FLAG_TIMED_OUT)):
        if kv.get(key) == "true":
            flags |= flag
    return int(kv.get("status", "0") or 0), flags


def status_text(bits: int, flags: int) -> str:
    """One world's state, as the view's panel says it."""
    parts = []
    if flags & FLAG_FROZEN or bits & FROZEN:
        why = "diverged" if bits & Status.DIVERGED else "contact buffer overflow"
        parts.append(f"frozen ({why}) until reset")
    if flags & FLAG_BAD or bits & Status.BAD_COMMAND:
        parts.append("bad command")
    if flags & FLAG_TIMED_OUT:
        parts.append("command timeout: holding")
    return ", ".join(parts) or "running"
