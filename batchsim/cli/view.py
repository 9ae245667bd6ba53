"""`batchsim view FILE [--view-host ADDRESS] [--view-port N]`: a recording in the web view, scrubbed
through (ros_bridge/view_file.py); Ctrl-C ends it."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from batchsim import startup
from batchsim.cli.args import UsageError, view_parser


def view(argv: Sequence[str]) -> int:
    args = view_parser().parse_args(list(argv))
    if not 0 < args.view_port < 65536:
        raise UsageError(f"--view-port must be in 1..65535, got {args.view_port}")
    try:
        from ros_bridge.recording_file import ReplayError
        from ros_bridge.view_file import serve
    except ModuleNotFoundError as e:
        extra = "record" if (e.name or "").startswith("mcap") else "view"
        raise UsageError(f"batchsim view needs {e.name}: {startup.install_command(extra)}") from None
    try:
        serve(args.file, args.view_host, args.view_port, say=lambda line: print(f"batchsim: {line}", file=sys.stderr, flush=True))
    except ReplayError as e:
        raise UsageError(str(e)) from None
    except KeyboardInterrupt:
        pass
    return 0
