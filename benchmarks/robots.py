"""Check every robot in a directory as a new user would: load it, start it in its keyframe,
run it, and say what each backend makes of it.

    .venv/bin/python benchmarks/robots.py DIR [DIR ...] [--backends cpu,warp,mjx] [--seconds 2] [--worlds 4]

A robot is a scene file: in each folder, `scene*.xml` if there are any, else every `.xml`
that MuJoCo compiles to a model with actuators (files included by others are skipped).
Archives (`*.tar.xz`, as ../shared/robots holds them) are unpacked to a temporary folder
first. Per robot and backend it prints one line: where worlds start, whether every world
stays finite and unfrozen (after `batchsim info` lists it) for `--seconds` of simulated time with the initial command held,
and the physics steps per second it ran at; a backend that cannot simulate the model says
why (the message names the backends that can). Exit code 1 if any check failed.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

import batchsim
from batchsim.backends import BackendUnavailable
from batchsim.model import ModelError


def scenes(directory: Path) -> list[Path]:
    """The robots' scene files under `directory` (one level of folders, or the folder itself)."""
    folders = [directory] + sorted(p for p in directory.iterdir() if p.is_dir())
    found = []
    for folder in folders:
        files = sorted(folder.glob("scene*.xml")) or sorted(folder.glob("*.xml"))
        included = set()
        for f in files:
            text = f.read_text(errors="replace")
            included |= {part.split('"')[1] for part in text.split("<include file=")[1:] if '"' in part}
        found += [f for f in files if f.name not in included]
    return found


def unpack(paths: list[Path], into: Path) -> list[Path]:
    """Directories to check: archives among `paths` unpacked under `into`."""
    out = []
    for p in paths:
        if p.is_dir():
            archives = sorted(p.glob("*.tar.xz"))
            for a in archives:
                with tarfile.open(a) as tar:
                    tar.extractall(into / p.name, filter="data")
            out.append(into / p.name if archives else p)
        elif p.name.endswith(".tar.xz"):
            with tarfile.open(p) as tar:
                tar.extractall(into / p.stem, filter="data")
            out.append(into / p.stem)
    return out


def check(scene: Path, backend: str, seconds: float, nworld: int) -> tuple[bool, str]:
    """Run one robot on one backend; (ok, one line)."""
    from batchsim.cli.info import info

    try:
        spec = batchsim.load(scene)
    except ModelError as e:
        return False, f"load failed: {e}"
    with contextlib.redirect_stdout(io.StringIO()) as listing:
        if info([str(scene), "--backend", "cpu"]) != 0 or "starts in" not in listing.getvalue():
            return False, "batchsim info failed"
    if spec.mjmodel.nu == 0:
        return True, "no actuators: skipped"
    try:
        sim = batchsim.make(spec, nworld, backend)
        sim.configure()
        sim.activate()
    except (BackendUnavailable, batchsim.ConfigurationError, ValueError) as e:
        return False, f"cannot run: {e}"
    nstep = max(1, round(0.01 / sim.dt))  # 100 Hz control
    periods = max(1, round(seconds / (nstep * sim.dt)))
    sim.read()
    pose0 = _pose(sim)
    start = time.perf_counter()
    for _ in range(periods):
        sim.write()
        sim.step(nstep)
        sim.read()
    wall = time.perf_counter() - start
    finite = bool(np.isfinite(sim.state).all()) and bool(np.isfinite(sim.device_arrays()["qpos"]).all())
    frozen = int(np.count_nonzero(sim.frozen))
    collapse = _collapse(sim, pose0) if finite and not frozen else None
    ok = finite and frozen == 0 and collapse is None
    rate = nworld * nstep * periods / wall
    sim.shutdown()
    held = "holds its start pose" if collapse is None else f"COLLAPSES: {collapse}"
    line = (
        f"starts in {spec.initial.source}; {sim.time[0]:.2f} s: "
        f"{'finite' if finite else 'NOT FINITE'}, {frozen}/{nworld} frozen, {held}; {rate / 1e3:.1f}k steps/s"
    )
    return ok, line


JOINT_DRIFT = 0.35  # rad (or m): a joint this far from its start pose with its command held has fallen
BASE_DROP = 0.3  # of the start height: a floating base this much lower has fallen


def _pose(sim: batchsim.BatchedSystem) -> tuple[np.ndarray, np.ndarray | None]:
    """(joint positions (nworld, njoint), base height (nworld,) or None)."""
    names = sim.export_state_interfaces()
    cols = [names.index(f"{j.name}/position") for j in sim.spec.joints if f"{j.name}/position" in names]
    base = None if sim.base_state is None else sim.base_state[:, 2].copy()
    return sim.state[:, cols].copy(), base


def _collapse(sim: batchsim.BatchedSystem, pose0: tuple[np.ndarray, np.ndarray | None]) -> str | None:
    """Why the robot did not hold its start pose with its initial command, or None if it did."""
    q0, z0 = pose0
    q, z = _pose(sim)
    what = None
    if z0 is not None and (z0 - z).max() > BASE_DROP * max(float(z0.max()), 0.1):
        w = int(np.argmax(z0 - z))
        what = f"its base fell from {z0[w]:.2f} m to {z[w]:.2f} m"
    elif q0.size and np.abs(q - q0).max() > JOINT_DRIFT:
        w, j = np.unravel_index(np.argmax(np.abs(q - q0)), q.shape)
        joint = [jt.name for jt in sim.spec.joints][j]
        what = f"joint {joint} moved {q[w, j] - q0[w, j]:+.2f} from its start"
    if what is None:
        return None
    kinds = {c.kind.value for c in sim.spec.commands if c.pid is None}
    if kinds == {"effort"}:
        why = "its actuators are torque motors and the held command is a torque (0 unless the keyframe gives ctrl)"
        if sim.spec.initial.ctrl_given:
            why = "its actuators are torque motors and the keyframe's ctrl is held as a torque"
        return f"{what}: {why}; give it a controller (or PIDs in a ros2_control block)"
    return f"{what} with its initial command held"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dirs", nargs="+", type=Path, help="folders of robots, .tar.xz archives, or scene files")
    p.add_argument("--backends", default="cpu", help="comma-separated: cpu, warp, mjx (default cpu)")
    p.add_argument("--seconds", type=float, default=2.0, help="simulated seconds per robot (default 2)")
    p.add_argument("--worlds", type=int, default=4, help="worlds per run (default 4)")
    args = p.parse_args(argv)
    failed = 0
    with tempfile.TemporaryDirectory() as tmp:
        files = [p for p in args.dirs if p.suffix == ".xml"]
        folders = unpack([p for p in args.dirs if p.suffix != ".xml"], Path(tmp))
        for scene in files + [s for d in folders for s in scenes(d)]:
            for backend in args.backends.split(","):
                ok, line = check(scene, backend, args.seconds, args.worlds)
                failed += not ok
                name = f"{scene.parent.name}/{scene.name}"
                print(f"{'ok  ' if ok else 'FAIL'} {name:48s} {backend:5s} {line}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
