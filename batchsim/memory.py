"""Shared memory between the physics process and its helper processes (the ROS bridge's
workers, a fleet's per-device shard processes): named NumPy arrays in one segment, and
single-producer single-consumer byte rings for variable-size messages.

    layout = Layout([("state", (nworld, 36), "f8"), ("seq", (2,), "i8")])
    memory = Memory.create(layout)                 # the physics process: creates, unlinks
    memory = Memory.attach(layout, memory.name)    # a worker: same arrays, never unlinks
    memory["state"][3] = ...

Only the process that creates a segment unlinks it. On Python < 3.13 a process that
attaches also registers the segment with its resource tracker, which would unlink it when
that process exits; `attach` undoes that registration. A physics process killed outright
still has its segment unlinked by its own resource tracker.
"""

from __future__ import annotations

import dataclasses
import math
import os
import secrets
import struct
from collections.abc import Iterator, Sequence
from multiprocessing import resource_tracker, shared_memory

import numpy as np

ALIGN = 64  # bytes: every array starts on a cache line, so two writers never share one
PREFIX = "batchsim_"  # segment names: batchsim_<pid of the creator>_<random>, in /dev/shm on Linux


SHM = "/dev/shm"  # where Linux keeps POSIX shared memory (a tmpfs; a container's is 64 MiB by default)


class SharedMemoryFull(ValueError):
    """The shared-memory filesystem has no room for a fleet's segment: one line, naming what is needed."""


def check_room(nbytes: int, where: str = SHM) -> None:
    """Raise SharedMemoryFull unless `where` has `nbytes` free. A segment takes its pages as they
    are written, so one that does not fit dies of SIGBUS at the first page that finds no room,
    in whichever process writes it (the whole fleet, no line said). Checked against the whole
    segment: its camera blocks are written once someone subscribes to every camera."""
    try:
        st = os.statvfs(where)
    except OSError:
        return  # not Linux's tmpfs: nothing to ask
    free = st.f_bavail * st.f_frsize
    if nbytes > free:
        mib = 1 << 20
        raise SharedMemoryFull(
            f"shared memory: this fleet needs {nbytes / mib:.0f} MiB in {where} and {free / mib:.0f} MiB "
            f"are free (of {st.f_blocks * st.f_frsize / mib:.0f}); free some (segments left by killed "
            f"runs: ls {where}) or make it larger (a container: docker run --shm-size=...)"
        )


@dataclasses.dataclass(frozen=True)
class ArraySpec:
    """One array of a Layout: its name, shape and dtype (a NumPy dtype string)."""

    name: str
    shape: tuple[int, ...]
    dtype: str

    @property
    def nbytes(self) -> int:
        return int(np.dtype(self.dtype).itemsize * math.prod(self.shape))


