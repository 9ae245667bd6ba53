"""`BlockWriter` (ros_bridge/worker/mcap_file.py) against mcap's own `Writer`: the same messages,
metadata and attachment written both ways read back the same through mcap's seeking and
streaming readers (messages, their order, sequences, the summary's statistics, schemas,
channels, indexes), with every CRC checked; a file cut short reads up to its last chunk."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest
from conftest import need

need("mcap")
need("zstandard")

from mcap.data_stream import ReadDataStream  # noqa: E402
from mcap.exceptions import EndOfFile  # noqa: E402
from mcap.reader import NonSeekingReader, SeekingReader  # noqa: E402
from mcap.records import Chunk, Message, MessageIndex  # noqa: E402
from mcap.stream_reader import get_chunk_data_stream  # noqa: E402
from mcap.writer import CompressionType, Writer  # noqa: E402

from ros_bridge.worker.mcap_file import BlockWriter  # noqa: E402

NCHANNEL, NPERIOD = 37, 120


def _messages(seed: int = 0):
    """Periods of blocks: (t, channel ids, (n, L) payloads), layouts of two lengths, a single
    message (a /clock) each period, worlds missing from some periods (frozen)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(NPERIOD):
        t = 1_000_000 * (k + 1)
        out.append((t, np.array([1]), rng.integers(0, 256, (1, 12), dtype=np.uint8)))
        for lo, hi, length in ((2, 20, 180), (20, NCHANNEL + 1, 196)):
            ids = np.arange(lo, hi)
            ids = ids[rng.random(len(ids)) > 0.1]
            out.append((t, ids, rng.integers(0, 256, (len(ids), length), dtype=np.uint8)))
    return out


def _write(writer, block: bool, chunk_bytes: int) -> None:
    writer.start(profile="ros2", library="test")
    writer.add_metadata("batchsim", {"worlds": "[0, 1]"})
    schema = writer.register_schema(name="std_msgs/msg/Int8", encoding="ros2msg", data=b"int8 data")
    for c in range(1, NCHANNEL + 1):
        channel = writer.register_channel(
            topic=f"/world_{c}/x", message_encoding="cdr", schema_id=schema, metadata={"k": "v"}
        )
        assert channel == c
    sequence = np.zeros(NCHANNEL + 1, np.int64)
    for k, (t, ids, rows) in enumerate(_messages()):
        if k == NPERIOD:  # an attachment between chunks, as the recorder's geometry
            writer.add_attachment(0, 0, "geometry.npz", "application/x-npz", b"\x01" * 1000)
        if block:
            writer.add_block(ids, t, rows)
        else:
            for c, row in zip(ids.tolist(), rows, strict=True):
                writer.add_message(
                    c, log_time=t, data=row.tobytes(), publish_time=t, sequence=int(sequence[c])
                )
                sequence[c] += 1
    writer.finish()


def _files(chunk_bytes: int = 1 << 14) -> tuple[bytes, bytes]:
    ours, theirs = io.BytesIO(), io.BytesIO()
    _write(BlockWriter(ours, chunk_bytes=chunk_bytes), True, chunk_bytes)
    _write(Writer(theirs, chunk_size=chunk_bytes, compression=CompressionType.ZSTD), False, chunk_bytes)
    return ours.getvalue(), theirs.getvalue()


def _body(data: bytes, at: int) -> bytes:
    length = int.from_bytes(data[at + 1 : at + 9], "little")
    return data[at + 9 : at + 9 + length]


def _record(data: bytes, at: int, kind):
    """The record of type `kind` at byte `at` of `data`."""
    body = _body(data, at)
    return (
        kind.read(ReadDataStream(io.BytesIO(body)), len(body))
        if kind is Message
        else kind.read(ReadDataStream(io.BytesIO(body)))
    )


def _read(reader, **kw):
    return [
        (ch.topic, m.log_time, m.publish_time, m.sequence, m.data) for _, ch, m in reader.iter_messages(**kw)
    ]


