"""Text in shared memory: utf-8 in a NUL-padded byte row (a rejection's reason, a service's
answer, a world's draw). No rclpy here."""

from __future__ import annotations

import numpy as np


def put_text(row: np.ndarray, text: str) -> None:
    """`text` into `row` ((n,) u1), clipped to the row, the rest NULs."""
    data = text.encode("utf-8", "replace")[: len(row)]
    row[: len(data)] = np.frombuffer(data, np.uint8)
    row[len(data) :] = 0


def text_of(row: np.ndarray) -> str:
    """The text `row` holds: up to its first NUL."""
    return row.tobytes().split(b"\0", 1)[0].decode("utf-8", "replace")