class Layout:
    """Where each named array lies in one block of memory. Picklable: both sides of a
    process boundary build the same views from it."""

    def __init__(self, arrays: Sequence[tuple[str, tuple[int, ...], str]]):
        self.arrays: list[ArraySpec] = []
        self.offsets: dict[str, int] = {}
        offset = 0
        for name, shape, dtype in arrays:
            if name in self.offsets:
                raise ValueError(f"array {name!r} is laid out twice")
            spec = ArraySpec(name, tuple(int(n) for n in shape), dtype)
            self.arrays.append(spec)
            self.offsets[name] = offset
            offset += -(-max(spec.nbytes, 1) // ALIGN) * ALIGN
        self.nbytes = max(offset, ALIGN)

    def __contains__(self, name: str) -> bool:
        return name in self.offsets

    def views(self, buffer: memoryview | bytearray | np.ndarray) -> dict[str, np.ndarray]:
        out = {}
        for spec in self.arrays:
            out[spec.name] = np.ndarray(spec.shape, spec.dtype, buffer=buffer, offset=self.offsets[spec.name])
        return out


class Memory:
    """The arrays of a Layout, in a shared memory segment or in this process's own memory.

    Attributes:
      name: the segment's name (None for local memory); what a worker attaches to.
    """

    def __init__(self, layout: Layout, segment: shared_memory.SharedMemory | None, owner: bool):
        self.layout = layout
        self._segment = segment
        self._owner = owner
        # calloc'd: pages cost nothing until written (camera blocks are mostly never written)
        self._local = np.zeros(layout.nbytes, np.uint8) if segment is None else None
        buffer = segment.buf if segment is not None else self._local
        self._arrays = layout.views(buffer)
        self.name = segment.name if segment is not None else None

    @classmethod
    def create(cls, layout: Layout, *, shared: bool = True) -> Memory:
        """Zeroed arrays; in a new shared segment unless `shared` is False (one process)."""
        if not shared:
            return cls(layout, None, owner=True)
        check_room(layout.nbytes)
        name = f"{PREFIX}{os.getpid()}_{secrets.token_hex(4)}"
        # a new segment reads as zeros (ftruncate) and takes pages only as they are written:
        # not touching them keeps a fleet's unused camera blocks free
        segment = shared_memory.SharedMemory(name=name, create=True, size=layout.nbytes)
        return cls(layout, segment, owner=True)

    @classmethod
    def attach(cls, layout: Layout, name: str) -> Memory:
        """The arrays of a segment another process created; this process never unlinks it."""
        segment = shared_memory.SharedMemory(name=name)
        if not name.startswith(f"{PREFIX}{os.getpid()}_"):
            # Python < 3.13 registers attached segments too, to unlink them at exit: only the
            # creator may (one that this process created itself stays registered, once)
            try:
                resource_tracker.unregister(segment._name, "shared_memory")  # noqa: SLF001 (the stdlib's own name)
            except Exception:
                pass
        if segment.size < layout.nbytes:
            raise ValueError(f"shared memory {name!r} holds {segment.size} bytes, the layout needs {layout.nbytes}")
        return cls(layout, segment, owner=False)

    def __getitem__(self, name: str) -> np.ndarray:
        return self._arrays[name]

    def __contains__(self, name: str) -> bool:
        return name in self._arrays

    def close(self) -> None:
        """Drop the views and the mapping; the creator also unlinks the segment. Idempotent."""
        self._arrays = {}
        segment, self._segment = self._segment, None
        if segment is None:
            return
        try:
            segment.close()
        except BufferError:  # a view is still alive somewhere: the mapping goes with the process
            pass
        if self._owner:
            try:
                segment.unlink()
            except FileNotFoundError:
                pass


# --- byte rings ---

_HEADER = struct.Struct("<II")  # record length in bytes (header included, padded to 8), kind
PAD = 0  # a record kind that fills the ring's tail up to its end


def ring_arrays(name: str, capacity: int) -> list[tuple[str, tuple[int, ...], str]]:
    """The Layout entries of one ring: its two positions and its bytes."""
    capacity = -(-capacity // 8) * 8
    return [(f"{name}.pos", (2,), "i8"), (f"{name}.data", (capacity,), "u1")]


class Ring:
    """A single-producer single-consumer ring of byte records in shared memory.

    The producer owns `pos[0]` (bytes written, ever) and the consumer `pos[1]` (bytes
    read); each only ever increases, so a new producer (a restarted worker) continues where
    the old one stopped and nothing is replayed. A record is visible once the producer
    has advanced `pos[0]` past it, after writing it whole.
    """

    def __init__(self, memory: Memory, name: str):
        self.pos = memory[f"{name}.pos"]
        self.data = memory[f"{name}.data"]
        self.capacity = self.data.size

    def put(self, kind: int, payload: bytes | memoryview | np.ndarray) -> bool:
        """Append one record; False (nothing written) when the ring lacks room for it."""
        if isinstance(payload, np.ndarray):
            body = np.ascontiguousarray(payload).view(np.uint8).reshape(-1)
        else:
            body = np.frombuffer(payload, np.uint8)
        size = _HEADER.size + len(body)
        padded = -(-size // 8) * 8
        if padded > self.capacity // 2:
            return False
        write, read = int(self.pos[0]), int(self.pos[1])
        at = write % self.capacity
        tail = self.capacity - at
        need = padded + (tail if tail < padded else 0)
        if self.capacity - (write - read) < need:
            return False
        if tail < padded:  # the record does not fit before the end: pad the tail, start over
            self.data[at : at + _HEADER.size] = np.frombuffer(_HEADER.pack(tail, PAD), np.uint8)
            write += tail
            at = 0
        self.data[at + _HEADER.size : at + size] = body
        # zeros to the 8-byte boundary: take() hands these bytes out with the payload, and a record
        # read as text (a JSON document, rstripped of NULs) must not end in an older record's bytes
        self.data[at + size : at + padded] = 0
        self.data[at : at + _HEADER.size] = np.frombuffer(_HEADER.pack(padded, kind), np.uint8)
        self.pos[0] = write + padded
        return True

    def take(self) -> Iterator[tuple[int, np.ndarray]]:
        """Every record written so far, as (kind, a copy of its payload)."""
        write, read = int(self.pos[0]), int(self.pos[1])
        while read < write:
            at = read % self.capacity
            length, kind = _HEADER.unpack_from(self.data, at)
            if length < _HEADER.size or length > self.capacity:  # never written whole: resync
                read = write
                break
            if kind != PAD:
                yield kind, self.data[at + _HEADER.size : at + length].copy()
            read += length
            self.pos[1] = read
        self.pos[1] = read

    @property
    def used(self) -> int:
        return int(self.pos[0] - self.pos[1])
