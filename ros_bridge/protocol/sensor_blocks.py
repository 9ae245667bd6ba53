"""The sensor blocks: one camera's or lidar's images or scans of every world in shared
memory, seqlocked per world (the writer in the loop's process, the reader in a worker);
and what is asked of them: the want bits the workers set per world and sensor
(`sensors.want`: `WantWriter`, read by the loop with `wanted`) and the camera images the web
view shows, one per browser (`view.camera`: `CameraRequest`). No rclpy here. The layout of the blocks is
ros_bridge/sensor_topics.py's (`SensorPlan.arrays`).

Each reader keeps its own `seen` (the seq it last took, per world): the workers one each for
their worlds, a recording (ros_bridge/worker/sensor_recording.py) one for the recorded
worlds, in shared memory (`rec.sensors.seen`, recorded worlds x sensors) so that the writer
can wait for it where every sample must reach the file (`--rtf 0`). A reader that finds a
world's seq moved by more than 2 since `seen` missed the samples in between (overwritten
before it looked).
"""

from __future__ import annotations

import numpy as np

WANT_RGB = 1  # <camera>/image_raw, or a lidar's topic
WANT_DEPTH = 2  # <camera>/depth/image_raw
WANT_INFO = 4  # <camera>/camera_info (renders too: its stamps are the frames')
PART_BITS = {"rgb": WANT_RGB, "depth": WANT_DEPTH, "ranges": WANT_RGB}  # which rows a sample wrote


class SensorBlock:
    """One camera's or lidar's arrays in shared memory, and its per-world seqlock.

    Args:
      memory: the shared arrays (batchsim.memory.Memory, or anything indexable by name).
      prefix: "cam{k}" or "lid{k}".
      parts: the data arrays' names after the prefix ("rgb", "depth" or "ranges").
    """

    def __init__(self, memory, prefix: str, parts: tuple[str, ...]):
        self.data = {p: memory[f"{prefix}.{p}"] for p in parts}
        self.seq = memory[f"{prefix}.seq"]
        self.time = memory[f"{prefix}.time"]
        self.parts = memory[f"{prefix}.parts"]

    def write(self, worlds: np.ndarray, time: float, rows: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """Write a sample of `worlds` (n,): per part, (the worlds it is written for, their
        rows); seq goes odd, then even, so a reader never takes a torn row for whole."""
        self.seq[worlds] += 1
        self.parts[worlds] = 0
        for part, (where, values) in rows.items():
            if len(where):
                self.data[part][where] = values
                self.parts[where] |= PART_BITS[part]
        self.time[worlds] = time
        self.seq[worlds] += 1

    def read(self, lo: int, hi: int, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """The rows of worlds [lo, hi) written since `seen` ((hi - lo,) seq values, updated):
        (local rows (n,), which parts each holds (n,) PART_BITS, stamps (n,) f8 sim seconds,
        per part (n, ...) copies)."""
        return self.read_worlds(np.arange(lo, hi), seen)

    def read_worlds(
        self, worlds: np.ndarray, seen: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """`read` of any worlds ((k,) indices; `seen` (k,)): rows index `worlds`."""
        before = self.seq[worlds]
        rows = np.flatnonzero((before != seen) & (before % 2 == 0))
        if not rows.size:
            return rows, np.zeros(0, np.uint8), np.zeros(0), {}
        worlds = worlds[rows]
        time = self.time[worlds]
        parts = self.parts[worlds]
        data = {p: a[worlds] for p, a in self.data.items()}  # fancy indexing: copies
        whole = self.seq[worlds] == before[rows]  # not rewritten while we copied
        if not whole.all():  # those come again, newer, next time
            rows, time, parts = rows[whole], time[whole], parts[whole]
            data = {p: a[whole] for p, a in data.items()}
        seen[rows] = before[rows]
        return rows, parts, time, data


def want_arrays(nworld: int, nsensor: int) -> list[tuple[str, tuple[int, ...], str]]:
    """Per world and sensor (cameras, then lidars): the WANT_* bits of its topics someone subscribes to."""
    return [("sensors.want", (nworld, max(1, nsensor)), "u1")]


class WantWriter:
    """A worker's side: the want bits of its worlds [lo, hi)."""

    def __init__(self, memory, lo: int, hi: int):
        self._want = memory["sensors.want"][lo:hi]

    @property
    def nsensor(self) -> int:
        return self._want.shape[1]

    def put(self, bits: np.ndarray) -> None:
        """(hi - lo, nsensor) WANT_* bits, written at once."""
        self._want[:] = bits


def wanted(memory) -> np.ndarray:
    """The loop's side: (nworld, nsensor) u1, a copy of every world's want bits."""
    return memory["sensors.want"].copy()


MAX_VIEW_CAMERAS = 8  # the (world, camera) pairs the web view asks for at once: one per browser, at most


def camera_request_arrays() -> list[tuple[str, tuple[int, ...], str]]:
    """The (world, camera index) pairs whose images the web view shows, one per row (its
    browsers', each its picked world's); -1 in a row it does not use."""
    return [("view.camera", (MAX_VIEW_CAMERAS, 2), "i8")]


class CameraRequest:
    """The view process asks (`ask`, `clear`); the loop reads (`asked`) and renders each pair's
    camera of its world as though someone subscribed to its image (one render per camera,
    batched over the worlds asked). A torn read (a row's world new, its camera old) renders one
    period's wrong image: the view shows only frames rendered after it asked."""

    def __init__(self, memory):
        self._request = memory["view.camera"].reshape(-1, 2)

    @property
    def slots(self) -> int:
        """How many distinct pairs it holds at once (MAX_VIEW_CAMERAS)."""
        return self._request.shape[0]

    def ask(self, pairs) -> list[tuple[int, int]]:
        """Ask for `pairs` ((world, camera) each, the first most wanted) in place of what was
        asked: the first `slots` distinct ones. Returns those, in order; the others wait."""
        held = list(dict.fromkeys((int(w), int(c)) for w, c in pairs))[: self.slots]
        rows = np.full(self._request.shape, -1, np.int64)
        if held:
            rows[: len(held)] = held
        self._request[:] = rows
        return held

    def clear(self) -> None:
        self._request[:] = -1

    def asked(self) -> set[tuple[int, int]]:
        """The distinct (world, camera) pairs asked for (empty while the view shows none)."""
        return {(w, c) for w, c in self._request.tolist() if w >= 0 and c >= 0}


def gaps(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Per world, the samples a reader missed in one read, from its `seen` before and after
    (each write moves a world's seq by 2; a world not read, or read from its first sample,
    misses none)."""
    gap = (after - before) // 2 - 1
    return np.where((after != before) & (before >= 0), gap, 0).clip(min=0)


def missed(before: np.ndarray, after: np.ndarray) -> int:
    """`gaps`, summed over the worlds."""
    return int(gaps(before, after).sum())
