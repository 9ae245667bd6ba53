"""The recording rings of a fleet of several groups (ros_bridge/protocol/recording.py), over plain
arrays: each group's RecordWriter copies its snapshots into its own ring, and the recorder's
GroupsReader takes them as one stream in sim-time order, a period held until every ring has
reached it; the first group's ring may record no world (it leads, and its periods give /clock).
The whole path, a `batchsim --record` of two groups: tests/test_groups_recording.py."""

from __future__ import annotations

import numpy as np

from ros_bridge.protocol.demand import demand_arrays
from ros_bridge.protocol.recording import (
    GroupsReader,
    RecordReader,
    RecordWriter,
    recording_arrays,
    set_recording,
)
from ros_bridge.protocol.snapshot import reset_snapshots, snapshot_arrays, write_snapshot

WIDTH = 3  # one channel of 3 values per world


def _group(nworld: int, worlds: list[int]) -> tuple[dict, RecordWriter, RecordReader]:
    """One group's shared arrays (a dict stands in for the segment), its ring's writer and reader."""
    arrays = [*snapshot_arrays(nworld, [WIDTH]), *demand_arrays(1, 1, False), *recording_arrays(1, len(worlds), [0], [WIDTH])]
    memory = {name: np.zeros(shape, dtype) for name, shape, dtype in arrays}
    reset_snapshots(memory)
    writer = RecordWriter(memory, [0], np.array(worlds, np.intp))
    writer.restart()
    set_recording(memory, [0])
    return memory, writer, RecordReader(memory, [0])


def _period(memory: dict, writer: RecordWriter, k: int, nworld: int) -> None:
    """Period k's snapshot (sim time k/100 s, each world's values k + its number), into the ring."""

    def fill(out: np.ndarray) -> None:
        out[:] = k + np.arange(nworld)[:, None]

    status, flags = np.zeros(nworld, np.uint8), np.zeros(nworld, np.uint8)
    write_snapshot(memory, k, k, k / 100, False, status, flags, [fill], [True], every_channel=True)
    assert writer.put_newest()


def test_the_groups_rings_are_read_as_one_stream_in_sim_time_order():
    lead = _group(2, [])  # the first group: none of its worlds recorded
    other = _group(3, [0, 2])
    reader = GroupsReader([lead[2], other[2]])
    for k in range(4):  # the first group's ring ahead of the second's (read in turn, one loop writes both)
        _period(lead[0], lead[1], k, 2)
    for k in range(2):
        _period(other[0], other[1], k, 3)
    taken = reader.take()
    assert [(g, p.period) for g, p in taken] == [(0, 0), (1, 0), (0, 1), (1, 1)]  # periods 2, 3 wait for group 1
    assert taken[0][1].channels[0].shape == (1, WIDTH)  # a ring of no world: its meta only (sim time, for /clock)
    assert taken[1][1].channels[0][:, 0].tolist() == [0.0, 2.0]  # the recorded worlds 0 and 2, at period 0
    for k in range(2, 4):
        _period(other[0], other[1], k, 3)
    _period(lead[0], lead[1], 4, 2)
    assert [(g, p.period) for g, p in reader.take()] == [(0, 2), (1, 2), (0, 3), (1, 3)]
    assert not reader.pending()
    assert [(g, p.period) for g, p in reader.take(final=True)] == [(0, 4)]  # the end: what is held goes out
    assert reader.dropped() == 0
