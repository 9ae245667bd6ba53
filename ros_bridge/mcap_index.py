"""The messages of chosen topics of a complete MCAP file, through its indexes. No rclpy here.

mcap's SeekingReader parses every record of every chunk it opens in Python: to reach a 1024-world
recording's /tf it walks millions of joint_states records (issue 46: `batchsim view` of a 256-world
recording printed nothing for 9 minutes). Here only the summary and the wanted channels' message
index records are read (a few bytes a message), and a message's bytes are cut from its chunk when
asked, the chunk decompressed once (the last few are kept). A file cut short has no summary:
`IndexedFile` raises NoIndex, and the caller reads it as a stream.

The summary is read here too (`read_summary`), its chunk indexes' per-channel offsets as NumPy
arrays: mcap's reader parses each (channel, offset) pair in Python, 12 million of them in a
1024-world, 60 s recording (each chunk index lists every channel), 48 s under the profiler.
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
        self._stream = stream
        self.channels, self.schemas, chunks = read_summary(stream)
        if not chunks:
            raise NoIndex
        self._chunks = sorted(chunks, key=lambda c: c.start)
        self._data: collections.OrderedDict[int, bytes] = collections.OrderedDict()

    def channel_ids(self, wanted: Callable[[str], bool]) -> list[int]:
        """The channels whose topic `wanted` takes."""
        return [cid for cid, c in self.channels.items() if wanted(c.topic)]

    def index(self, channels: Iterable[int]) -> np.ndarray:
        """Every message of `channels`, sorted by log time: a structured array of `time` (ns),
        `chunk` (its chunk's number), `offset` (in the chunk's records) and `channel`."""
        wanted = np.array(sorted(set(channels)), np.uint16)
        parts = []
        for k, chunk in enumerate(self._chunks):
            offsets = chunk.offsets[np.isin(chunk.offsets["channel"], wanted)]
            for cid, at in zip(offsets["channel"].tolist(), offsets["offset"].tolist(), strict=True):
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

        self._stream.seek(self._chunks[k].start + 1 + 8)
        stream, size = get_chunk_data_stream(Chunk.read(ReadDataStream(self._stream)))
        data = stream.read(size)
        self._data[k] = data
        while len(self._data) > CHUNKS_KEPT:
            self._data.popitem(last=False)
        return data


_ENTRY = np.dtype([("time", "<u8"), ("chunk", "<i8"), ("offset", "<u8"), ("channel", "<u2")])


# --- the summary section ---
_OFFSET = np.dtype([("channel", "<u2"), ("offset", "<u8")])  # a chunk index's message index offsets, packed
_SCHEMA, _CHANNEL, _CHUNK_INDEX, _FOOTER = 0x03, 0x04, 0x08, 0x02


class ChunkEntry:
    """One chunk index: where its chunk `start`s in the file, and `offsets`, each channel's
    message index record there (a structured array of `channel`, `offset`)."""

    __slots__ = ("start", "offsets")

    def __init__(self, start: int, offsets: np.ndarray):
        self.start, self.offsets = start, offsets


def read_summary(stream: BinaryIO) -> tuple[dict[int, Any], dict[int, Any], list[ChunkEntry]]:
    """A complete file's channels and schemas (mcap's records) and chunk indexes, from its summary
    section. NoIndex where the file has none (cut short, or written without one)."""
    from mcap.records import Channel, Schema

    stream.seek(0, 2)
    size = stream.tell()
    if size < 8 + 37 + 8:
        raise NoIndex
    stream.seek(size - 8 - 29)  # the footer record: opcode, length, summary start, summary offset start, crc
    footer = stream.read(29)
    if footer[0] != _FOOTER:
        raise NoIndex
    (start,) = struct.unpack_from("<Q", footer, 9)
    if start == 0:
        raise NoIndex
    stream.seek(start)
    data = stream.read(size - 8 - 29 - start)
    channels: dict[int, Any] = {}
    schemas: dict[int, Any] = {}
    chunks: list[ChunkEntry] = []
    at = 0
    while at + 9 <= len(data):
        op, length = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        body = at + 9
        if op == _SCHEMA:
            sid, = struct.unpack_from("<H", data, body)
            name, p = _string(data, body + 2)
            encoding, p = _string(data, p)
            (n,) = struct.unpack_from("<I", data, p)
            schemas[sid] = Schema(id=sid, name=name, encoding=encoding, data=bytes(data[p + 4 : p + 4 + n]))
        elif op == _CHANNEL:
            cid, sid = struct.unpack_from("<HH", data, body)
            topic, p = _string(data, body + 4)
            encoding, p = _string(data, p)
            metadata, p = _string_map(data, p)
            channels[cid] = Channel(id=cid, schema_id=sid, topic=topic, message_encoding=encoding, metadata=metadata)
        elif op == _CHUNK_INDEX:
            chunk_start, = struct.unpack_from("<Q", data, body + 16)
            (n,) = struct.unpack_from("<I", data, body + 32)
            chunks.append(ChunkEntry(chunk_start, np.frombuffer(data, _OFFSET, n // _OFFSET.itemsize, body + 36).copy()))
        at = body + length
    return channels, schemas, chunks


def _string(data: bytes, at: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", data, at)
    return data[at + 4 : at + 4 + n].decode(), at + 4 + n


def _string_map(data: bytes, at: int) -> tuple[dict[str, str], int]:
    (n,) = struct.unpack_from("<I", data, at)
    end, p, out = at + 4 + n, at + 4, {}
    while p < end:
        key, p = _string(data, p)
        out[key], p = _string(data, p)
    return out, end
