"""Remove Fast DDS's shared-memory segments that no live process maps: what ROS processes killed
by the tests leave in /dev/shm (`fastrtps_*`, their `_el` port locks and `sem.fastrtps_*`
mutexes), as Fast DDS's own `fastdds shm clean` does. `make test` runs it between the suite and
the timing tests: with a thousand stale segments the web view's page stalled for minutes and
its timing test failed (a clean /dev/shm: 82 s for the view file).

    python tests/stale_dds_segments.py          # prints how many it removed

Run it only where no ROS process is starting: a segment just created is not mapped yet.
"""

from __future__ import annotations

import re
from pathlib import Path

SHM = Path("/dev/shm")


def mapped() -> set[str]:
    """The /dev/shm names some live process maps."""
    names: set[str] = set()
    for maps in Path("/proc").glob("[0-9]*/maps"):
        try:
            names.update(re.findall(r"/dev/shm/(\S+)", maps.read_text()))
        except OSError:  # a process that ended meanwhile, or one we may not read
            continue
    return names


def stale() -> list[Path]:
    live = mapped()
    out = []
    for path in [*SHM.glob("fastrtps_*"), *SHM.glob("sem.fastrtps_*")]:
        base = path.name.removeprefix("sem.").removesuffix("_el").removesuffix("_mutex")
        if not any(name.startswith(base) for name in live):
            out.append(path)
    return out


if __name__ == "__main__":
    removed = 0
    for path in stale():
        try:
            path.unlink()
            removed += 1
        except OSError:
            pass
    print(f"removed {removed} stale Fast DDS segments from {SHM}")
