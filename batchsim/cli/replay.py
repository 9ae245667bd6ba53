"""`batchsim replay FILE [--worlds I,J-K] [--rate X]`: an MCAP recording republished over ROS 2
(ros_bridge/worker/replay.py), with /clock, as `ros2 bag play` would."""

from __future__ import annotations

import sys
import time as wallclock
from collections.abc import Sequence

from batchsim import startup
from batchsim.cli.args import UsageError, replay_parser


def replay(argv: Sequence[str]) -> int:
    args = replay_parser().parse_args(list(argv))
    if not args.delay >= 0:
        raise UsageError(f"--delay must be >= 0 seconds, got {args.delay}")
    try:
        from ros_bridge.worker.replay import ReplayError
        from ros_bridge.worker.replay import replay as play
    except ModuleNotFoundError as e:
        extra = "record" if (e.name or "").startswith("mcap") else "ros"
        raise UsageError(f"replay needs {e.name}: {startup.install_command(extra)}") from None
    began = wallclock.monotonic()
    try:
        n, first, last = play(
            args.file,
            args.worlds,
            args.rate,
            args.delay,
            say=lambda line: print(f"batchsim: {line}", file=sys.stderr),
        )
    except ReplayError as e:
        raise UsageError(str(e)) from None
    print(
        f"batchsim: replayed {n} messages of {args.file} (sim time {first:.3f} .. {last:.3f} s) "
        f"in {wallclock.monotonic() - began:.1f} s",
        file=sys.stderr,
    )
    return 0
