"""One fleet over several devices: the worlds split into contiguous ranges, one BatchedSystem per
device, behind the one contract. system.py is the composite (ShardedSystem), shards.py its
shards (a thread or a process each), process.py a shard process's program, messages.py what
goes between them, rows.py the fleet's arrays they share.
"""

from __future__ import annotations

from batchsim.backends.sharded.sources import PerDevice
from batchsim.backends.sharded.system import ShardedSystem

__all__ = ["PerDevice", "ShardedSystem"]
