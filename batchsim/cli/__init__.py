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

import importlib
import sys
from collections.abc import Sequence
from typing import Any

from batchsim.cli.args import EXIT_USAGE, UsageError, split_ros_args

# the command's parts, imported when used (PEP 562 for `from batchsim.cli import run`): `--help`,
# `--version` and a mistyped flag are answered before MuJoCo, the backends or rclpy load (issue 46).
# A subcommand's function is its module's (`batchsim.cli.info.info`): the package's attribute
# `info` is that module once imported.
_LAZY = {
    "StatusLine": "batchsim.cli.runner",
    "build": "batchsim.cli.runner",
    "check_args": "batchsim.cli.args",
    "default_model": "batchsim.cli.args",
    "run": "batchsim.cli.runner",
    "run_parser": "batchsim.cli.args",
    "sensor_lines": "batchsim.cli.info",
    "setup_controllers": "batchsim.cli.runner",
    "start_ros": "batchsim.cli.runner",
    "version_line": "batchsim.cli.args",
}
#: subcommand -> (module, function, its parser: "module:function", light modules only); "" is the run itself
_COMMANDS = {
    "": ("batchsim.cli.runner", "run", "batchsim.cli.args:run_parser"),
    "info": ("batchsim.cli.info", "info", "batchsim.cli.args:info_parser"),
    "replay": ("batchsim.cli.replay", "replay", "batchsim.cli.args:replay_parser"),
    "view": ("batchsim.cli.view", "view", "batchsim.cli.args:view_parser"),
    "evaluate": ("batchsim.cli.evaluate", "evaluate", "batchsim.cli.args:evaluate_parser"),
    "resim": ("batchsim.cli.resim", "resim", "batchsim.cli.analysis_args:resim_parser"),
    "calibrate": ("batchsim.cli.calibrate", "calibrate", "batchsim.cli.analysis_args:calibrate_parser"),
}

__all__ = [
    "EXIT_USAGE", "StatusLine", "UsageError", "build", "check_args", "default_model", "main",
    "run", "run_parser", "sensor_lines", "setup_controllers", "start_ros", "user_errors", "version_line",
]  # fmt: skip


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module 'batchsim.cli' has no attribute {name!r}")
    return getattr(importlib.import_module(_LAZY[name]), name)


def user_errors() -> tuple[type[Exception], ...]:
    """What the user can fix: printed as one line, exit 2 (imported when an error is to be judged)."""
    from batchsim.backends import BackendUnavailable
    from batchsim.lifecycle import LifecycleError
    from batchsim.loop import OptionError, RateError
    from batchsim.memory import SharedMemoryFull
    from batchsim.model import ModelError
    from batchsim.model.params import ParamsError
    from batchsim.sensors import DeclarationError, SensorConfigError
    from batchsim.startup import MemoryCheckError
    from batchsim.types import ConfigurationError
    from batchsim.variation import VariationError

    return (
        UsageError, ModelError, ConfigurationError, BackendUnavailable, LifecycleError, ParamsError, MemoryCheckError,
        OptionError, RateError, SensorConfigError, DeclarationError, VariationError, SharedMemoryFull,
    )  # fmt: skip


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv and argv[0] in _COMMANDS else ""
    if command:
        argv = argv[1:]
    module, name, parser = _COMMANDS[command]
    try:
        # parsed here first, with nothing heavy imported: --help, --version and a bad flag answer at once
        where, function = parser.split(":")
        getattr(importlib.import_module(where), function)().parse_args(split_ros_args(argv)[0] if not command else argv)
        return getattr(importlib.import_module(module), name)(argv)
    except UsageError as e:  # before anything heavy was imported: the parser's own
        print(f"batchsim: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:  # `batchsim info arm | head`
        sys.stderr.close()
        return 0
    except Exception as e:
        if not isinstance(e, user_errors()):
            raise  # an internal bug keeps its traceback
        print(f"batchsim: error: {e}", file=sys.stderr)  # what the user can fix, as one line
        return EXIT_USAGE
