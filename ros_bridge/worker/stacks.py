"""Where a worker's threads spend their time, sampled: a developer's tool for fleets that
fall behind (`BATCHSIM_WORKER_STACKS=DIR`: each worker process writes `DIR/worker_<index>.txt`
every 2 s, the most frequent innermost stacks of each of its threads, sampled every 5 ms).

A sample is taken only when the sampling thread gets the GIL, so time spent in a long C call
that holds it shows as the frame that made the call, after it returns; the counts are a guide.
"""

from __future__ import annotations

import collections
import os
import sys
import threading
import time

DEPTH = 6  # frames per stack, innermost first
PERIOD = 0.005  # s between samples
WRITE_EVERY = 2.0  # s between two writes of the file


def start(directory: str, index: int) -> None:
    """Sample this process's threads from now on, into `directory/worker_<index>.txt`."""
    path = os.path.join(directory, f"worker_{index}.txt")
    counts: collections.Counter[tuple[str, str]] = collections.Counter()
    names = {t.ident: t.name for t in threading.enumerate()}

    def sample() -> None:
        me = threading.get_ident()
        written = time.monotonic()
        while True:
            time.sleep(PERIOD)
            for ident, frame in sys._current_frames().items():
                if ident == me:
                    continue
                stack, f = [], frame
                while f is not None and len(stack) < DEPTH:
                    stack.append(f"{os.path.basename(f.f_code.co_filename)}:{f.f_lineno}:{f.f_code.co_name}")
                    f = f.f_back
                if ident not in names:
                    names.update({t.ident: t.name for t in threading.enumerate()})
                counts[(names.get(ident, str(ident)), " < ".join(stack))] += 1
            if time.monotonic() - written > WRITE_EVERY:
                written = time.monotonic()
                total = sum(counts.values()) or 1
                lines = [f"{n / total:6.1%}  {thread:24s} {stack}" for (thread, stack), n in counts.most_common(60)]
                with open(path, "w") as out:
                    out.write(f"{total} samples\n" + "\n".join(lines) + "\n")

    threading.Thread(target=sample, name="stack_sampler", daemon=True).start()
