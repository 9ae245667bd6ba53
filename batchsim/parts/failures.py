"""Failed worlds, said once each: rate-limited log lines, and where MuJoCo's own log goes.

A world that diverges or overflows is frozen by the contract (`batchsim.hardware`); this
module tells the user, through Python `logging` (logger `batchsim.<backend>`), one line per
world naming it and the reason, at most `BURST` such lines per `WINDOW` seconds: 8192 worlds
diverging in one period give three lines and one with the count, not 8192.

MuJoCo itself reports the same event as a raw `WARNING: Nan, Inf or huge value in QACC ...`
on stderr, once per world, and appends it to `MUJOCO_LOG.TXT` in the working directory.
`set_log_dir` sends that log to a directory of the user's choosing and takes it off the
console, through MuJoCo's own default handler (`mju_setLogConfig`, bound as
`mujoco.MjLogConfig.set`): a C handler, so `mujoco.batch`'s worker threads write through it
without entering Python. A Python handler (`mujoco.set_mju_user_warning`) is called from
those threads too and has to take the GIL on each call; it is not needed here, because
batchsim reads every world's warnings from its counters after each step.
"""

from __future__ import annotations

import logging
import os
import tempfile
import time as wallclock
from collections.abc import Sequence
from pathlib import Path

import mujoco
import numpy as np

#: individual lines per window; the rest are counted into one line
BURST = 3
#: seconds of wall-clock time per window
WINDOW = 2.0
MUJOCO_LOG_NAME = "MUJOCO_LOG.TXT"

_mujoco_log: Path | None = None  # where set_log_dir sent MuJoCo's log, once it did


def default_log_dir() -> Path:
    """Where MuJoCo's log goes unless the user says: `$XDG_STATE_HOME/batchsim`, by default
    `~/.local/state/batchsim` (never the working directory)."""
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state) / "batchsim"


def set_log_dir(directory: str | Path | None = None) -> Path:
    """Send MuJoCo's own log to `directory/MUJOCO_LOG.TXT` (None: `default_log_dir()`), and no
    longer to the console. Process-wide, as MuJoCo's log is; returns the file's path.

    Raises ValueError naming the directory if it cannot be created or the path is too long
    for MuJoCo (1023 bytes).
    """
    global _mujoco_log
    folder = Path(directory).expanduser() if directory is not None else default_log_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"log directory {str(folder)!r}: {e.strerror or e}") from None
    path = folder.resolve() / MUJOCO_LOG_NAME
    if len(os.fsencode(str(path))) >= 1024:
        raise ValueError(f"log directory {str(folder)!r}: the path is too long for MuJoCo (1023 bytes at most)")
    try:  # a folder the log can never be written to is refused now, not named in a line later
        with open(path, "a"):
            pass
    except OSError as e:
        raise ValueError(f"log directory {str(folder)!r}: cannot write {path.name} there: {e.strerror or e}") from None
    config = mujoco.MjLogConfig.get()
    config.logto_console = False  # batchsim logs its own line per failed world instead
    config.logto_file = True
    config.logfile = str(path)
    config.set()
    _mujoco_log = path
    return path


def mujoco_log_default() -> bool:
    """Whether MuJoCo's log is still as MuJoCo sets it up (console and ./MUJOCO_LOG.TXT)."""
    config = mujoco.MjLogConfig.get()
    return bool(config.logto_console) and config.logfile == MUJOCO_LOG_NAME


def ensure_log_dir() -> None:
    """Take MuJoCo's log out of the working directory unless someone already placed it: to
    `default_log_dir()`, or where that cannot be written, a folder in the temp directory."""
    if _mujoco_log is not None or not mujoco_log_default():
        return
    fallback = Path(tempfile.gettempdir()) / f"batchsim-{os.getuid() if hasattr(os, 'getuid') else 'user'}"
    for folder in (default_log_dir(), fallback):
        try:
            set_log_dir(folder)
            return
        except ValueError:
            continue


def mujoco_log() -> Path | None:
    """The file MuJoCo's log goes to, if batchsim placed it."""
    return _mujoco_log


def warning_text(warning: int, info: int) -> str:
    """MuJoCo's text for a warning (`mju_warningText`, e.g. "Nan, Inf or huge value in QACC at
    DOF 3"), its first sentence only."""
    text = mujoco.mju_warningText(int(warning), int(info))
    return text.split(". ")[0].rstrip(".")


class FailureLog:
    """One log line per failed world, rate-limited: `BURST` lines per `WINDOW` seconds, then
    one line with the count of those held back.

    `report` is called with the worlds that failed in one step() call; `flush` once per call
    however it went, so that a count held back is said once its window is over.
    """

    def __init__(self, backend: str, nworld: int, *, mujoco_logs: bool = False):
        """`mujoco_logs`: the engine is C MuJoCo, which logs these failures itself: the first
        line names the file its log went to."""
        self.log = logging.getLogger(f"batchsim.{backend}")
        self.prefix = f"batchsim: {backend}:"
        self.nworld = nworld
        self.offset = 0  # added to the worlds named: a shard's world i is the fleet's offset + i
        self._window_end = -np.inf
        self._budget = BURST
        self._held: dict[str, list[int]] = {}  # what -> worlds held back this window
        self._said_where = not mujoco_logs

    def report(self, worlds: np.ndarray, what: Sequence[str], reasons: Sequence[str], times: np.ndarray) -> None:
        """Worlds that failed in one period. `what[i]` is a verb ("diverged", "overflowed"),
        `reasons[i]` says why, `times[i]` is the sim time the world is frozen at."""
        worlds = np.asarray(worlds) + self.offset
        now = wallclock.monotonic()
        if now >= self._window_end:
            self._say_held()
            self._window_end = now + WINDOW
            self._budget = BURST
        shown = min(self._budget, len(worlds))
        self._budget -= shown
        for i in range(shown):
            self.log.warning(
                "%s world %d %s at sim time %.4f s (%s); frozen until reset%s",
                self.prefix,
                int(worlds[i]),
                what[i],
                float(times[i]),
                reasons[i],
                self._where(),
            )
        rest: dict[str, list[int]] = {}
        for i in range(shown, len(worlds)):
            rest.setdefault(what[i], []).append(int(worlds[i]))
        if not rest:
            return
        if shown:  # many at once: the count now, in the same breath
            self._say(rest, "in the same period")
        else:
            for verb, ids in rest.items():
                self._held.setdefault(verb, []).extend(ids)

    def flush(self) -> None:
        """Say what was held back once its window is over (cheap when nothing was)."""
        if self._held and wallclock.monotonic() >= self._window_end:
            self._say_held()
            self._window_end = -np.inf

    def _say_held(self) -> None:
        if self._held:
            held, self._held = self._held, {}
            self._say(held, f"in the last {WINDOW:g} s")

    def _say(self, groups: dict[str, list[int]], when: str) -> None:
        for verb, ids in groups.items():
            shown = ", ".join(str(w) for w in ids[:8]) + (", ..." if len(ids) > 8 else "")
            self.log.warning(
                "%s %d more of %d worlds %s %s (worlds %s); frozen until reset",
                self.prefix,
                len(ids),
                self.nworld,
                verb,
                when,
                shown,
            )

    def _where(self) -> str:
        # once per system: where MuJoCo's own lines about it went
        if self._said_where or _mujoco_log is None:
            return ""
        self._said_where = True
        return f"; MuJoCo's log: {_mujoco_log}"
