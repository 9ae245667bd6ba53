"""What the web view costs the loop: without it, with it and no browser, with a browser attached.

    .venv/bin/python benchmarks/view.py --repeat 3               # 64 arms at 100 Hz, 20 s per run
    .venv/bin/python benchmarks/view.py --worlds 1024 --backend warp

The loop runs in this process as `batchsim` runs it (the arm's default controllers, the ROS 2
bridge with its workers in processes, RTF 1). Three runs: no view; `--view` with nobody
looking; `--view` with a headless Chromium (Debian's, software WebGL where there is no GPU)
showing the page the whole time. Reported per run: the RTF held and the loop's own time per
period (the pacing sleep excluded: median, 99th percentile, worst). Nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # its siblings

from paced_fleet import paced_fleet, timed_run  # noqa: E402


def run(opts: argparse.Namespace, view: bool, browser: bool) -> dict:
    from ros_bridge.bridge import BridgeOptions
    from ros_bridge.options import ViewOptions

    with paced_fleet(opts, BridgeOptions(view=ViewOptions(port=opts.port) if view else None)) as (_sim, loop, _host):
        chrome = None
        if browser:
            chrome = subprocess.Popen(
                [opts.chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--window-size=1000,700", "--remote-debugging-port=0", f"http://localhost:{opts.port}"],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
            )  # fmt: skip
            time.sleep(5.0)  # the page loads and takes the scene

        def stop_browser() -> None:
            if chrome is not None:
                if opts.screenshot:  # what the page showed: proof that the browser drew the fleet
                    print(screenshot(opts, f"http://localhost:{opts.port}"), flush=True)
                os.killpg(chrome.pid, 9)
                chrome.wait()

        return timed_run(loop, after=stop_browser)


def screenshot(opts: argparse.Namespace, url: str) -> str:
    """A second headless Chromium's screenshot of the page into --screenshot, and how many of its
    pixels are the arm's orange-brown links (tests/test_view.py's test of the same)."""
    subprocess.run(
        [opts.chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--window-size=1000,700", "--virtual-time-budget=8000", f"--screenshot={opts.screenshot}", url],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=120, check=False,
    )  # fmt: skip
    try:
        import numpy as np
        from PIL import Image

        shot = np.asarray(Image.open(opts.screenshot).convert("RGB")).astype(int)
    except (OSError, ImportError) as e:
        return f"screenshot: none ({e})"
    r, g, b = shot[..., 0], shot[..., 1], shot[..., 2]
    arm = int(((r > 120) & (r - g > 40) & (g - b > 30)).sum())
    return f"screenshot: {opts.screenshot}, {shot.shape[1]}x{shot.shape[0]}, {arm} pixels of the arms' links"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--model", default="arm")
    p.add_argument("--backend", default="cpu")
    p.add_argument("--control-rate", type=float, default=100.0)
    p.add_argument("--duration", type=float, default=20.0, help="sim seconds per run")
    p.add_argument("--repeat", type=int, default=1, help="rounds of the three, one after the other (a shared machine's load drifts)")
    p.add_argument("--port", type=int, default=8099)
    p.add_argument("--domain", type=int, default=92)
    p.add_argument("--chromium", default=shutil.which("chromium"), help="the browser to attach (default: chromium on PATH)")
    p.add_argument("--screenshot", default=None, help="a PNG of the page taken at the end of each browser run")
    opts = p.parse_args()
    os.environ.update({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(opts.domain)})
    import mujoco
    import viser

    print(f"# {platform.node()}: {platform.machine()}, {os.cpu_count()} cores; Python {platform.python_version()}, "
          f"MuJoCo {mujoco.__version__}, viser {viser.__version__}")  # fmt: skip
    print(f"# {opts.worlds} x {opts.model} on {opts.backend}, control {opts.control_rate:g} Hz, {opts.duration:g} s per run")
    for label, view, browser in [("no view", False, False), ("view, no browser", True, False), ("view + Chromium", True, True)] * opts.repeat:
        r = run(opts, view, browser)
        print(f"{label:18s} rtf {r['rtf']:.3f} | loop's own time per period: median {r['median']:.3f} ms, "
              f"p99 {r['p99']:.3f} ms, worst {r['worst']:.2f} ms | {r['periods']} periods")  # fmt: skip


if __name__ == "__main__":
    main()
