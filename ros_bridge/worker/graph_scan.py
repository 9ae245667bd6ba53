"""A bridge worker's look at the ROS graph, spread over its ticks: `GraphScan`.

Every few tenths of a second, up to GRAPH_SCAN seconds, the worker lists the graph's topics (topics created on request,
commands to unknown actuators, remote endpoints of another definition) and looks at each
name in Python (a worker of 1024 arms on the 2-core VM: 15 ms a pass over its 2,054 topics).
With a large fleet the graph holds every world's topics (4096 arms over 8 workers: ~8,000
names, some 50 ms at that rate), and a pass in one tick stalls the worker that long, long
enough for the loop to overwrite snapshots it had not published. A pass now takes the
list once and looks at at most SLICE names a tick; the services and the type check run once
the pass is through. The wait between passes is what keeps the passes at SCAN_SHARE of the
worker's time, from MIN_SCAN (a small fleet: a subscriber's on-request topic is created within a
few tenths of a second) up to GRAPH_SCAN (a large one). No rclpy import: the node is the worker's.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

SLICE = 1000  # names looked at per tick (~6 ms)
GRAPH_SCAN = 1.0  # s from one pass's end to the next's start, at most
MIN_SCAN = 0.2  # s, at least
SCAN_SHARE = 0.02  # of the worker's time the passes may take


class GraphScan:
    """Passes over the graph's topics every `every` seconds, SLICE names per `step`.

    Args:
      node: the worker's rclpy node.
      on_topic: called with each topic's name.
      on_pass: called with the pass's whole (name, types) list once every name was seen.
      every: seconds from the end of one pass to the start of the next; None: as the module's
        docstring says, from what the last pass took.
    """

    def __init__(
        self, node: Any, on_topic: Callable[[str], None], on_pass: Callable[[list], None], every: float | None = None
    ):
        self.node = node
        self.on_topic = on_topic
        self.on_pass = on_pass
        self.every = every
        self._topics: list | None = None  # the pass under way
        self._at = 0
        self._next = 0.0
        self._spent = 0.0  # s the pass under way has taken

    def step(self, now: float) -> None:
        """A tick: start a pass when one is due, and look at the next SLICE names of it."""
        if self._topics is None:
            if now < self._next:
                return
            began = time.perf_counter()
            self._topics, self._at, self._spent = self.node.get_topic_names_and_types(), 0, 0.0
        else:
            began = time.perf_counter()
        topics, end = self._topics, min(self._at + SLICE, len(self._topics))
        for name, _types in topics[self._at : end]:
            self.on_topic(name)
        self._at = end
        if end == len(topics):
            self.on_pass(topics)
            self._spent += time.perf_counter() - began
            wait = self.every if self.every is not None else min(GRAPH_SCAN, max(MIN_SCAN, self._spent / SCAN_SHARE))
            self._topics, self._next = None, now + wait
        else:
            self._spent += time.perf_counter() - began
