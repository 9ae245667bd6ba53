"""The host side of the warp engine's arrays: the host arrays the contract reads and writes are
pinned (page-locked) memory that the device copies into directly, so read() costs one DMA per
array and no host copy. `WarpEngine.bind` makes them (`pin`).

A fleet's shard (batchsim.backends.sharded) reads into the fleet's arrays instead, binding
them a second time (`follow`): its rows of a shared-memory segment, or of the fleet's own
memory when the shards are threads. That memory is page-locked here too, the whole buffer
once per process (cuMemHostRegister, CU_MEMHOSTREGISTER_PORTABLE: every device's context
sees it as pinned), and unlocked when the last engine reading into it is gone. Where the
driver refuses, the copies still work, through the driver's pageable path (slower).
"""

from __future__ import annotations

import ctypes
import dataclasses
import logging
import threading
import weakref
from typing import Any

import numpy as np
import warp as wp

from batchsim.engine import EngineBuffers

log = logging.getLogger("batchsim.warp")

PAGE = 4096
_PORTABLE = 0x01  # CU_MEMHOSTREGISTER_PORTABLE
_SHARED = ("readings", "sensordata", "time", "command")  # the EngineBuffers arrays the device copies


def host_array(shape: tuple[int, ...], dtype: Any, cuda: bool) -> wp.array:
    """A zeroed host array: pinned (page-locked) where the device is a GPU."""
    return wp.zeros(shape, dtype=dtype, device="cpu", pinned=cuda)


@dataclasses.dataclass
class HostArrays:
    """EngineBuffers' readings, sensordata, time and command as Warp host arrays (float64), the
    ends of the device's copies (the arrays themselves on Warp's CPU device, whose kernels
    read and write them)."""

    readings: wp.array
    sensordata: wp.array
    time: wp.array
    command: wp.array


def pin(buffers: EngineBuffers, cuda: bool) -> tuple[HostArrays, EngineBuffers]:
    """Pinned arrays (on a GPU) holding `buffers`' values, and the buffers made of their views."""
    host = HostArrays(*(host_array(getattr(buffers, f).shape, wp.float64, cuda) for f in _SHARED))
    views = {}
    for field in _SHARED:
        views[field] = getattr(host, field).numpy()
        views[field][:] = getattr(buffers, field)
    return host, dataclasses.replace(buffers, **views)


def follow(host: HostArrays, buffers: EngineBuffers, device: Any, owner: object) -> HostArrays:
    """`host` with the arrays of `buffers` that are not its own (a fleet's) wrapped in their place,
    page-locked for `device` (a GPU) while `owner` lives: read() copies (a GPU) or gathers (Warp's
    CPU device) straight into them, and write() takes the commands straight from them."""
    arrays = {}
    for field in _SHARED:
        mine, given = getattr(host, field), getattr(buffers, field)
        ours = given.ctypes.data == mine.ptr and given.shape == tuple(mine.shape)
        arrays[field] = mine if ours or not given.size else _wrap(given, device, owner)
    return HostArrays(**arrays)


def _wrap(array: np.ndarray, device: Any, owner: object) -> wp.array:
    """A Warp host array over `array`'s memory, page-locked for the device where it can be."""
    locked = lock_pages(array, device) if device.is_cuda else None
    if locked is not None:
        unlock = weakref.finalize(owner, unlock_pages, locked, device)
        unlock.atexit = False  # a process's end unlocks everything: no driver call as it tears down
    return wp.array(
        ptr=array.ctypes.data, dtype=wp.float64, shape=array.shape, device="cpu", pinned=locked is not None
    )


# ---------------------------------------------------------------- page-locking, per process

_lock = threading.Lock()
_locked: dict[int, list[Any]] = {}  # a locked buffer's first page -> [its users, the buffer, kept alive]
_driver: Any = None


def _cuda_driver() -> Any:
    global _driver
    if _driver is None:
        lib = ctypes.CDLL("libcuda.so.1")
        lib.cuMemHostRegister_v2.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint]
        lib.cuMemHostUnregister.argtypes = [ctypes.c_void_p]
        _driver = lib
    return _driver


def whole_buffer(array: np.ndarray) -> tuple[int, int, Any]:
    """The page-aligned (address, size) of the buffer `array` is a view of (a shared-memory
    mapping, or the NumPy array that owns the memory), and that buffer."""
    owner: Any = array
    while isinstance(owner, np.ndarray) and owner.base is not None:
        owner = owner.base
    flat = owner if isinstance(owner, np.ndarray) else np.frombuffer(owner, np.uint8)
    start, end = flat.ctypes.data, flat.ctypes.data + flat.nbytes
    start -= start % PAGE
    end += -end % PAGE
    return start, end - start, owner


def lock_pages(array: np.ndarray, device: Any) -> int | None:
    """Page-lock the buffer under `array` for the CUDA devices of this process (once per
    buffer, counted): its address, for unlock_pages; None where the driver refuses."""
    address, size, owner = whole_buffer(array)
    with _lock:
        entry = _locked.get(address)
        if entry is not None:
            entry[0] += 1
            return address
        try:
            with wp.ScopedDevice(device):  # the driver call needs a current context
                code = _cuda_driver().cuMemHostRegister_v2(address, size, _PORTABLE)
        except OSError as e:
            code = str(e)
        if code != 0:
            log.info("batchsim: warp: the fleet's arrays are not page-locked (cuMemHostRegister: %s); reads copy through pageable memory", code)
            return None
        _locked[address] = [1, owner]
        return address


def unlock_pages(address: int, device: Any) -> None:
    """lock_pages undone by one of the users of the buffer at `address`; the last unlocks it."""
    with _lock:
        entry = _locked.get(address)
        if entry is None:
            return
        entry[0] -= 1
        if entry[0] > 0:
            return
        del _locked[address]
        try:
            with wp.ScopedDevice(device):
                _cuda_driver().cuMemHostUnregister(address)
        except Exception:  # a process at its exit, its contexts gone: the pages go with it
            pass
