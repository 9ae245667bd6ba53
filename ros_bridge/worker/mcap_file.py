"""An MCAP file written a block of messages at a time: `BlockWriter`.

mcap's own `Writer` takes one message per call (a Message record object, a record builder, a
message index entry: ~3.4 us of Python each), which caps one recorder process at ~300,000
messages a second before anything else is done; 1024 worlds x 2 topics x 100 Hz asks for
205,000. A period of a fleet is a block of equal-length messages (one output's rows of one
layout, `messages.BulkMessages`), so here a block's Message records, its message index
entries and its statistics are laid out with numpy, all at once, while the file's structure
stays mcap's: the records that are not per message (header, schemas, channels, metadata,
attachments, statistics, summary offsets, footer) are `mcap.records`' own, written the way
`mcap.writer.Writer` writes them (schemas and channels inside the chunks, every summary
group repeated, a summary offset per group, CRCs), so mcap's readers see what its writer
would have written. Chunks are compressed with zstd or lz4.
"""

from __future__ import annotations

import struct
import zlib
from collections import OrderedDict, deque
from concurrent.futures import ThreadPoolExecutor
from typing import BinaryIO

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAX_PENDING = 4  # closed chunks waiting for their compression before the writer waits too
ZSTD_LEVEL = 1  # a recorder's chunk: 640 MB/s at level 1, 340 at the default 3, the same size (fleet data)
MAGIC = bytes((137, 77, 67, 65, 80, 48, 13, 10))
MESSAGE_HEAD = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel, sequence, log time, publish time
_HEAD = np.dtype(
    [
        ("op", "u1"),
        ("length", "<u8"),
        ("channel", "<u2"),
        ("sequence", "<u4"),
        ("log_time", "<u8"),
        ("publish_time", "<u8"),
    ]
)
assert _HEAD.itemsize == MESSAGE_HEAD
INDEX_HEAD = 1 + 8 + 2 + 4  # a MessageIndex record: opcode, length, channel, its entries' bytes
_INDEX_HEAD = np.dtype([("op", "u1"), ("length", "<u8"), ("channel", "<u2"), ("bytes", "<u4")])
_ENTRY = np.dtype([("log_time", "<u8"), ("offset", "<u8")])
_WHERE = np.dtype([("channel", "<u2"), ("offset", "<u8")])  # the chunk index's message index offsets


def _compressor(compression: str):
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.compress
    if compression == "":
        return bytes
    raise ValueError(f"compression {compression!r}: zstd, lz4 or ''")


def message_records(channels: np.ndarray, sequences: np.ndarray, t: int, rows: np.ndarray) -> bytes:
    """The Message records of `rows` ((n, L) uint8 payloads), one per row, back to back.

    Args:
      channels: (n,) channel ids. sequences: (n,) their sequence numbers.
      t: the log and publish time (ns) of every one."""
    n, length = rows.shape
    block = np.empty((n, MESSAGE_HEAD + length), np.uint8)
    head = np.empty(n, _HEAD)
    head["op"] = Opcode.MESSAGE
    head["length"] = MESSAGE_HEAD - 9 + length
    head["channel"] = channels
    head["sequence"] = sequences
    head["log_time"] = t
    head["publish_time"] = t
    block[:, :MESSAGE_HEAD] = head.view(np.uint8).reshape(n, MESSAGE_HEAD)
    block[:, MESSAGE_HEAD:] = rows
    return block.tobytes()


