"""Where a control period of `benchmarks/sensors.py --loop` goes, phase by phase, per backend.

sensors.py's loop (read, SensorSampler.update, write, step at --control-rate; every world's
camera at --camera-rate and lidar at --lidar-rate, spread over the periods, frames drawn on
the render thread while the physics steps), timed in phases, in five configurations of the
same model, backend and world count:

  physics            no sensors (the physics-only rate)
  lidar              the lidar only (the render thread and its GL context made, idle)
  camera             the camera only
  camera+lidar       both, as sensors.py --loop runs them
  camera+lidar sync  both, the frames drawn in the loop's thread by update() (render() in
                     place of render_async()): no drawing beside the physics

Per control period, median and worst (ms): read, write, step (the physics, with mjx's device
sync), other (the loop's own Python), and the sampler (SensorSampler.update), of which: host
copy (mjx: qpos/mocap downloaded into the host mirror; calls per period beside it), camera
submit (poses copied, the render queued), lidar site poses (threaded kinematics), lidar rays
(mujoco.batch's ray, the cast less the site poses), render wait (the loop waiting for the
render thread, MAX_PENDING), drawing (sync only) and rest. The frames' drawing is broken
down where it ran, on the render thread (beside the loop: not part of the period) or in the
sampler: kinematics (mj_kinematics + mj_camlight), scene (mjv_updateScene), draw
(mjr_render), read pixels (mjr_readPixels), convert (row flip, depth to metres), frames.

Configurations take turns in --rounds rounds (a loaded machine); RTF counts the renders in
flight at a round's end. mjx runs sensors.py's `mjx_rover()`, cpu the shipped rover.

    MUJOCO_GL=egl python benchmarks/sensor_loop_profile.py --backends cpu,mjx --worlds 16 --sizes 320x240,64x64
"""

from __future__ import annotations

import argparse
import datetime
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sensors import CAMERA, LIDAR, MODEL, make, size_arg, write_json  # noqa: E402
from throughput import device_name, versions  # noqa: E402

import batchsim.backends.host_sensors as host_sensors  # noqa: E402
from batchsim.loop.sampler import SensorSampler  # noqa: E402
from batchsim.types import PendingFrames  # noqa: E402

CONFIGS = ("physics", "lidar", "camera", "camera+lidar", "camera+lidar sync")
WANTED = {"lidar": (LIDAR,), "camera": (CAMERA,)}  # the others: both
SAMPLER_PHASES = tuple(
    "host copy|camera submit|lidar site poses|lidar rays|render wait|drawing|rest".split("|")
)
LOOP_PHASES = ("period", "read", "sampler", *SAMPLER_PHASES, "write", "step", "other")
RENDER_PHASES = ("kinematics", "scene", "draw", "read pixels", "convert", "total")
MUJOCO_CALLS = {
    "mj_kinematics": "kinematics",
    "mj_camlight": "kinematics",
    "mjv_updateScene": "scene",
    "mjr_render": "draw",
    "mjr_readPixels": "read pixels",
}


