"""How long `batchsim view FILE` takes to serve a recording (issue 46: a 46 MB, 256-world recording
printed nothing for about 9 minutes before its URL line).

    .venv/bin/python benchmarks/view_open.py --worlds 256 --seconds 20
    .venv/bin/python benchmarks/view_open.py --file run.mcap      # an existing recording

Records `batchsim --worlds N --rtf 0 --duration S --record FILE` (the arm, on a private ROS domain)
unless --file is given, then runs `batchsim view FILE` and times its `view: http://...` line from
the command's start. Printed: the file's size, its worlds and the seconds to the URL line. Nothing
is asserted.
"""

from __future__ import annotations

import argparse
import os
import platform
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet import LOCALHOST, _pythonpath, _versions  # noqa: E402


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", type=int, default=256)
    p.add_argument("--seconds", type=float, default=20.0, help="sim seconds recorded")
    p.add_argument("--file", type=Path, default=None, help="time this recording instead of making one")
    p.add_argument("--domain", type=int, default=61)
    p.add_argument("--timeout", type=float, default=900.0, help="give up on the URL line after this many s")
    opts = p.parse_args()
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(opts.domain), "PYTHONPATH": _pythonpath()}
    path = opts.file
    if path is None:
        path = Path(tempfile.mkdtemp()) / "run.mcap"
        args = ["--worlds", str(opts.worlds), "--rtf", "0", "--duration", str(opts.seconds), "--quiet", "--record", str(path)]
        start = time.monotonic()
        subprocess.run([sys.executable, "-m", "batchsim.cli", *args], env=env, check=True, stdout=subprocess.DEVNULL)
        print(f"# recorded {opts.worlds} worlds x {opts.seconds:g} s in {time.monotonic() - start:.0f} s", flush=True)
    start = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "batchsim.cli", "view", str(path), "--view-port", str(_free_port())],
                            env=env, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)  # fmt: skip
    url = None
    try:
        for line in proc.stderr:
            if "view: http" in line:
                url = time.monotonic() - start
                break
            if time.monotonic() - start > opts.timeout:
                break
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    print(f"# {platform.node() or 'host'}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; {_versions()}; {time.strftime('%Y-%m-%d')}")
    took = f"{url:.1f}" if url is not None else f"none within {opts.timeout:g}"
    print(f"| {path.name} | {path.stat().st_size / 1e6:.0f} MB | view's URL line after {took} s |", flush=True)


if __name__ == "__main__":
    main()
