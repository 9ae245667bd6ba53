"""The `batchsim` command's edges: flag values, the memory estimate, start-up progress and
interrupts, the status line, --version, install hints. Command tests run
`python -m batchsim.cli` in a subprocess, as a user would.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import importlib.util
import os
import pty
import signal
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import pytest
from conftest import need

import batchsim
from batchsim import startup
from batchsim.cli.args import batchsim_version
from batchsim.loop import LoopStats, OptionError, SimLoop, format_stats
from ros_bridge.naming import NamingError, world_namespaces

ROOT = Path(__file__).resolve().parent.parent


def batchsim_cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        [sys.executable, "-m", "batchsim.cli", *args], capture_output=True, text=True, timeout=timeout, env=env
    )


def one_error_line(out: subprocess.CompletedProcess) -> str:
    assert out.returncode == 2, out.stderr
    assert "Traceback" not in out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    return lines[0]


# ---------------------------------------------------------------- flag values


@pytest.mark.parametrize(
    "args, message",
    [
        (["--duration", "nan"], "--duration must be a finite number of simulated seconds > 0, got nan"),
        (["--duration", "-1"], "--duration must be a finite number of simulated seconds > 0, got -1.0"),
        (["--rtf", "nan"], "--rtf must be a finite number >= 0"),
        (["--threads", "-3"], "--threads must be >= 1"),
        (["--thread-priority", "120"], "--thread-priority must be 0-99 (0: the normal policy), got 120"),
        (["--cpu-affinity", "4096"], "--cpu-affinity names no core of this machine"),
        (["--cpu-affinity", "one"], "argument --cpu-affinity: cores are whole numbers separated by commas, got 'one'"),
        (["--control-rate", "nan"], "--control-rate must be a finite number > 0, got nan"),
        (["--publish-rate", "inf"], "--publish-rate must be a finite number > 0, got inf"),
        (["--qos-depth", "0"], "--qos-depth must be >= 1, got 0"),
        (["--model", "{tmp}"], "is a directory, not an MJCF file"),
    ],
)
def test_bad_flag_values_are_one_line_and_exit_2(args, message, tmp_path):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    line = one_error_line(batchsim_cli(*args, "--no-ros"))
    assert message in line


@pytest.mark.parametrize(
    "env, args, message",
    [
        ({"ROS_DOMAIN_ID": "abc"}, [], "ROS_DOMAIN_ID=abc: must be an integer in 0..232"),
        ({"ROS_DOMAIN_ID": "240"}, [], "ROS_DOMAIN_ID=240: must be an integer in 0..232"),
        ({}, ["--model", "{tmp}/binary.xml", "--no-ros"], "binary.xml: not a text file (byte 0x91 at offset 1 is not UTF-8)"),
        ({}, ["--log-dir", "/sys/kernel", "--no-ros"], "--log-dir: log directory '/sys/kernel': cannot write MUJOCO_LOG.TXT there"),
        # issue 47's review: a YAML that is not UTF-8 text was a UnicodeDecodeError traceback for each of these
        *(
            ({}, [flag, "{tmp}/binary.yaml", "--no-ros"], "binary.yaml: not a text file (byte 0x91 at offset 1 is not UTF-8)")
            for flag in ("--controllers", "--sensors", "--fleet", "--randomize")
        ),
    ],
)
def test_what_a_new_user_gets_wrong_is_one_line_naming_the_cause(env, args, message, tmp_path, monkeypatch):
    """Issue 23: a 15-line traceback (ROS_DOMAIN_ID=abc), Fast DDS port errors (240), a decode error
    naming no file, a log directory that can never be written accepted."""
    (tmp_path / "binary.xml").write_bytes(b"<\x91\x00\xff")
    (tmp_path / "binary.yaml").write_bytes(b"a\x91\x00\xff")
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    line = one_error_line(batchsim_cli(*(a.replace("{tmp}", str(tmp_path)) for a in args), "--duration", "0.1"))
    assert message in line, line


def test_namespace_templates_take_format_specs():
    assert world_namespaces(3, "w_{i:03d}") == ["w_000", "w_001", "w_002"]
    assert world_namespaces(2, "fleet/w{i:02d}/arm") == ["fleet/w00/arm", "fleet/w01/arm"]
    with pytest.raises(NamingError, match=r"has no \{i\}"):
        world_namespaces(2, "robot")
    with pytest.raises(NamingError, match="gives 'w_1' to several worlds"):
        world_namespaces(12, "w_{i!s:.1}")  # a spec that truncates: worlds 1 and 10 would share topics


def test_a_bad_namespace_template_is_refused_before_start_up():
    line = one_error_line(batchsim_cli("--worlds", "12", "--namespace", "w_{i!s:.1}"))
    assert "--namespace 'w_{i!s:.1}' gives 'w_1' to several worlds" in line


# ---------------------------------------------------------------- memory


def test_a_fleet_that_cannot_fit_is_refused_before_anything_is_allocated():
    # 10 million arms with ROS: ~15 TB by the estimate, on any machine
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": "101"}
    out = subprocess.run(
        [sys.executable, "-m", "batchsim.cli", "--worlds", "10000000", "--backend", "cpu"],
        capture_output=True, text=True, timeout=120, env=env,
    )  # fmt: skip
    line = one_error_line(out)
    assert "10000000 worlds need about" in line and "available" in line
    assert "ROS 2 bridge" in line and "--no-ros" in line and "--skip-memory-check" in line


@pytest.mark.slow  # over a few seconds: `make quick` leaves it out
def test_memory_estimate_splits_host_and_device_and_checks_both():
    spec = batchsim.load("arm")
    host = batchsim.backends.estimate_memory(spec, "cpu", 1000, ros=True, nthread=2)
    assert host.device == 0
    assert host.ros_per_world == startup.ROS_BRIDGE_BYTES_PER_WORLD
    assert host.ros_fixed == startup.ROS_BRIDGE_BYTES_PER_WORKER  # one worker by default
    eight = batchsim.backends.estimate_memory(spec, "cpu", 1000, ros=True, nthread=2, ros_workers=8)
    assert eight.host - host.host == 7 * startup.ROS_BRIDGE_BYTES_PER_WORKER
    assert "ROS 2 bridge 1.2 GB" in eight.breakdown()  # 1000 x 0.4 MB + 8 x 100 MB
    assert host.host >= 1000 * (host.physics_per_world + host.ros_per_world)
    more = batchsim.backends.estimate_memory(spec, "cpu", 2000, ros=True, nthread=2)
    assert more.host - host.host == 1000 * (host.physics_per_world + host.ros_per_world)

    gpu = batchsim.backends.estimate_memory(spec, "warp", 1000, ros=False, on_device=True, nconmax=8, njmax=40)
    assert gpu.device == 1000 * gpu.physics_per_world
    on_host = batchsim.backends.estimate_memory(spec, "warp", 1000, ros=False, nconmax=8, njmax=40)  # Warp's CPU device
    assert on_host.device == 0 and on_host.host > gpu.host

    with_controllers = batchsim.backends.estimate_memory(spec, "cpu", 1000, ros=True, nthread=2, controllers=True)
    assert with_controllers.host - host.host == 1000 * with_controllers.controllers_per_world > 0

    assert startup.check_host_memory(host, available=100 * host.host) is None
    assert "will take about" in startup.check_host_memory(host, available=int(1.1 * host.host))
    with pytest.raises(startup.MemoryCheckError, match="1000 worlds need about .* of RAM"):
        startup.check_host_memory(host, available=host.host // 2)
    startup.check_device_memory(gpu, None)  # not reported: not checked
    with pytest.raises(startup.MemoryCheckError, match="warp's device memory"):
        startup.check_device_memory(gpu, startup.DeviceMemory(free=gpu.device // 2, total=gpu.device))


# ---------------------------------------------------------------- progress


def pty_stream() -> tuple[int, object]:
    """A real terminal: (the master fd to read, a text stream on the slave that isatty())."""
    master, slave = pty.openpty()
    return master, os.fdopen(slave, "w", buffering=1)


def read_all(fd: int) -> str:
    os.set_blocking(fd, False)
    chunks = []
    while True:
        try:
            chunk = os.read(fd, 65536)
        except (BlockingIOError, OSError):
            break
        if not chunk:
            break
        chunks.append(chunk)
    return b"".join(chunks).decode()


def test_progress_shows_only_slow_stages_live_on_a_terminal():
    master, stream = pty_stream()
    progress = startup.Progress(stream, after=0.3)
    assert progress.tty
    with progress.stage("quick"):
        pass
    with progress.stage("allocating 9 worlds"):
        time.sleep(1.2)
    progress.close()
    out = read_all(master)
    assert "quick" not in out
    assert "\rbatchsim: allocating 9 worlds ... 1 s\x1b[K" in out  # redrawn, the rest of the line cleared
    assert "allocating 9 worlds: done in 1." in out


def test_progress_in_a_log_is_one_line_per_slow_stage(tmp_path):
    with open(tmp_path / "log", "w") as stream:
        progress = startup.Progress(stream, after=0.2)
        with progress.stage("compiling"):
            time.sleep(0.9)
        progress.close()
    lines = (tmp_path / "log").read_text().splitlines()
    assert lines[0] == "batchsim: compiling ..." and lines[1].startswith("batchsim: compiling: done in 0.")
    assert len(lines) == 2


# ---------------------------------------------------------------- interrupts


GUARDED_CALL = """
import sys
from mujoco import batch
import batchsim
from batchsim.startup import Progress, StartupGuard
b = batch.Batch(batchsim.load("arm").mjmodel, 200_000, nthread=1)
progress = Progress(sys.stderr, after=0.0)
with StartupGuard(progress):
    with progress.stage("resetting 200000 worlds"):
        for _ in range(1000):  # minutes in mujoco.batch, which releases the GIL
            b.reset()
            b.forward()
