"""Rate-limited log lines: one line per key (a topic and a reason) per window, and a line
with the count held back when a window closes; and how a helper process ended, in words
(`how_ended`). No rclpy here.

    throttle = LogThrottle(logger.warning, interval=2.0)
    throttle.warn(("/world_3/commands", Problem.NOT_FINITE), "rejected command on ...: value nan ...")
    throttle.flush()   # now and then: windows that closed with lines held back say how many
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Hashable

LOG_INTERVAL = 2.0  # s of wall time: one line per key and window


class LogThrottle:
    """At most one line per key every `interval` seconds, and a summary of what it held back.

    Thread-safe: ROS callbacks and the loop thread may warn at once.

    Args:
      emit: writes one line (a logger's warning method, `print`).
      interval: the window, seconds.
      clock: monotonic seconds (tests pass a fake).
    """

    def __init__(
        self,
        emit: Callable[[str], None],
        interval: float = LOG_INTERVAL,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.emit = emit
        self.interval = interval
        self.clock = clock
        self._lock = threading.Lock()
        # key -> [window start, lines held back, the last line held back]
        self._open: dict[Hashable, list] = {}

    def warn(self, key: Hashable, text: str) -> bool:
        """Log `text` unless a line of `key` was logged less than `interval` ago; True if logged."""
        now = self.clock()
        out: list[str] = []
        with self._lock:
            window = self._open.get(key)
            if window is not None and now - window[0] < self.interval:
                window[1] += 1
                window[2] = text
                return False
            if window is not None and window[1]:
                out.append(self._summary(window))
            self._open[key] = [now, 0, ""]
            out.append(text)
        for line in out:
            self.emit(line)
        return True

    def flush(self) -> None:
        """Close the windows that have run out: one line each for those that held lines back."""
        now = self.clock()
        out: list[str] = []
        with self._lock:
            for key in [k for k, w in self._open.items() if now - w[0] >= self.interval]:
                window = self._open.pop(key)
                if window[1]:
                    out.append(self._summary(window))
        for line in out:
            self.emit(line)

    def _summary(self, window: list) -> str:
        n = window[1]
        return f"{window[2]} ({n} {'line' if n == 1 else 'lines'} like it held back in {self.interval:g} s)"


def how_ended(code: int) -> str:
    """How a helper process ended, from its exit status (a subprocess returncode)."""
    return f"was killed by signal {-code}" if code < 0 else f"exited with code {code}"