class BlockWriter:
    """One MCAP file. The stream must be open for binary writing and support `tell()`.

    Args:
      stream: where the file goes.
      chunk_bytes: a chunk closes once its uncompressed records reach this size (and on `flush`).
      compression: "zstd", "lz4" or "" for none.
    """

    def __init__(self, stream: BinaryIO, chunk_bytes: int = 1 << 20, compression: str = "zstd"):
        self.stream = stream
        self.chunk_bytes = chunk_bytes
        self.compression = compression
        self._compress = _compressor(compression)
        self._schemas: OrderedDict[int, Schema] = OrderedDict()
        self._channels: OrderedDict[int, Channel] = OrderedDict()
        self._counts = np.zeros(1, np.int64)  # messages per channel id
        self._sequence = np.zeros(1, np.int64)  # the next sequence number per channel id
        self._chunk_indexes: list[bytes] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._start_time: int | None = None
        self._end_time = 0
        self._nchunk = 0
        # one thread: a ZstdCompressor is not thread-safe (two at once crashed the process)
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mcap-compress")
        self._pending: deque = deque()  # closed chunks: (data, index, start, end, compression job)
        self._new_chunk()

    # --- the per-message records of the open chunk ---
    def _new_chunk(self) -> None:
        self._parts: list[bytes] = []
        self._size = 0
        self._index: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # channels, times, offsets
        self._chunk_start: int | None = None
        self._chunk_end = 0

    def _append(self, data: bytes) -> None:
        self._parts.append(data)
        self._size += len(data)

    def _record(self, record) -> None:
        builder = RecordBuilder()
        record.write(builder)
        self._append(builder.end())

    def _grow(self, channel: int) -> None:
        if channel >= len(self._counts):
            more = max(channel + 1, 2 * len(self._counts))
            self._counts = np.concatenate([self._counts, np.zeros(more - len(self._counts), np.int64)])
            self._sequence = np.concatenate([self._sequence, np.zeros(more - len(self._sequence), np.int64)])

    # --- what the file holds ---
    def start(self, profile: str, library: str) -> None:
        self.stream.write(MAGIC)
        builder = RecordBuilder()
        Header(profile=profile, library=library).write(builder)
        self.stream.write(builder.end())

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas[schema.id] = schema
        self._record(schema)
        return schema.id

    def register_channel(
        self, topic: str, message_encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> int:
        channel = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata=metadata,
        )
        self._channels[channel.id] = channel
        self._grow(channel.id)
        self._record(channel)
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._out_of_chunk(
            Metadata(name=name, metadata=data),
            lambda offset, length: self._metadata_indexes.append(
                MetadataIndex(offset=offset, length=length, name=name)
            ),
        )

    def add_attachment(
        self, create_time: int, log_time: int, name: str, media_type: str, data: bytes
    ) -> None:
        self._out_of_chunk(
            Attachment(
                create_time=create_time, log_time=log_time, name=name, media_type=media_type, data=data
            ),
            lambda offset, length: self._attachment_indexes.append(
                AttachmentIndex(
                    offset=offset,
                    length=length,
                    create_time=create_time,
                    log_time=log_time,
                    data_size=len(data),
                    name=name,
                    media_type=media_type,
                )
            ),
        )

    def _out_of_chunk(self, record, index) -> None:
        """A record of the data section outside any chunk, and its summary index."""
        self._finish_chunk()
        self._write_chunks(every=True)
        builder = RecordBuilder()
        record.write(builder)
        data = builder.end()
        offset = self.stream.tell()
        self.stream.write(data)
        index(offset, len(data))

    def add_message(self, channel: int, t: int, data: bytes) -> None:
        """One message (log time = publish time = `t`, ns)."""
        self.add_block(np.array([channel]), t, np.frombuffer(data, np.uint8)[None, :])

    def add_block(self, channels: np.ndarray, t: int, rows: np.ndarray) -> None:
        """One message per row of `rows` ((n, L) uint8) on `channels` ((n,) distinct ids), all at `t` (ns)."""
        n = len(channels)
        if n == 0:
            return
        channels = np.asarray(channels, np.int64)
        sequences = self._sequence[channels]
        self._sequence[channels] += 1
        self._counts[channels] += 1
        offsets = self._size + np.arange(n, dtype=np.int64) * (MESSAGE_HEAD + rows.shape[1])
        self._append(message_records(channels, sequences & 0xFFFFFFFF, t, rows))
        self._index.append((channels, np.full(n, t, np.int64), offsets))
        self._chunk_start = t if self._chunk_start is None else min(self._chunk_start, t)
        self._chunk_end = max(self._chunk_end, t)
        if self._size >= self.chunk_bytes:
            self._finish_chunk()

    # --- chunks ---
    def _finish_chunk(self) -> None:
        """Close the open chunk. It is compressed on a thread (zstd lets go of the GIL) while the
        next one fills, and written, with its message indexes, in order (`_write_chunks`)."""
        if not self._index:  # no message yet: schemas and channels wait for the chunk that has one
            return
        data = b"".join(self._parts)
        job = self._pool.submit(self._pack, data)
        self._pending.append((data, self._index, self._chunk_start, self._chunk_end, job))
        self._new_chunk()
        self._write_chunks()

    def _pack(self, data: bytes) -> tuple[bytes, int]:
        return self._compress(data), zlib.crc32(data)

    def _write_chunks(self, every: bool = False) -> None:
        """Write the closed chunks whose compression is done, oldest first; with `every` (or
        more than MAX_PENDING waiting), wait for them."""
        while self._pending and (every or len(self._pending) > MAX_PENDING or self._pending[0][-1].done()):
            data, index, start, end, job = self._pending.popleft()
            packed, crc = job.result()
            builder = RecordBuilder()
            Chunk(
                compression=self.compression,
                data=packed,
                message_start_time=start,
                message_end_time=end,
                uncompressed_crc=crc,
                uncompressed_size=len(data),
            ).write(builder)
            record = builder.end()
            chunk_offset = self.stream.tell()
            self.stream.write(record)
            indexes, offsets = _message_indexes(index, chunk_offset + len(record))
            self.stream.write(indexes)
            self._chunk_indexes.append(
                struct.pack("<QQQQI", start, end, chunk_offset, len(record), len(offsets))
                + offsets
                + struct.pack("<QI", len(indexes), len(self.compression))
                + self.compression.encode()
                + struct.pack("<QQ", len(packed), len(data))
            )
            self._start_time = start if self._start_time is None else min(self._start_time, start)
            self._end_time = max(self._end_time, end)
            self._nchunk += 1

    def flush(self) -> None:
        """Close the open chunk and hand everything to the stream."""
        self._finish_chunk()
        self._write_chunks(every=True)
        self.stream.flush()

    def finish(self) -> None:
        """The last chunk, the data end, the summary, the footer. The stream stays open."""
        self._finish_chunk()  # schemas or channels without a message are in the summary only, as mcap's Writer leaves them
        self._write_chunks(every=True)
        self._pool.shutdown()
        builder = RecordBuilder()
        DataEnd(data_section_crc=0).write(builder)
        self.stream.write(builder.end())
        summary_start = self.stream.tell()
        summary = RecordBuilder()
        groups: list[SummaryOffset] = []

        def group(opcode: Opcode, write) -> None:
            start = summary.count
            write()
            groups.append(
                SummaryOffset(
                    group_opcode=opcode, group_start=summary_start + start, group_length=summary.count - start
                )
            )

        group(Opcode.SCHEMA, lambda: [s.write(summary) for s in self._schemas.values()])
        group(Opcode.CHANNEL, lambda: [c.write(summary) for c in self._channels.values()])
        group(Opcode.STATISTICS, lambda: self._statistics().write(summary))
        group(Opcode.CHUNK_INDEX, lambda: [self._chunk_index(summary, b) for b in self._chunk_indexes])
        group(Opcode.ATTACHMENT_INDEX, lambda: [a.write(summary) for a in self._attachment_indexes])
        group(Opcode.METADATA_INDEX, lambda: [m.write(summary) for m in self._metadata_indexes])
        offset_start = summary_start + summary.count
        for g in groups:
            g.write(summary)
        data = summary.end()
        crc = zlib.crc32(
            struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start), zlib.crc32(data)
        )
        self.stream.write(data)
        builder = RecordBuilder()
        Footer(summary_start=summary_start, summary_offset_start=offset_start, summary_crc=crc).write(builder)
        self.stream.write(builder.end() + MAGIC)
        self.stream.flush()

    @staticmethod
    def _chunk_index(summary: RecordBuilder, body: bytes) -> None:
        summary.start_record(Opcode.CHUNK_INDEX)
        summary.write(body)
        summary.finish_record()

    def _statistics(self) -> Statistics:
        counts = {c: int(self._counts[c]) for c in self._channels if self._counts[c]}
        return Statistics(
            message_count=int(self._counts.sum()),
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=len(self._attachment_indexes),
            metadata_count=len(self._metadata_indexes),
            chunk_count=self._nchunk,
            message_start_time=self._start_time or 0,
            message_end_time=self._end_time,
            channel_message_counts=counts,
        )

    @property
    def messages(self) -> int:
        """Messages added so far."""
        return int(self._counts.sum())


