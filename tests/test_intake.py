"""The bridge worker's bounded intake (ros_bridge/worker/intake.py), without ROS: a fake node
and clock."""

from __future__ import annotations

import pytest

from ros_bridge.protocol.commands import Problem
from ros_bridge.worker.intake import FLOOR, PAUSE, PER_PERIOD, WINDOW, Intake


class FakeNode:
    def __init__(self):
        self.live: dict[str, object] = {}  # topic -> callback

    def create_subscription(self, msg_type, topic, callback, qos):
        self.live[topic] = callback
        return topic

    def destroy_subscription(self, sub):
        del self.live[sub]


class Recorder:
    def __init__(self):
        self.dropped: list[tuple] = []
        self.lines: list[str] = []

    def dropped_(self, world, period, topic, count, reason):
        self.dropped.append((world, topic, count))

    def warn(self, key, text):
        assert key[1] is Problem.FLOOD
        self.lines.append(text)


def make():
    node, rec, now, period = FakeNode(), Recorder(), [0.0], [0]
    diagnostics = type("D", (), {"dropped": lambda self, *a: rec.dropped_(*a)})()
    intake = Intake(node, None, lambda: period[0], diagnostics, rec, clock=lambda: now[0])
    return node, rec, now, period, intake


def test_a_flooded_topic_is_paused_and_counted_and_its_neighbours_take_everything():
    node, rec, now, period, intake = make()
    got = {3: 0, 4: 0}
    intake.subscribe(3, object, "/world_3/commands", lambda m: got.__setitem__(3, got[3] + 1))
    intake.subscribe(4, object, "/world_4/commands", lambda m: got.__setitem__(4, got[4] + 1))
    intake.service()  # the first window: FLOOR
    for _ in range(FLOOR + 30):
        node.live["/world_3/commands"]("m")
    for _ in range(FLOOR):
        node.live["/world_4/commands"]("m")
    intake.service()  # over: paused at once
    assert got == {3: FLOOR, 4: FLOOR}
    assert "/world_3/commands" not in node.live and intake.paused == ["/world_3/commands"]
    now[0] += WINDOW
    intake.service()
    assert rec.dropped == [(3, "/world_3/commands", 30)]
    assert rec.lines and "dropped 30 messages on /world_3/commands" in rec.lines[0]
    now[0] += PAUSE
    intake.service()
    assert "/world_3/commands" in node.live and intake.paused == []


def test_the_limit_grows_with_the_periods_the_loop_advanced():
    node, rec, now, period, intake = make()
    intake.subscribe(0, object, "/world_0/commands", lambda m: None)
    intake.service()
    period[0] = 100  # a lockstep commander flat out: one message per period
    now[0] += WINDOW
    intake.service()
    assert intake.limit == FLOOR + PER_PERIOD * 100
    for _ in range(100):
        node.live["/world_0/commands"]("m")
    now[0] += WINDOW
    intake.service()
    assert rec.dropped == [] and intake.paused == []


def test_a_lockstep_commander_that_starts_flat_out_after_a_quiet_window_is_not_cut_off():
    node, rec, now, period, intake = make()
    intake.subscribe(0, object, "/world_0/commands", lambda m: None)
    intake.service()
    now[0] += WINDOW
    intake.service()  # nothing advanced: the limit is FLOOR
    for _ in range(5 * FLOOR):  # each message lets the loop advance one period
        node.live["/world_0/commands"]("m")
        period[0] += 1
    intake.service()
    assert rec.dropped == [] and intake.paused == []


def test_a_flood_that_goes_on_is_listened_to_less_and_less_often():
    node, rec, now, period, intake = make()
    intake.subscribe(3, object, "/world_3/commands", lambda m: None)
    pauses = []
    for _ in range(5):
        intake.service()
        for _ in range(FLOOR + 1):
            node.live["/world_3/commands"]("m")
        start = now[0]
        intake.service()
        while "/world_3/commands" not in node.live:
            now[0] += WINDOW
            intake.service()
        pauses.append(round(now[0] - start, 1))
    # resumed at the window's end after the pause ran out
    assert pauses == pytest.approx([PAUSE, 2 * PAUSE, 4 * PAUSE, 8 * PAUSE, 8 * PAUSE], abs=1.5 * WINDOW)