print("not interrupted")
"""


@pytest.mark.slow  # over a few seconds: `make quick` leaves it out
def test_a_signal_inside_a_long_library_call_exits_promptly():
    proc = subprocess.Popen([sys.executable, "-c", GUARDED_CALL], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert "resetting 200000 worlds" in proc.stderr.readline()
    time.sleep(0.5)
    sent = time.monotonic()
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    elapsed = time.monotonic() - sent
    assert proc.returncode == 130, err
    assert "batchsim: interrupted by SIGINT during start-up (resetting 200000 worlds); nothing ran" in err
    assert "not interrupted" not in out
    assert elapsed < 10, elapsed  # the grace is 0.5 s; minutes if the guard waited for the call


SIGNAL_IN_GC_CALLBACK = """
import gc, os, signal, sys, time
from batchsim.startup import Progress, StartupGuard
def callback(phase, info):  # as jax's _xla_gc_callback: Python cannot raise out of it
    if phase == "start":
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.01)  # the handler runs here, inside the callback
progress = Progress(sys.stderr, after=0.0)
with StartupGuard(progress):
    with progress.stage("compiling"):
        gc.callbacks.append(callback)
        gc.collect()
        gc.callbacks.remove(callback)
        time.sleep(float(sys.argv[1]))
print("not interrupted")
"""


@pytest.mark.parametrize("after", [0.0, 5.0], ids=["block-ends-first", "grace-ends-first"])
def test_a_signal_swallowed_by_a_gc_callback_still_exits_with_one_line(after):
    proc = subprocess.run(
        [sys.executable, "-c", SIGNAL_IN_GC_CALLBACK, str(after)], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 143, proc.stderr
    assert "not interrupted" not in proc.stdout
    lines = [line for line in proc.stderr.strip().splitlines() if "interrupted" in line or "Exception" in line]
    where = "" if after == 0.0 else " (compiling)"  # a stage that ended is not named
    assert lines == [f"batchsim: interrupted by SIGTERM during start-up{where}; nothing ran"], proc.stderr


@pytest.mark.skipif(importlib.util.find_spec("jax") is None, reason="mjx needs jax")
def test_sigterm_while_mjx_compiles_exits_promptly_with_one_line():
    proc = subprocess.Popen(
        [sys.executable, "-m", "batchsim.cli", "--worlds", "2", "--backend", "mjx", "--no-ros"],
        stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    watchdog = threading.Timer(300, proc.kill)  # a build that never shows the stage must not hang the suite
    watchdog.start()
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if "compiling mjx's program for 2 worlds" in line:
            break
    watchdog.cancel()
    if proc.poll() is not None or "compiling" not in lines[-1]:
        proc.kill()
        pytest.fail("no compiling stage shown:\n" + "".join(lines))
    sent = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    rest = proc.stderr.read()
    proc.wait(timeout=60)
    elapsed = time.monotonic() - sent
    stage = line.strip().removeprefix("batchsim: ").removesuffix(" ...")
    assert proc.returncode == 143, rest
    assert rest.strip().splitlines() == [f"batchsim: interrupted by SIGTERM during start-up ({stage}); nothing ran"]
    assert elapsed < 10, elapsed


# ---------------------------------------------------------------- the status line


def test_status_line_shows_paused_and_clears_the_rest_of_the_line():
    from batchsim.cli import StatusLine

    assert "paused" in format_stats(LoopStats(sim_time=1.0, paused=True), 2, "cpu")
    assert "rtf" not in format_stats(LoopStats(sim_time=1.0, paused=True), 2, "cpu")

    sim = batchsim.make("arm", 2, "cpu")
    sim.configure()
    sim.activate()
    loop = SimLoop(sim, rtf=1.0)
    master, stream = pty_stream()
    status = StatusLine(loop, sim.nworld, "cpu", stream=stream)
    with status:
        runner = threading.Thread(target=loop.run, args=(status.report,), kwargs={"report_every": 0.3})
        runner.start()
        time.sleep(1.0)
        loop.pause(True)
        time.sleep(2.5)  # the pause watcher redraws once a second
        loop.stop()
        runner.join(timeout=10)
    sim.shutdown()
    out = read_all(master)
    frames = out.split("\r")
    assert any("| rtf " in f for f in frames), out
    paused = [f for f in frames if "| paused |" in f]
    assert paused and all(f.rstrip("\n").endswith("\x1b[K") for f in paused), out
    assert out.endswith("\n")


def test_the_status_line_fits_the_terminal(monkeypatch):
    """A 112-character line on 80 columns wrapped, and each redraw left a stale row (issue 46):
    the line is fitted to the terminal's width each time it is drawn."""
    import os

    from batchsim.cli.runner import fit

    line = format_stats(LoopStats(sim_time=12.5, rtf=1.0, steps_per_second=2.0e3), 16, "cpu (auto: no CUDA GPU, so mujoco.batch on the CPU)")
    assert len(line) > 80
    assert fit(line, 200) == line
    short = fit(line, 79)
    assert len(short) <= 79 and "(auto" not in short and short.startswith("sim")
    assert fit(line, 20) == line[:19] + "…"
    monkeypatch.setattr("shutil.get_terminal_size", lambda *a, **k: os.terminal_size((60, 24)))
    from batchsim.cli import StatusLine

    master, stream = pty_stream()
    StatusLine(None, 16, "cpu", stream=stream)._draw(line)
    drawn = read_all(master).split("\r")[-1].removesuffix("\x1b[K")
    assert len(drawn) <= 59, drawn


