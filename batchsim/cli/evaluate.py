"""`batchsim evaluate`: a policy controller across randomized worlds, in-process at full speed.

    batchsim evaluate --model arm --controllers examples/policies/arm_reach.yaml \
        --randomize examples/policies/randomize.yaml --worlds 64 [--episodes 3] \
        [--json report.json] [--plot report.png]

Prints the success rate, the tracking error and time to target, and the worst worlds with their
draws and the command that runs one alone (batchsim.evaluation).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import batchsim
from batchsim.cli.args import UsageError
from batchsim.controllers import load_controllers
from batchsim.evaluation.episodes import EvalOptions, find_policy, run_episodes
from batchsim.evaluation.report import as_json, plot, table
from batchsim.loop import SimLoop


def evaluate_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="batchsim evaluate",
        description="Run a policy controller over N randomized worlds for E episodes, commands drawn per world "
        "(seeded), and report success, tracking error and the worst worlds.",
    )
    p.add_argument("--model", default="arm", help="a shipped model's name or an MJCF file (default: arm)")
    p.add_argument(
        "--controllers",
        required=True,
        help="the controller_manager YAML declaring the batchsim/PolicyController",
    )
    p.add_argument(
        "--controller", default=None, help="the policy controller's name, where the YAML declares several"
    )
    p.add_argument(
        "--randomize", default=None, help="the randomization YAML each world draws its conditions from"
    )
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument(
        "--world-offset",
        type=int,
        default=0,
        help="the first world's number: --worlds 1 --world-offset W reproduces world W",
    )
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--episode-seconds", type=float, default=3.0)
    p.add_argument(
        "--tolerance",
        type=float,
        default=0.1,
        help="success: the error below this at an episode's end (rad, m, m/s)",
    )
    p.add_argument(
        "--fall-height", type=float, default=None, help="a floating base below this height (m) has fallen"
    )
    p.add_argument(
        "--seed", type=int, default=0, help="the commands' seed (the conditions' is the randomize file's)"
    )
    p.add_argument("--backend", default="cpu")
    p.add_argument("--worst", type=int, default=5, help="how many of the worst worlds to list")
    p.add_argument("--json", type=Path, default=None, help="write every world's results here")
    p.add_argument("--plot", type=Path, default=None, help="write a plot here (.png, .svg, .pdf)")
    return p


def evaluate(argv: Sequence[str]) -> int:
    args = evaluate_parser().parse_args(argv)
    for flag, value, low in (
        ("--worlds", args.worlds, 1),
        ("--episodes", args.episodes, 1),
        ("--world-offset", args.world_offset, 0),
    ):
        if value < low:
            raise UsageError(f"{flag} must be >= {low}, got {value}")
    if not (args.episode_seconds > 0 and args.tolerance > 0):
        raise UsageError(
            f"--episode-seconds and --tolerance must be > 0, got {args.episode_seconds:g} and {args.tolerance:g}"
        )
    options = EvalOptions(args.episodes, args.episode_seconds, args.tolerance, args.seed, args.fall_height)
    sim = batchsim.make(
        args.model, args.worlds, args.backend, randomize=args.randomize, world_offset=args.world_offset
    )
    sim.configure()
    sim.activate()
    manager = load_controllers(args.controllers, sim.spec, args.worlds)
    for line in manager.warnings:
        print(f"batchsim: warning: {line}", file=sys.stderr)
    policy = find_policy(manager, args.controller)
    loop = SimLoop(sim, control_rate=manager.update_rate, rtf=0, participants=[manager])
    start = time.perf_counter()
    results = run_episodes(sim, manager, loop, policy, options, args.world_offset)
    wall = time.perf_counter() - start
    randomize = f" --randomize {args.randomize}" if args.randomize else ""
    reproduce = (
        f"batchsim evaluate --model {args.model} --controllers {args.controllers}{randomize} --worlds 1 "
        f"--world-offset {{world}} --episodes {args.episodes} --episode-seconds {args.episode_seconds:g} --seed {args.seed}"
    )
    title = f"{policy.name} ({policy.policy.model.name}) on {args.worlds} {args.model} worlds{randomize}"
    print(f"{title}: {args.episodes} episodes in {wall:.1f} s ({policy.runtime.provider})")
    print("\n".join(table(results, reproduce, args.worst)))
    about = {
        "model": str(args.model),
        "controllers": str(args.controllers),
        "controller": policy.name,
        "policy": str(policy.policy.model),
        "randomize": args.randomize,
        "world_offset": args.world_offset,
        "backend": args.backend,
    }
    if args.json is not None:
        args.json.write_text(json.dumps(as_json(results, about), indent=1))
        print(f"wrote {args.json}")
    if args.plot is not None:
        try:
            print(f"wrote {plot(results, args.plot, title)}")
        except RuntimeError as e:
            raise UsageError(str(e)) from None
    return 0