class Clock:
    """Seconds per phase (and calls) in the current control period, from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._now, self._calls = defaultdict(float), defaultdict(int)

    def add(self, phase: str, seconds: float) -> None:
        with self._lock:
            self._now[phase] += seconds
            self._calls[phase] += 1

    def take(self) -> tuple[dict[str, float], dict[str, int]]:
        """The period's times and call counts; a new period starts."""
        with self._lock:
            now, calls = self._now, self._calls
            self._now, self._calls = defaultdict(float), defaultdict(int)
        return now, calls

    def timed(self, phase: str, fn: Callable, render: bool = False) -> Callable:
        """`fn`, its time added to `phase` (on the render thread as 'render: phase' if `render`)."""

        def call(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                where = "loop render" if threading.current_thread() is threading.main_thread() else "render"
                self.add(f"{where}: {phase}" if render else phase, time.perf_counter() - t)

        return call


def instrument(clock: Clock, backend: str) -> Callable[[], None]:
    """Time the host renderer's and ray caster's parts (module-wide); returns the undo."""
    import mujoco

    cls = host_sensors.HostSensors
    methods = {"submit": "camera submit", "site_poses": "lidar site poses", "cast": "lidar cast"}
    saved = [(mujoco, name, getattr(mujoco, name)) for name in MUJOCO_CALLS]
    saved += [(host_sensors, "_draw", host_sensors._draw)] + [(cls, k, getattr(cls, k)) for k in methods]
    for name, phase in MUJOCO_CALLS.items():
        setattr(mujoco, name, clock.timed(phase, getattr(mujoco, name), render=True))
    host_sensors._draw = clock.timed("total", host_sensors._draw, render=True)
    for name, phase in methods.items():
        setattr(cls, name, clock.timed(phase, getattr(cls, name)))
    if backend == "mjx":  # its download of the state into the host mirror (read() does not use it)
        import jax

        saved.append((jax, "device_get", jax.device_get))
        jax.device_get = clock.timed("host copy", jax.device_get)

    def undo() -> None:
        for owner, name, value in saved:
            setattr(owner, name, value)

    return undo


class Loop:
    """One configuration's system and sampler, run a slice at a time."""

    def __init__(self, config: str, backend: str, nworld: int, size: tuple[int, int], args, clock: Clock):
        self.config, self.clock = config, clock
        sensors = config != "physics"
        rates = {"camera_rate": args.camera_rate, "lidar_rate": args.lidar_rate} if sensors else {}
        self.sim = sim = make(backend, nworld, size if sensors else None, **rates)
        self.substeps = max(1, round(1.0 / (args.control_rate * sim.dt)))
        self.period = self.substeps * sim.dt
        self.sampler = None
        if sensors:
            for name in WANTED.get(config, (CAMERA, LIDAR)):
                sim.sensors.want(name)
            self.sampler = SensorSampler(sim)
            sim.render(CAMERA), sim.scan(LIDAR)  # GL context, buffers: setup excluded
            deliver = self.sampler._deliver

            def timed_deliver(at: float, job) -> None:
                t = time.perf_counter()
                job.result()  # kept by the job: _deliver's own result() does not wait again
                clock.add("render wait", time.perf_counter() - t)
                deliver(at, job)

            self.sampler._deliver = timed_deliver
            if config.endswith("sync"):  # drawn now, in this thread: render() in place of render_async()

                def render_now(camera: str, worlds) -> PendingFrames:
                    done: Future = Future()
                    done.set_result(tuple(sim.render(camera, worlds)))
                    return PendingFrames(done, camera, np.asarray(worlds), sim.sensors)

                sim.render_async = render_now
        self.t_sim, self.wall, self.frames, self.scans = 0.0, 0.0, 0, 0
        self.periods: list[dict[str, float]] = []

    def run(self, seconds: float) -> None:
        sim, sampler, clock, add = self.sim, self.sampler, self.clock, self.clock.add
        clock.take()
        end = self.t_sim + seconds
        t0 = time.perf_counter()
        while self.t_sim < end - 1e-9:
            t = time.perf_counter()
            sim.read()
            t1 = time.perf_counter()
            if sampler is not None:
                sampler.update(sim, self.t_sim, self.period)
            t2 = time.perf_counter()
            sim.write()
            t3 = time.perf_counter()
            sim.step(self.substeps)
            t4 = time.perf_counter()
            add("read", t1 - t), add("sampler", t2 - t1), add("write", t3 - t2), add("step", t4 - t3)
            add("period", t4 - t)
            self.t_sim += self.period
            self.periods.append(self._row(*clock.take()))
        if sampler is not None:
            sampler.flush()
        self.wall += time.perf_counter() - t0

    @staticmethod
    def _row(now: dict[str, float], calls: dict[str, int]) -> dict[str, float]:
        row = dict(now)
        if "lidar cast" in row:
            row["lidar rays"] = row.pop("lidar cast") - row.get("lidar site poses", 0.0)
        if "loop render: total" in row:  # sync: drawn in the sampler
            row["drawing"] = row["loop render: total"]
        if row.get("sampler"):
            row["rest"] = row["sampler"] - sum(row.get(k, 0.0) for k in SAMPLER_PHASES[:-1])
        row["other"] = row["period"] - sum(row[k] for k in ("read", "sampler", "write", "step"))
        for where in ("render", "loop render"):
            if f"{where}: total" in row:
                parts = sum(row.get(f"{where}: {k}", 0.0) for k in RENDER_PHASES[:-2])
                row[f"{where}: convert"] = row[f"{where}: total"] - parts
                row[f"{where}: frames"] = calls.get(f"{where}: draw", 0)
        if "host copy" in row:
            row["host copies"] = calls["host copy"]
        return row

    def close(self) -> None:
        if self.sampler is not None:
            self.frames, self.scans = self.sampler.produced[CAMERA], self.sampler.produced[LIDAR]
        self.sim.shutdown()


def profile(backend: str, nworld: int, size: tuple[int, int], args) -> dict:
    clock = Clock()
    undo = instrument(clock, backend)
    loops = []
    try:
        loops = [Loop(config, backend, nworld, size, args, clock) for config in CONFIGS]
        for r in range(args.rounds):
            for loop in loops[r % len(loops) :] + loops[: r % len(loops)]:
                loop.run(args.seconds / args.rounds)
    finally:
        for loop in loops:
            loop.close()
        undo()
    out = {"backend": backend, "nworld": nworld, "size": f"{size[0]}x{size[1]}", "configs": {}}
    out["budget_ms"] = loops[0].period * 1e3
    for loop in loops:
        rows = loop.periods
        stats = {}
        for k in {k for row in rows for k in row}:
            scale = 1 if k.endswith(("copies", "frames")) else 1e3  # counts, else ms
            values = [row.get(k, 0.0) * scale for row in rows]
            stats[k] = (float(np.median(values)), float(max(values)))
        out["configs"][loop.config] = {
            "rtf": loop.t_sim / loop.wall,
            "steps_per_s": nworld * loop.substeps * len(rows) / loop.wall,
            "frames_per_s": loop.frames / loop.wall,
            "scans_per_s": loop.scans / loop.wall,
            "periods": len(rows),
            "ms": stats,
        }
    return out


def show(result: dict, args) -> None:
    configs = result["configs"]
    print(
        f"\n{result['backend']}, {result['nworld']} worlds, {result['size']}, control {args.control_rate:g} Hz "
        f"(budget {result['budget_ms']:.2f} ms), camera {args.camera_rate:g} Hz, lidar {args.lidar_rate:g} Hz"
    )
    for name, c in configs.items():
        period = c["ms"]["period"]
        print(
            f"  {name:18s} rtf {c['rtf']:5.2f}  {c['steps_per_s']:9,.0f} steps/s  period median {period[0]:6.2f} ms "
            f"worst {period[1]:6.2f} ms  {c['frames_per_s']:6,.0f} frames/s  {c['scans_per_s']:6,.0f} scans/s"
        )
    print(f"  {'ms per period, median / worst':30s}" + "".join(f"{name:>18s}" for name in configs))

    def line(label: str, key: str, fmt: str = "{:7.3f} /{:8.3f}") -> None:
        cells = [c["ms"].get(key) for c in configs.values()]
        if all(cell is None or max(cell) == 0 for cell in cells):
            return
        print(f"  {label:30s}" + "".join(f"{fmt.format(*cell) if cell else '-':>18s}" for cell in cells))

    for phase in LOOP_PHASES:
        line(("    " if phase in SAMPLER_PHASES else "") + phase, phase)
        if phase == "host copy":
            line("      (calls)", "host copies", "{:7.0f} /{:8.0f}")
    for where, label in (("render", "drawing, render thread"), ("loop render", "drawing, in the sampler")):
        line(label, f"{where}: total")
        for phase in RENDER_PHASES[:-1]:
            line("    " + phase, f"{where}: {phase}")
        line("    (frames)", f"{where}: frames", "{:7.0f} /{:8.0f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--backends", default="cpu,mjx")
    p.add_argument("--worlds", default="16")
    p.add_argument("--sizes", default="320x240", help="camera resolutions, e.g. 320x240,64x64")
    p.add_argument("--seconds", type=float, default=3.0, help="simulated s per configuration, all rounds")
    p.add_argument("--rounds", type=int, default=3)
    for name, default in (("--control-rate", 100.0), ("--camera-rate", 10.0), ("--lidar-rate", 10.0)):
        p.add_argument(name, type=float, default=default)
    p.add_argument("--json", default="benchmarks/out/sensor_loop_profile.json")
    args = p.parse_args(argv)
    backends = [b for b in args.backends.split(",") if b]
    header = f"# {device_name(backends)} | {versions()} | {datetime.date.today()} | model {MODEL} (camera {CAMERA}, lidar {LIDAR})"
    print(header, flush=True)
    results = []
    for backend in backends:
        for n in [int(x) for x in args.worlds.split(",") if x]:
            for size in [size_arg(x) for x in args.sizes.split(",") if x]:
                results.append(profile(backend, n, size, args))
                show(results[-1], args)
                sys.stdout.flush()
    write_json(Path(args.json), {"header": header, "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