# ---------------------------------------------------------------- version, imports, hints


def test_help_names_every_command_and_every_flag_the_docs_give():
    """`--help` named neither `replay` nor `view` nor `--ros-args` (issue 46): every command and
    every flag of docs/cli.md's "The command" block (the README's, before the docs moved to
    docs/) is in some `--help`."""
    import re

    page = (Path(__file__).parent.parent / "docs" / "cli.md").read_text()
    block = page.split("## The command", 1)[1].split("```", 2)[1]
    commands = ("", "info", "replay", "view", "evaluate", "resim", "calibrate")
    helps = {cmd: " ".join(batchsim_cli(*cmd.split(), "--help").stdout.split()) for cmd in commands}
    main = helps[""]
    for command in ("batchsim info", "batchsim replay", "batchsim view", "batchsim evaluate", "batchsim resim", "batchsim calibrate", "--ros-args"):
        assert command in main, command
    flags = set(re.findall(r"--[a-z][a-z0-9-]*", block))
    assert len(flags) > 30
    missing = sorted(f for f in flags if not any(re.search(rf"{f}\b", text) for text in helps.values()))
    assert not missing, missing


def test_version():
    out = batchsim_cli("--version")
    assert out.returncode == 0
    assert out.stdout.startswith("batchsim ") and "mujoco" in out.stdout


