"""A package build's stages as subprocesses, visible and safe to run twice at once: a line as each
starts and a "still <stage>, N s" line every progress_interval() s, its output in a log, a failure
naming the stage, its last lines and the log (BuildError); and the flock that lets one build of a
package run at a time (`lock`), saying whom it waits for. build.py builds the packages with them.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import shlex
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

PREFIX = "ros interfaces:"  # every line this module and `python -m ros_bridge.interfaces` print
PROGRESS_ENV = "BATCHSIM_INTERFACES_PROGRESS_S"  # seconds between "still ..." lines (default 10)
PROGRESS_S = 10.0
TAIL_LINES = 15  # lines of a failed stage's output in its error


class BuildError(RuntimeError):
    """A stage of a package's build failed; the message names the stage, its last lines and the log."""

    def __init__(self, message: str, *, label: str = "", stage: str = "", log: Path | None = None):
        super().__init__(message)
        self.label, self.stage, self.log = label, stage, log

    def short(self) -> str:
        """One line: what failed and where its whole output is."""
        where = f", log {self.log}" if self.log else ""
        return _named(self.label, f"{self.stage} failed{where}") if self.stage else str(self).splitlines()[0]


def _named(label: str, text: str) -> str:
    return f"{label}: {text}" if label else text


_SAY = threading.Lock()


def say(text: str) -> None:
    """One progress line on stdout, at once (whole: packages build in two threads)."""
    with _SAY:
        sys.stdout.write(f"{PREFIX} {text}\n")
        sys.stdout.flush()


def progress_interval() -> float:
    """Seconds between "still ..." lines: BATCHSIM_INTERFACES_PROGRESS_S, else 10."""
    try:
        value = float(os.environ.get(PROGRESS_ENV) or PROGRESS_S)
    except ValueError:
        value = PROGRESS_S
    return value if value > 0 else PROGRESS_S


def run_stage(label: str, stage: str, cmd: list[str], log_path: Path, env: dict[str, str] | None = None,
              detail: str = "") -> None:
    """Run `cmd`, its output appended to `log_path`: a line as it starts, a "still <stage>, N s"
    line every progress_interval() s while it runs; BuildError naming the stage, the last
    lines of its output and the log if it fails."""
    interval = progress_interval()
    with open(log_path, "ab") as log:
        log.write(f"\n$ {shlex.join(cmd)}\n".encode())
        log.flush()
        offset = log.tell()
        say(_named(label, stage + (f": {detail}" if detail else "") + " ..."))
        start = time.monotonic()
        try:
            proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        except OSError as error:
            raise BuildError(_named(label, f"{stage} could not start: {error}"), label=label, stage=stage,
                             log=log_path) from None
        try:
            ticks = 1
            while True:
                try:
                    code = proc.wait(timeout=max(0.0, start + ticks * interval - time.monotonic()))
                    break
                except subprocess.TimeoutExpired:
                    say(_named(label, f"still {stage}, {time.monotonic() - start:.0f} s"))
                    ticks += 1
        finally:
            if proc.poll() is None:  # interrupted: leave no compiler running
                proc.kill()
                proc.wait()
    if code != 0:
        took = time.monotonic() - start
        raise BuildError(
            _named(label, f"{stage} failed after {took:.0f} s (`{shlex.join(cmd)}` exited {code}); ")
            + f"its last lines:\n{_tail(log_path, offset)}\n  the whole output: {log_path}",
            label=label, stage=stage, log=log_path,
        )


def _tail(log_path: Path, offset: int) -> str:
    """The last TAIL_LINES lines written to `log_path` since `offset`, after the first error lines above them."""
    with open(log_path, "rb") as log:
        log.seek(offset)
        lines = [line for line in log.read().decode(errors="replace").splitlines() if line.strip()]
    tail = lines[-TAIL_LINES:]
    errors = [line for line in lines[:-TAIL_LINES] if re.search(r"\berror:|CMake Error|\*\*\* ", line)][:3]
    shown = [*errors, "..."] if errors else []
    return "\n".join(f"    | {line}" for line in [*shown, *tail]) or "    | (no output)"


@contextlib.contextmanager
def lock(path: Path, label: str, what: str = "another build") -> Iterator[bool]:
    """Hold an exclusive flock on `path` (made if missing); yield whether another holder made us wait.

    While waiting: a line naming the holder, then a "still waiting" line every progress_interval() s.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as handle:
        waited = not _try_lock(handle)
        if waited:
            holder = path.read_text().strip()
            say(_named(label, f"waiting for {what}'s lock{f' ({holder})' if holder else ''}: {path}"))
            start, ticks, interval = time.monotonic(), 1, progress_interval()
            while not _try_lock(handle):
                time.sleep(min(0.2, interval / 4))
                if time.monotonic() >= start + ticks * interval:
                    say(_named(label, f"still waiting for {what}'s lock, {time.monotonic() - start:.0f} s"))
                    ticks += 1
        try:
            handle.seek(0)
            handle.truncate()
            handle.write(f"pid {os.getpid()} on {socket.gethostname()}, for {sys.prefix}\n")
            handle.flush()
            yield waited
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _try_lock(handle) -> bool:
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


