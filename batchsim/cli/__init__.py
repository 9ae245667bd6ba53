"""The `batchsim` command: args.py (flags and their checks; bridge_flags.py, the bridge's, from
ros_bridge/options.py), runner.py (the run), info.py (`batchsim info`), replay.py and view.py
(`batchsim replay`, `batchsim view`), evaluate.py (`batchsim evaluate`), description_topic.py (`--robot-description-topic`).

    batchsim --worlds 16                     16 arms, over ROS 2, in real time
    batchsim --worlds 64 --model quadruped --rtf 0 --no-ros
    batchsim --worlds 16 --controllers controllers.yaml   ros2_control controllers in every world
    batchsim info arm                        interfaces and sensors of a model
    batchsim --worlds 16 --record run.mcap   every world's state topics into one MCAP file
    batchsim replay run.mcap --worlds 3      republish a recording over ROS 2, with /clock
    batchsim --worlds 64 --view              the fleet in 3D in a browser, live
    batchsim view run.mcap                   a recording in the same page, scrubbed through
    batchsim evaluate --controllers P.yaml   a policy controller's success across randomized worlds

Errors a user can fix (a missing file, malformed XML, an unknown model, a bad flag, a
fleet that will not fit in memory) print one line and exit with code 2. Start-up stages
that take over a second show progress. Ctrl-C or SIGTERM during start-up exits promptly
with one line and code 130 or 143 (nothing ran); once the run has begun they end it
cleanly with code 0.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from batchsim.backends import BackendUnavailable
from batchsim.cli.args import EXIT_USAGE, UsageError, check_args, default_model, run_parser, version_line
from batchsim.cli.evaluate import evaluate
from batchsim.cli.info import info, sensor_lines
from batchsim.cli.replay import replay
from batchsim.cli.runner import StatusLine, build, run, setup_controllers, start_ros
from batchsim.cli.view import view
from batchsim.lifecycle import LifecycleError
from batchsim.loop import OptionError, RateError
from batchsim.memory import SharedMemoryFull
from batchsim.model import ModelError
from batchsim.model.params import ParamsError
from batchsim.sensors import DeclarationError, SensorConfigError
from batchsim.startup import MemoryCheckError
from batchsim.types import ConfigurationError
from batchsim.variation import VariationError

__all__ = [
    "EXIT_USAGE", "USER_ERRORS", "StatusLine", "UsageError", "build", "check_args", "default_model", "info", "main",
    "run", "run_parser", "sensor_lines", "setup_controllers", "start_ros", "version_line",
]  # fmt: skip


USER_ERRORS = (
    UsageError, ModelError, ConfigurationError, BackendUnavailable, LifecycleError, ParamsError, MemoryCheckError,
    OptionError, RateError, SensorConfigError, DeclarationError, VariationError, SharedMemoryFull,
)  # fmt: skip


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] == "info":
            return info(argv[1:])
        if argv and argv[0] == "replay":
            return replay(argv[1:])
        if argv and argv[0] == "view":
            return view(argv[1:])
        if argv and argv[0] == "evaluate":
            return evaluate(argv[1:])
        return run(argv)
    except USER_ERRORS as e:  # what the user can fix, as one line; an internal bug keeps its traceback
        print(f"batchsim: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:  # `batchsim info arm | head`
        sys.stderr.close()
        return 0
