"""`batchsim evaluate`: a policy controller across randomized worlds, in-process at full speed.

    batchsim evaluate --model arm --controllers examples/policies/arm_reach.yaml \
        --randomize examples/policies/randomize.yaml --worlds 64 [--episodes 3] \
        [--json report.json] [--plot report.png]

Prints the success rate, the tracking error and time to target, and the worst worlds with their
draws and the command that runs one alone (batchsim.evaluation).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence

import batchsim
from batchsim.cli.args import UsageError, evaluate_parser
from batchsim.cli.reports import write_reports
from batchsim.controllers import load_controllers
from batchsim.evaluation.episodes import EvalOptions, find_policy, run_episodes
from batchsim.evaluation.report import as_json, plot, table
from batchsim.loop import SimLoop


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
    write_reports(args.json, lambda: as_json(results, about), args.plot, lambda path: plot(results, path, title))
    return 0