def _not_installed(dist: str) -> str:
    raise importlib.metadata.PackageNotFoundError(dist)


def test_version_from_a_source_checkout_is_pyprojects():
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert batchsim_version(_not_installed) == f"{declared} (source checkout)"
    assert batchsim_version(lambda dist: "9.9.9") == "9.9.9"


def test_version_command_without_distribution_metadata(tmp_path):
    """`python -m batchsim.cli --version` with the checkout on PYTHONPATH, run elsewhere, and no batchsim
    distribution found (as when nothing was pip-installed)."""
    code = (
        "import importlib.metadata as m, runpy, sys\n"
        "found = m.version\n"
        "def version(dist):\n"
        "    if dist == 'batchsim':\n"
        "        raise m.PackageNotFoundError(dist)\n"
        "    return found(dist)\n"
        "m.version = version\n"
        "sys.argv = ['batchsim', '--version']\n"
        "runpy.run_module('batchsim.cli', run_name='__main__', alter_sys=True)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=60)
    assert out.returncode == 0, out.stderr
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert out.stdout.startswith(f"batchsim {declared} (source checkout) (mujoco "), out.stdout
    assert "unknown" not in out.stdout


def test_controllers_are_reachable_after_import_batchsim():
    code = "import batchsim; print(batchsim.controllers.load_controllers.__name__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/", timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "load_controllers"


def test_view_of_a_file_needs_no_rclpy(tmp_path):
    """Issue 42: `batchsim view FILE` without ROS 2 said to install [view], which brings no
    rclpy: the view of a file imported rclpy for the replay's error class and through the worker
    package. Where rclpy does not import, a file that is not a recording is named as such."""
    need("mcap", "batchsim view needs the record extra")
    need("viser", "batchsim view needs the view extra")
    notes = tmp_path / "notes.txt"
    notes.write_text("not a recording\n")
    code = (
        "import runpy, sys\n"
        "sys.modules['rclpy'] = None  # as where ROS 2 is not installed: importing it fails\n"
        f"sys.argv = ['batchsim', 'view', {str(notes)!r}]\n"
        "runpy.run_module('batchsim.cli', run_name='__main__', alter_sys=True)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert one_error_line(out) == f"batchsim: error: {notes} is not an MCAP file (it does not start with MCAP's magic bytes)"


def test_install_hint_is_a_command_a_user_can_run():
    hint = startup.install_command("warp")
    assert hint == f"pip install -e '{ROOT}[warp]'"


# ---------------------------------------------------------------- benchmarks/throughput.py


@pytest.mark.slow  # over a few seconds: `make quick` leaves it out
def test_throughput_plot_keeps_the_auto_column_each_row_was_recorded_with(tmp_path):
    fields = "date,device,model,backend,nworld,nstep,contract_sps,raw_sps,ratio,auto,compile_s,note"
    rows = [  # recorded under an older rule: cpu up to 1024 worlds on this GPU host
        "2026-10-01,NVIDIA H200,humanoid,cpu,1024,10,500000,510000,0.98,cpu,1,",
        "2026-10-01,NVIDIA H200,humanoid,warp,1024,10,900000,910000,0.99,cpu,9,",
    ]
    (tmp_path / "old.csv").write_text("\n".join([fields, *rows]) + "\n")
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks/throughput.py"), "--plot", str(tmp_path / "old.csv"), "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    picks = [line.split() for line in out.stdout.splitlines() if line.strip().startswith("1024 ")]
    assert picks and picks[-1][1] == "cpu", out.stdout  # today's rule (warp from 512) would say warp


def test_an_internal_bug_is_not_passed_off_as_a_usage_error(monkeypatch, capsys):
    """Issue 22: main() caught every ValueError, so a bug exited 2 as a one-line usage error."""
    from batchsim import cli
    from batchsim.cli import runner

    def broken(argv):
        raise ValueError("an index went wrong somewhere")

    monkeypatch.setattr(runner, "run", broken)  # what main() calls once the flags parse
    with pytest.raises(ValueError, match="an index went wrong"):
        cli.main(["--no-ros"])

    def user_error(argv):
        raise OptionError("", "unknown backend 'foo' (choose from auto, cpu, mjx, warp)")

    monkeypatch.setattr(runner, "run", user_error)
    assert cli.main(["--backend", "foo"]) == 2
    assert capsys.readouterr().err.strip() == "batchsim: error: unknown backend 'foo' (choose from auto, cpu, mjx, warp)"


def test_ros_args_are_split_off_as_ros_executables_do():
    from batchsim.cli.args import split_ros_args

    ours, ros = split_ros_args(["--worlds", "2", "--ros-args", "-p", "use_sim_time:=true", "--", "--no-tf",
                                "--ros-args", "--log-level", "warn"])  # fmt: skip
    assert ours == ["--worlds", "2", "--no-tf"]
    assert ros == ["-p", "use_sim_time:=true", "--log-level", "warn"]
    assert split_ros_args(["--worlds", "2", "--", "x"]) == (["--worlds", "2", "--", "x"], [])


def test_the_bridge_flags_are_the_bridge_options_with_their_defaults():
    """ros_bridge.options declares each option's flag and default once: no flag given is
    BridgeOptions() (a recording only on request, no view); each flag sets its option."""
    from batchsim.cli.args import run_parser
    from batchsim.cli.bridge_flags import bridge_options, option_flag
    from ros_bridge.options import BridgeOptions, Reliability, ViewOptions

    def options(*argv: str):
        args = run_parser().parse_args(list(argv))
        args.ros_args = ["-p", "a:=1"] if argv else []
        return bridge_options(args)

    assert options() == BridgeOptions()
    given = options("--bridge-workers", "3", "--no-clock", "--no-tf", "--reliability", "best_effort", "--lockstep",
                    "--record-worlds", "0,2-3", "--view", "--view-port", "9000", "--ros2-control", "r.urdf")  # fmt: skip
    assert (given.workers, given.clock, given.tf, given.reliability, given.lockstep) == (3, False, False, Reliability.BEST_EFFORT, True)
    assert given.record.worlds == (0, 2, 3) and given.view == ViewOptions(port=9000)
    assert (given.description, given.ros_args) == ("r.urdf", ("-p", "a:=1"))
    assert option_flag("workers") == "--bridge-workers" and option_flag("control_rate") == "--control-rate"


def test_the_status_line_in_a_log_comes_every_10_s_unless_told():
    """Issue 23: in a log (stderr not a terminal) a status line a second is noise."""
    import io

    from batchsim.cli import StatusLine

    sim = batchsim.make("arm", 1, "cpu")
    loop = SimLoop(sim, rtf=1.0)
    stats = LoopStats(sim_time=1.0)
    for every, expected in ((None, 1), (0.1, 3)):
        stream = io.StringIO()
        status = StatusLine(loop, 1, "cpu", stream=stream, every=every)
        assert status.every == (10.0 if every is None else every)
        for _ in range(3):
            status.report(stats)
            time.sleep(0.12)
        assert len(stream.getvalue().splitlines()) == expected, stream.getvalue()
    out = batchsim_cli("--worlds", "1", "--no-ros", "--duration", "0.1", "--status-every", "0")
    assert out.returncode == 2 and "--status-every must be a finite number of seconds > 0" in out.stderr


@pytest.mark.parametrize("backend, batched", [("warp", True), ("cpu", False)])
def test_start_up_compiles_the_cameras_and_lidars_drawn_in_batched_kernels(backend, batched):
    """Issue 24: a warp rover fleet with cameras and lidars stalled 26 s at their first request
    (render and ray kernels compiled on first use): the compile stage renders and scans once,
    on the device and without noise (the noise streams stay at their start); the host
    renderer (cpu, mjx) has nothing to compile and is not asked."""
    from conftest import need

    if backend == "warp":
        need("warp")
    from batchsim.cli import runner

    sim = batchsim.make("rover", 2, backend)
    sim.configure()
    sim.activate()
    loop = SimLoop(sim, rtf=0)
    calls = []
    render, scan = sim.render, sim.scan
    sim.render = lambda name, *a, **k: calls.append(("render", name, k)) or render(name, *a, **k)
    sim.scan = lambda name, *a, **k: calls.append(("scan", name, k)) or scan(name, *a, **k)
    lines = []
    progress = startup.Progress()
    progress.stage = lambda text: (lines.append(text), contextlib.nullcontext())[1]
    sim.compiles_first_period = True  # the cpu row: the stage runs, its sensors are not drawn
    runner.compile_programs(sim, loop, progress)
    cameras, lidars = list(sim.sensors.cameras), list(sim.sensors.lidars)
    assert cameras and lidars
    if batched:
        assert calls == [("render", c, {"device": True}) for c in cameras] + [("scan", name, {"device": True}) for name in lidars]
        assert lines == ["compiling warp's program for 2 worlds and its 1 camera, 1 lidar"]
    else:
        assert calls == [] and lines == ["compiling cpu's program for 2 worlds"]
    assert sim.time[0] == 0.0  # reset after
    sim.shutdown()


# what the command's quick answers may not import: each costs a new user seconds (issue 46)
HEAVY = ("numpy", "mujoco", "rclpy", "jax", "warp", "yaml", "importlib.metadata")


@pytest.mark.parametrize("argv", [["--help"], ["--bogus"], ["--worlds", "x"], ["info", "--help"], ["view", "--bogus"], ["evaluate", "--help"]])
def test_help_and_usage_errors_are_answered_before_anything_heavy_is_imported(argv):
    """Issue 46: every command, `--help` and a mistyped flag spent 4-10 s importing MuJoCo and the
    backends before it parsed its arguments."""
    code = (
        "import sys\nfrom batchsim.cli import main\n"
        f"try:\n    rc = main({argv!r})\nexcept SystemExit as e:\n    rc = e.code\n"
        f"print(rc, sorted(m for m in {HEAVY!r} if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    rc, loaded = out.stdout.strip().splitlines()[-1].split(" ", 1)
    assert rc in ("0", "2") and loaded == "[]", out.stdout + out.stderr


def test_the_parsers_backend_names_are_the_registrys():
    from batchsim.backends import names
    from batchsim.cli.args import SHIPPED_BACKENDS

    assert list(SHIPPED_BACKENDS) == [b.value for b in batchsim.backends.Backend] == names()[:4]


@pytest.mark.timing
def test_a_mistyped_flag_and_help_answer_within_a_second():
    """Issue 46's check, timed alone (the `timing` tests run with nothing beside them)."""
    for argv in (["--bogus"], ["--help"], ["--version"]):
        start = time.monotonic()
        out = subprocess.run([sys.executable, "-m", "batchsim.cli", *argv], capture_output=True, text=True, timeout=60)
        took = time.monotonic() - start
        assert out.returncode in (0, 2) and took < 1.0, (argv, took, out.stderr)
