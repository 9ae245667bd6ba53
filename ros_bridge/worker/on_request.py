"""Per-world ROS entities created when a client of them appears in the graph.

A fleet of thousands of worlds cannot afford every world's services and action servers at
start (each is several DDS endpoints that discovery must match). A served kind lists its
entities by base name; the worker's graph scan (every second) hands it every name it sees
(`requested`), and the entities whose base a client named are created on the executor
thread (`drain`), where rclpy's entities are safe to create; `--all-topics` creates them
all at start (`create_all`). A drain creates at most PER_DRAIN of them: creating an action
server takes milliseconds (five DDS endpoints), and a worker's 128 at once held its other
thread off for over a second (its publishing stalled); the executor loop drains again at
once while some are `pending`.
"""

from __future__ import annotations

import collections
from typing import Any

PER_DRAIN = 8  # entities created per drain, between which the worker's other thread runs


class OnRequest:
    """Entities keyed by a base name; `_create(base, value)` makes those of one key."""

    def __init__(self) -> None:
        self._pending: dict[str, Any] = {}  # base name -> what _create needs
        self._to_create: collections.deque[tuple[str, Any]] = collections.deque()

    def offer(self, base: str, value: Any) -> None:
        """Create `base`'s entities once a client names it."""
        self._pending[base] = value

    def base_of(self, name: str) -> str | None:
        """The base a graph name (a service's or topic's) belongs to; default: its parent."""
        return name.rpartition("/")[0]

    def requested(self, name: str) -> bool:
        """The graph scan saw `name`: queue its base's entities if they are ours. True if ours."""
        base = self.base_of(name)
        if base is None or base not in self._pending:
            return False
        self._to_create.append((base, self._pending.pop(base)))  # on the executor thread (drain)
        return True

    @property
    def pending(self) -> bool:
        """Entities asked for and not created yet."""
        return bool(self._to_create)

    def drain(self) -> None:
        """The executor thread: create (up to PER_DRAIN of) what the graph scan asked for."""
        for _ in range(min(PER_DRAIN, len(self._to_create))):
            self._create(*self._to_create.popleft())

    def create_all(self) -> None:
        """Every entity now (`--all-topics`)."""
        for base, value in list(self._pending.items()):
            del self._pending[base]
            self._create(base, value)

    def _create(self, base: str, value: Any) -> None:
        raise NotImplementedError
