"""`batchsim resim FILE [--worlds I,J-K] [--model M] [--tolerance X] [--json F] [--plot F]`: re-run
recorded worlds' physics from the inputs the recording holds (batchsim.resim) and say, per world,
whether the re-run is bit-exact, or where it parts from the recording and for how long it stays
within the tolerance."""

from __future__ import annotations

import dataclasses
import json
import sys
import time as wallclock
from collections.abc import Sequence

from batchsim import startup
from batchsim.cli.analysis_args import resim_parser
from batchsim.cli.args import UsageError
from batchsim.cli.reports import write_reports
from batchsim.plotting import pyplot


def resim(argv: Sequence[str]) -> int:
    args = resim_parser().parse_args(list(argv))
    if not args.tolerance > 0:
        raise UsageError(f"--tolerance must be > 0, got {args.tolerance}")
    try:
        import mcap  # noqa: F401
        import mcap_ros2  # noqa: F401
    except ModuleNotFoundError as e:
        raise UsageError(f"resim needs {e.name}: {startup.install_command('record')}") from None
    from batchsim.resim.compare import compare, compare_series, compare_tf
    from batchsim.resim.controllers import odometry_topics, rerun_controllers
    from batchsim.resim.layout import load_model, model_bytes, model_hash
    from batchsim.resim.physics import rerun
    from batchsim.resim.recorded import ResimError, read

    began = wallclock.monotonic()
    if args.controllers is not None and args.model is None:
        raise UsageError("--controllers re-runs the robot's controllers: name its model with --model (the recorded one)")
    controllers = _controllers(args) if args.controllers is not None else None  # None with a fleet: its robots' own
    ours = None  # --model's one-world system: its hash, and its controllers' odometry topics
    if args.model is not None:
        import batchsim

        ours = batchsim.make(args.model, 1, "cpu")
    try:
        odometry = odometry_topics(ours.spec, controllers) if args.controllers is not None else []
        groups = read(args.file, args.worlds, tf=args.tf, odometry=odometry)
    except ResimError as e:
        raise UsageError(str(e)) from None
    say = lambda line: print(f"batchsim: {line}", file=sys.stderr)  # noqa: E731
    if ours is not None:
        theirs = model_hash(model_bytes(ours.model))
        for recorded in groups:
            if theirs != recorded.meta["model_sha256"]:
                of = f" (group {recorded.group}, world {next(iter(recorded.worlds))})" if recorded.group else ""
                raise UsageError(
                    f"--model {args.model} is not the model {args.file} was recorded with{of} (SHA-256 {theirs[:12]} "
                    f"against {recorded.meta['model_sha256'][:12]}): a re-run of another model says nothing about the recording"
                )
    backends = []
    results, controlled, tfs = [], [], []
    for recorded in groups:
        model = load_model(recorded.model)
        backend = recorded.meta["backend"]
        backends.append(backend)
        group = f" of group {recorded.group}" if recorded.group else ""
        effort = json.loads(recorded.meta.get("effort", "{}"))  # where each joint's effort was read from
        say(
            f"re-running {len(recorded.worlds)} world(s){group} of {args.file} ({len(recorded.headers)} periods, recorded "
            f"on {backend}, MuJoCo {recorded.meta['mujoco']}) on MuJoCo's C step"
        )
        for w, world in recorded.worlds.items():
            if not world.starts:
                say(f"world {w}: the recording holds no start of it (its start was dropped): cannot be re-run")
                continue
            if args.controllers is not None:
                try:
                    run, verdict = rerun_controllers(args.model, controllers, recorded, world, poses=args.tf)
                except ResimError as e:
                    raise UsageError(str(e)) from None
                controlled.append((w, verdict))
                print(verdict.line(w))
                for topic, ours in verdict.odometry.items():
                    print(compare_series(topic, w, recorded.headers, ours, world.odometry.get(topic)))
            else:
                run = rerun(model, recorded.layout, recorded.headers, world, poses=args.tf, effort=effort)
            result = compare(model, w, run, recorded.headers, world.joint_states, args.tolerance)
            results.append(result)
            print(result.line())
            if args.tf:
                frames = compare_tf(model, run, recorded.headers, world.tf)
                tfs.append((w, frames))
                print(frames.line(w))
    for backend in dict.fromkeys(b for b in backends if b != "cpu"):
        say(f"a {backend} recording re-run on MuJoCo's C step parts from it: {backend} computes with kernels of its own (float32 on a GPU)")
    document = lambda: {  # noqa: E731
        "file": args.file, "backend": backends[0] if backends else None, "worlds": [r.to_json() for r in results],
        "controllers": [{"world": w, **{k: x for k, x in dataclasses.asdict(v).items() if k != "odometry"}} for w, v in controlled],
        "tf": [{"world": w, **dataclasses.asdict(v)} for w, v in tfs],
    }  # fmt: skip
    write_reports(args.json, document, args.plot, lambda path: _plot(results, path, args.tolerance))
    say(f"done in {wallclock.monotonic() - began:.1f} s")
    return 0


def _controllers(args) -> str | None:
    """--controllers' file, or the model's own controllers (None: a fleet file's, each robot's own)."""
    from batchsim.controllers import default_controllers
    from batchsim.fleet import is_fleet_file

    if is_fleet_file(args.model):
        if args.controllers:
            raise UsageError(f"--controllers {args.controllers}: a fleet's robots take their own controllers (the fleet file names them): give --controllers alone")
        return None
    if args.controllers:
        return args.controllers
    own = default_controllers(str(args.model))
    if own is None:
        raise UsageError(f"--controllers: {args.model} has no controllers of its own; name the YAML the run used")
    return str(own)


def _plot(results, path, tolerance: float) -> None:
    """The largest difference over time, per world (log scale; bit-exact worlds on the floor)."""
    import numpy as np

    plt = pyplot()

    fig, ax = plt.subplots(figsize=(8, 4))
    for r in results:
        ax.plot(r.time, np.maximum(r.error, 1e-17), label=f"world {r.world}")
    ax.axhline(tolerance, color="grey", linestyle="--", label=f"tolerance {tolerance:g}")
    ax.set_yscale("log")
    ax.set_xlabel("sim time (s)")
    ax.set_ylabel("largest joint difference")
    ax.set_title("re-run against the recording")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
