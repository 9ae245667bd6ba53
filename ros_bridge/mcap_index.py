"""The messages of chosen topics of a complete MCAP file, through its indexes. No rclpy here.

mcap's SeekingReader parses every record of every chunk it opens in Python: to reach a 1024-world
recording's /tf it walks millions of joint_states records (issue 46: `batchsim view` of a 256-world
recording printed nothing for 9 minutes). Here only the summary and the wanted channels' message
index records are read (a few bytes a message), and a message's bytes are cut from its chunk when
asked, the chunk decompressed once (the last few are kept). A file cut short has no summary:
`IndexedFile` raises NoIndex, and the caller reads it as a stream.
"""

from __future__ import annotations

import collections
import struct
from collections.abc import Callable, Iterable
from typing import Any, BinaryIO

import numpy as np

_INDEX_ENTRY = np.dtype([("time", "<u8"), ("offset", "<u8")])
_MESSAGE_HEAD = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel id, sequence, log time, publish time
CHUNKS_KEPT = 4  # decompressed chunks kept (a frame's messages are in one or two)


class NoIndex(Exception):
    """The file has no summary (cut short, or written without one)."""


class IndexedFile:
    """An open MCAP file's summary (`channels`, `schemas`), and its messages by index.

    Attributes:
      channels: channel id -> mcap Channel.
      schemas: schema id -> mcap Schema.
    """

    def __init__(self, stream: BinaryIO):
        from mcap.reader import SeekingReader

        self._stream = stream
        summary = SeekingReader(stream).get_summary()
        if summary is None or not summary.chunk_indexes:
            raise NoIndex
        self.channels = summary.channels
        self.schemas = summary.schemas
        self._chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
        self._data: collections.OrderedDict[int, bytes] = collections.OrderedDict()

    def channel_ids(self, wanted: Callable[[str], bool]) -> list[int]:
        """The channels whose topic `wanted` takes."""
        return [cid for cid, c in self.channels.items() if wanted(c.topic)]

    def index(self, channels: Iterable[int]) -> np.ndarray:
        """Every message of `channels`, sorted by log time: a structured array of `time` (ns),
        `chunk` (its chunk's number), `offset` (in the chunk's records) and `channel`."""
        wanted = set(channels)
        parts = []
        for k, chunk in enumerate(self._chunks):
            for cid, at in chunk.message_index_offsets.items():
                if cid not in wanted:
                    continue
                self._stream.seek(at + 1 + 8)  # past the record's opcode and length
                _cid, size = struct.unpack("<HI", self._stream.read(6))
                entries = np.frombuffer(self._stream.read(size), _INDEX_ENTRY)
                part = np.zeros(len(entries), _ENTRY)
                part["time"], part["offset"], part["chunk"], part["channel"] = entries["time"], entries["offset"], k, cid
                parts.append(part)
        out = np.concatenate(parts) if parts else np.zeros(0, _ENTRY)
        return out[np.argsort(out["time"], kind="stable")]

    def data(self, entry: Any) -> bytes:
        """One message's bytes (its serialized payload), of an `index` entry."""
        records = self._chunk(int(entry["chunk"]))
        at = int(entry["offset"])
        (length,) = struct.unpack_from("<Q", records, at + 1)
        return records[at + _MESSAGE_HEAD : at + 1 + 8 + length]

    def _chunk(self, k: int) -> bytes:
        if k in self._data:
            self._data.move_to_end(k)
            return self._data[k]
        from mcap.data_stream import ReadDataStream
        from mcap.records import Chunk
        from mcap.stream_reader import get_chunk_data_stream

        self._stream.seek(self._chunks[k].chunk_start_offset + 1 + 8)
        stream, size = get_chunk_data_stream(Chunk.read(ReadDataStream(self._stream)))
        data = stream.read(size)
        self._data[k] = data
        while len(self._data) > CHUNKS_KEPT:
            self._data.popitem(last=False)
        return data


_ENTRY = np.dtype([("time", "<u8"), ("chunk", "<i8"), ("offset", "<u8"), ("channel", "<u2")])
