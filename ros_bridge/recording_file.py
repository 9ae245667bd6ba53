"""Whether a file is a recording (`batchsim --record`'s MCAP) and whether it is complete: what
`batchsim replay` (worker/replay.py, over rclpy) and `batchsim view FILE` (view_file.py, which
needs no ROS 2) both check first. Nothing here imports rclpy."""

from __future__ import annotations

import struct

MAGIC = b"\x89MCAP0\r\n"


class ReplayError(ValueError):
    """A file that cannot be replayed or viewed, or a selection it does not hold: one line."""


def check_file(path: str) -> bool:
    """ReplayError unless `path` is an MCAP file; True if it is complete (its closing magic is there)."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MAGIC))
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - len(MAGIC)))
            tail = f.read(len(MAGIC))
    except IsADirectoryError:
        raise ReplayError(f"{path} is a directory, not an MCAP file") from None
    except OSError as e:
        raise ReplayError(f"{path}: {e.strerror}") from None
    if head != MAGIC:
        raise ReplayError(f"{path} is not an MCAP file (it does not start with MCAP's magic bytes)")
    return size > 2 * len(MAGIC) and tail == MAGIC


def cut_short_errors() -> tuple[type[BaseException], ...]:
    """What mcap's readers raise where a file ends inside a record (a struct.error from a short
    read, an EOFError, ...): the end of what can be read of a file cut short, else unreadable."""
    from mcap.exceptions import McapError  # the record extra; this module is read without it

    return (McapError, struct.error, EOFError, ValueError, OSError)
