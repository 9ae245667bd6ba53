"""Which batchsim processes of this host serve which namespaces, per ROS domain. No rclpy here.

A process that is about to serve namespaces registers them in a file it keeps locked
(flock) for as long as it lives; one that finds a live entry overlapping its own, or a
second /clock source, is refused at once. This makes the common mistake (a second fleet
started on the same domain on the same machine) certain to be caught, whatever DDS
discovery takes; fleets on other hosts are found in the ROS graph (worker.check_conflicts).

    registry = Registry.for_domain()
    registry.claim("batchsim_0_15", namespaces, clock=True)   # None, or (ConflictKind, message)
    ...
    registry.release()
"""

from __future__ import annotations

import enum
import fcntl
import json
import os
import tempfile
from pathlib import Path

from batchsim.types import AnyCase

ROOT = Path(tempfile.gettempdir()) / "batchsim-fleets"


class ConflictKind(AnyCase, enum.Enum):
    """What another live fleet already serves (`FleetConflict.kind`); the worker process
    reports it by value on its status pipe (`conflict namespace ...`)."""

    NAMESPACE = "namespace"  # one of this fleet's world namespaces
    CLOCK = "clock"  # /clock, which one process of a fleet may publish


class Registry:
    """This process's entry among the live batchsim processes of one ROS domain on this host.

    Args:
      directory: the domain's directory of entries.
    """

    def __init__(self, directory: Path):
        self.directory = directory
        self._fd: int | None = None
        self._path: Path | None = None

    @classmethod
    def for_domain(cls, domain: str | None = None, root: Path = ROOT) -> Registry:
        """The registry of `domain` (default: $ROS_DOMAIN_ID, else 0)."""
        domain = domain if domain is not None else os.environ.get("ROS_DOMAIN_ID", "0") or "0"
        return cls(root / f"domain_{domain}")

    def claim(self, node: str, namespaces: list[str], clock: bool) -> tuple[ConflictKind, str] | None:
        """Register; or return (kind, message) naming the live process this one would clash
        with (NAMESPACE: it serves one of `namespaces`; CLOCK: it publishes /clock too)."""
        self.directory.mkdir(parents=True, exist_ok=True, mode=0o777)
        guard = os.open(self.directory / ".lock", os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(guard, fcntl.LOCK_EX)  # one process checks and registers at a time
            mine = set(namespaces)
            for entry in sorted(self.directory.glob("*.json")):
                other = _read_live(entry)
                if other is None:
                    continue
                clash = sorted(mine & set(other["namespaces"]))
                if clash:
                    more = f" and {len(clash) - 1} more" if len(clash) > 1 else ""
                    return (
                        ConflictKind.NAMESPACE,
                        f"another batchsim process already serves /{clash[0]}{more} (node /{other['node']}, "
                        f"pid {other['pid']}): give this one other worlds (a world offset or another namespace "
                        "template) or another ROS domain",
                    )
                if clock and other["clock"]:
                    return (
                        ConflictKind.CLOCK,
                        f"another process already publishes /clock (node /{other['node']}, pid {other['pid']}): "
                        "only one process of a fleet may",
                    )
            path = self.directory / f"{os.getpid()}_{node}.json"  # a process may serve several groups of worlds
            fd = os.open(path, os.O_CREAT | os.O_RDWR | os.O_TRUNC, 0o666)
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.write(fd, json.dumps({"pid": os.getpid(), "node": node, "clock": clock, "namespaces": namespaces}).encode())
            self._fd, self._path = fd, path
            return None
        finally:
            os.close(guard)

    def release(self) -> None:
        """Leave the registry (also done by the kernel when the process dies). Idempotent."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if self._path is not None:
                self._path.unlink(missing_ok=True)
        finally:
            os.close(fd)


def _read_live(entry: Path) -> dict | None:
    """An entry's contents if its process still holds it; a dead process's entry is removed."""
    try:
        fd = os.open(entry, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:  # held: its process is alive
            try:
                return json.loads(entry.read_text())
            except (OSError, ValueError):
                return None
        entry.unlink(missing_ok=True)  # nobody holds it: its process is gone
        return None
    finally:
        os.close(fd)