def _message_indexes(index: list[tuple[np.ndarray, np.ndarray, np.ndarray]], at: int) -> tuple[bytes, bytes]:
    """The chunk's MessageIndex records (one per channel, its entries in the chunk's order),
    to be written at file offset `at`, and the chunk index's (channel u16, offset u64) pairs;
    laid out at once: one record's head and its 16-byte entries are put where they go."""
    channels = np.concatenate([c for c, _, _ in index])
    order = np.argsort(channels, kind="stable")
    channels = channels[order]
    entries = np.empty(len(channels), _ENTRY)
    entries["log_time"] = np.concatenate([t for _, t, _ in index])[order]
    entries["offset"] = np.concatenate([o for _, _, o in index])[order]
    ids, first, counts = np.unique(channels, return_index=True, return_counts=True)
    sizes = INDEX_HEAD + 16 * counts
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    heads = np.empty(len(ids), _INDEX_HEAD)
    heads["op"] = Opcode.MESSAGE_INDEX
    heads["length"] = sizes - 9
    heads["channel"] = ids
    heads["bytes"] = 16 * counts
    out = np.empty(int(sizes.sum()), np.uint8)
    out[starts[:, None] + np.arange(INDEX_HEAD)] = heads.view(np.uint8).reshape(-1, INDEX_HEAD)
    # entry j of its channel's record: after the record's head and the j entries before it
    j = np.arange(len(channels)) - np.repeat(first, counts)
    at_entry = np.repeat(starts + INDEX_HEAD, counts) + 16 * j
    out[at_entry[:, None] + np.arange(16)] = entries.view(np.uint8).reshape(-1, 16)
    where = np.empty(len(ids), _WHERE)
    where["channel"] = ids
    where["offset"] = at + starts
    return out.tobytes(), where.tobytes()