@pytest.mark.parametrize("log_time_order", [True, False])
def test_mcaps_readers_see_what_its_writer_would_have_written(log_time_order):
    ours, theirs = _files()
    a = SeekingReader(io.BytesIO(ours), validate_crcs=True)
    b = SeekingReader(io.BytesIO(theirs), validate_crcs=True)
    messages = _read(a, log_time_order=log_time_order)
    assert messages == _read(b, log_time_order=log_time_order)
    assert len(messages) > 3000
    assert _read(NonSeekingReader(io.BytesIO(ours), validate_crcs=True)) == _read(
        NonSeekingReader(io.BytesIO(theirs), validate_crcs=True)
    )
    sa, sb = a.get_summary(), b.get_summary()
    # chunks close at a block's end here, after any message there: their count may differ
    assert dataclasses.replace(sa.statistics, chunk_count=0) == dataclasses.replace(
        sb.statistics, chunk_count=0
    )
    assert sa.schemas == sb.schemas and sa.channels == sb.channels
    assert sa.statistics.chunk_count > 10  # several chunks: the indexes across them are used
    assert len(sa.chunk_indexes) == sa.statistics.chunk_count
    indexed = 0
    for index in sa.chunk_indexes:  # rosbag2 and Foxglove seek by the message indexes: check each
        assert index.compression == "zstd" and index.message_index_offsets
        chunk = _record(ours, index.chunk_start_offset, Chunk)
        assert index.chunk_length == 9 + len(_body(ours, index.chunk_start_offset))
        data = get_chunk_data_stream(chunk, validate_crc=True)[0].read(chunk.uncompressed_size)
        for channel, at in index.message_index_offsets.items():
            entries = _record(ours, at, MessageIndex)
            assert entries.channel_id == channel
            for t, offset in entries.records:
                m = _record(data, offset, Message)
                assert (m.channel_id, m.log_time) == (channel, t)
                indexed += 1
    assert indexed == len(messages)
    assert [x.name for x in a.iter_metadata()] == [x.name for x in b.iter_metadata()] == ["batchsim"]
    assert [x.data for x in a.iter_attachments()] == [x.data for x in b.iter_attachments()]
    # a time window and a topic filter go through the chunk and message indexes
    window = dict(topics=["/world_5/x", "/world_30/x"], starting_at=20_000_000, ending_before=60_000_000)
    assert _read(a, **window) == _read(b, **window) != []


def test_a_file_cut_short_reads_up_to_its_last_chunk():
    ours, _ = _files()
    cut = ours[: len(ours) * 2 // 3]  # no summary, no footer: a recorder killed outright
    messages = []
    with pytest.raises(EndOfFile):  # the cut: a record that never ended
        for _, channel, m in NonSeekingReader(io.BytesIO(cut)).iter_messages(log_time_order=False):
            messages.append((channel.topic, m.log_time, m.publish_time, m.sequence, m.data))
    assert len(messages) > 1000
    assert messages == _read(NonSeekingReader(io.BytesIO(ours)))[: len(messages)]


def test_the_views_summary_reader_sees_what_mcaps_does():
    """ros_bridge/mcap_index.py reads a file's summary itself (chunk indexes' offsets as NumPy):
    its channels, schemas and per-chunk offsets are mcap's reader's, on files of both writers."""
    from ros_bridge.mcap_index import NoIndex, read_summary

    for data in _files():
        channels, schemas, chunks = read_summary(io.BytesIO(data))
        summary = SeekingReader(io.BytesIO(data)).get_summary()
        assert channels == summary.channels and schemas == summary.schemas and len(chunks) > 3
        ours = {c.start: dict(zip(c.offsets["channel"].tolist(), c.offsets["offset"].tolist(), strict=True)) for c in chunks}
        assert ours == {c.chunk_start_offset: c.message_index_offsets for c in summary.chunk_indexes}
        with pytest.raises(NoIndex):
            read_summary(io.BytesIO(data[: len(data) // 2]))  # cut short: no footer
