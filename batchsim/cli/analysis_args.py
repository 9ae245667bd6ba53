"""The flags of `batchsim resim` and `batchsim calibrate`: argparse only, so that `--help` and a
mistyped flag answer before MuJoCo or mcap load (issue 46)."""

from __future__ import annotations

import argparse
from pathlib import Path

from batchsim.cli.args import Parser
from batchsim.cli.bridge_flags import world_list


def resim_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="batchsim resim",
        description="Re-run recorded worlds' physics from the inputs a recording holds (batchsim --record), "
        "and compare every recorded joint state and odometry with the re-simulated one.",
    )
    p.add_argument("file", help="an MCAP file written by batchsim --record (with its inputs)")
    p.add_argument("--worlds", type=world_list, default=None, metavar="I,J-K,...", help="the worlds re-run (default: every recorded world)")
    p.add_argument("--model", default=None, help="re-run this model (a name, an MJCF file or a fleet file) in place of the recording's own; refused unless it is the recorded one")
    p.add_argument(
        "--controllers", nargs="?", const="", default=None, metavar="FILE",
        help="re-run the world's controllers too, from the messages they took (the controller_manager YAML the run "
        "used; without FILE, the model's own); needs --model",
    )  # fmt: skip
    p.add_argument("--tf", action="store_true", help="compare the recorded /tf too (decodes every /tf message: slow on large fleets)")
    p.add_argument("--tolerance", type=float, default=1e-6, help="the horizon: how long each world stays within this error (rad, m, rad/s, m/s)")
    p.add_argument("--json", type=Path, default=None, help="write each world's result here")
    p.add_argument("--plot", type=Path, default=None, help="write the error over time here (.png, .svg, .pdf)")
    return p


def calibrate_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="batchsim calibrate",
        description="Replay a real robot's bag (its joint_states and the commands its controllers received) into N "
        "worlds that differ by the randomize block's draws, and narrow the ranges round by round to the draws that "
        "track the real robot best.",
    )
    p.add_argument("file", help="a rosbag2 MCAP of the real robot")
    p.add_argument("--model", default="arm", help="a shipped model's name or an MJCF file (default: arm)")
    p.add_argument("--controllers", default=None, help="the controller_manager YAML of the real robot's controllers")
    p.add_argument("--randomize", required=True, help="the ranges searched: a randomize block (uniform ranges)")
    p.add_argument("--worlds", type=int, default=256, help="worlds per round (default 256)")
    p.add_argument("--rounds", type=int, default=4, help="rounds of narrowing (default 4)")
    p.add_argument("--elite", type=float, default=0.1, help="the share of the best worlds a round narrows to (default 0.1)")
    p.add_argument("--seed", type=int, default=0, help="the search's seed")
    p.add_argument("--backend", default="cpu")
    p.add_argument("--namespace", default=None, help="the robot's namespace in the bag (default: the only one with joint_states)")
    p.add_argument("--out", type=Path, default=None, help="write the fitted randomize block here (YAML)")
    p.add_argument("--json", type=Path, default=None, help="write the fit here: fitted values, the error before and after")
    p.add_argument("--plot", type=Path, default=None, help="write the error per joint, before and after (.png, .svg, .pdf)")
    return p
