"""The web view (`batchsim --view`), in a real browser: headless Chromium (Debian's chromium and
chromium-driver; .ci/run installs them), driven over the WebDriver protocol, loads the page of a
running fleet; the screenshot's pixels show the robots, picking a world shows its status (a
world whose commands are rejected says `bad command`), and the page keeps up with the fleet."""

from __future__ import annotations

import base64
import contextlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
from conftest import need
from ros_fleet import LOCALHOST, domain_id, release_domain

rclpy = need("rclpy")
need("viser")
imageio = need("imageio")

# alone (the Makefile's second pass): software WebGL beside the other test process on 2 cores
# left a picked world unshown for 20 s (a CI run), and the page's RTF is a rate
pytestmark = [pytest.mark.ros, pytest.mark.timing]
CHROMIUM, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")
if not (CHROMIUM and DRIVER):
    if os.environ.get("BATCHSIM_FORCE_BACKENDS") == "1":
        raise RuntimeError("chromium and chromedriver are missing (Debian: apt-get install chromium chromium-driver)")
    pytest.skip("chromium and chromedriver are not installed", allow_module_level=True)


# types a number into the panel's world field as a user would (React sees an input event)
PICK = "const input = document.querySelector('input.mantine-NumberInput-input'); input.focus(); input.select();"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Browser:
    """Headless Chromium through chromedriver's WebDriver HTTP API (no selenium needed)."""

    def __init__(self) -> None:
        self.port = _free_port()
        self.driver = subprocess.Popen(  # a session of its own: close() ends chromium with it, however the test ends
            [DRIVER, f"--port={self.port}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
        )
        args = ["--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--window-size=1000,700"]
        # a script waits up to 150 s (chromedriver's default: 30): the page's thread was seen held for
        # minutes right after a world was picked on a machine whose /dev/shm held thousands of stale
        # Fast DDS segments from earlier runs (with them removed it took 18 s); headroom, not a cure
        always = {"goog:chromeOptions": {"binary": CHROMIUM, "args": args}, "timeouts": {"script": 150_000}}
        caps = {"capabilities": {"alwaysMatch": always}}
        deadline = time.monotonic() + 30
        while True:
            try:
                self.session = self.call("POST", "/session", caps)["sessionId"]
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)

    def call(self, method: str, path: str, body: dict | None = None):
        data = json.dumps(body).encode() if body is not None else None
        request = urllib.request.Request(f"http://127.0.0.1:{self.port}{path}", data=data, method=method)
        request.add_header("Content-Type", "application/json")
        try:
            with urllib.request.urlopen(request, timeout=180) as reply:
                return json.loads(reply.read())["value"]
        except urllib.error.HTTPError as e:  # WebDriver's own message says what went wrong
            raise RuntimeError(f"{method} {path}: {e.code} {e.read().decode(errors='replace')[:500]}") from None

    def session_call(self, method: str, path: str, body: dict | None = None):
        return self.call(method, f"/session/{self.session}{path}", body)

    def text(self) -> str:
        return self.session_call("POST", "/execute/sync", {"script": "return document.body.innerText", "args": []})

    def screenshot(self) -> np.ndarray:
        return imageio.v3.imread(base64.b64decode(self.session_call("GET", "/screenshot")))

    def robot_pixels(self, save=None) -> int:
        """The screenshot's pixels of the arm's orange-brown links (lit or shaded) left of the
        panel; the screenshot saved to `save` (to look at when a test fails)."""
        shot = self.screenshot()[..., :3].astype(int)
        if save is not None:
            imageio.v3.imwrite(save, shot.astype(np.uint8))
        r, g, b = shot[..., 0], shot[..., 1], shot[..., 2]
        return int(((r > 120) & (r - g > 40) & (g - b > 30))[:, : shot.shape[1] * 2 // 3].sum())

    def type_into(self, focus: str, text: str) -> None:
        """Type `text` and Enter, as a user would, into the field the script `focus` selects."""
        self.session_call("POST", "/execute/sync", {"script": focus, "args": []})
        keys = [{"type": kind, "value": key} for key in text + "\ue007" for kind in ("keyDown", "keyUp")]
        self.session_call("POST", "/actions", {"actions": [{"type": "key", "id": "keyboard", "actions": keys}]})

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.call("DELETE", f"/session/{self.session}")
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.driver.pid, signal.SIGKILL)
        self.driver.wait()


def _wait(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.2)
    return value


def test_the_view_shows_the_robots_a_picked_worlds_status_and_keeps_up(tmp_path):
    from rclpy.context import Context
    from rclpy.node import Node
    from std_msgs.msg import Float64MultiArray

    domain, port = domain_id(72), _free_port()
    log = tmp_path / "log"
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain)}
    args = ["--worlds", "4", "--quiet", "--controllers", "none", "--view", "--view-port", str(port)]
    proc = subprocess.Popen([sys.executable, "-m", "batchsim.cli", *args], env=env, stdout=open(log, "w"), stderr=subprocess.STDOUT)
    os.environ.update(LOCALHOST)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = Node("test_view_client", context=context)
    browser = None
    # world 3's commands are rejected (one value where the arm takes six): BAD_COMMAND
    pub = node.create_publisher(Float64MultiArray, "/world_3/commands", 10)
    try:
        line = _wait(lambda: next((x for x in log.read_text().splitlines() if x.startswith("batchsim: view: ")), None), 60,
                     "the view's line")  # fmt: skip
        url = line.split()[2]
        assert url == f"http://localhost:{port}"
        browser = Browser()
        browser.session_call("POST", "/url", {"url": url})
        _wait(lambda: "4 worlds" in browser.text(), 30, "the fleet's panel")
        _wait(lambda: pub.publish(Float64MultiArray(data=[0.1])) or "bad command 1" in browser.text(), 30, "world 3's bad command")
        time.sleep(2.0)  # the meshes arrive and are drawn (software WebGL)
        assert browser.robot_pixels(save=tmp_path / "view.png") > 300, "no robot in the screenshot"
        # pick world 3 by its number: the panel names it and says why it is not fine
        browser.type_into(PICK, "3")
        _wait(lambda: "world_3 (world 3): bad command" in browser.text(), 20, f"world 3's status\n{browser.text()}")
        no_image = f"return document.querySelectorAll(\"{CAMERA_IMAGE}\").length"
        assert browser.session_call("POST", "/execute/sync", {"script": no_image, "args": []}) == 0  # the arm has no camera
        # the page keeps up: the sim time it shows advances with the fleet (RTF 1)
        def shown() -> float:
            text = browser.text()
            return float(text.split("sim time ", 1)[1].split(" s", 1)[0])

        t0, w0 = shown(), time.monotonic()
        time.sleep(3.0)
        advanced = shown() - t0
        assert advanced > 0.5 * (time.monotonic() - w0), (advanced, browser.text())
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        if browser is not None:
            browser.close()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        release_domain(domain)


def test_the_view_shows_the_picked_worlds_camera_image(tmp_path):
    domain, port = domain_id(72), _free_port()
    log = tmp_path / "log"
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain)}
    args = ["--model", "rover", "--worlds", "2", "--quiet", "--controllers", "none", "--camera-resolution", "64x48",
            "--camera-rate", "20", "--view", "--view-port", str(port)]  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-m", "batchsim.cli", *args], env=env, stdout=open(log, "w"), stderr=subprocess.STDOUT)
    browser = None
    try:
        _wait(lambda: "batchsim: view: " in log.read_text(), 60, "the view's line")
        browser = Browser()
        browser.session_call("POST", "/url", {"url": f"http://localhost:{port}"})
        _wait(lambda: "front_camera (world 0)" in browser.text(), 30, f"the camera image's label\n{browser.text()}")
        browser.type_into(PICK, "1")
        _wait(lambda: "front_camera (world 1)" in browser.text(), 20, f"world 1's camera\n{browser.text()}")

        def image() -> list[np.ndarray] | None:  # the <img> on the page, as drawn: world 1's frame once it came
            found = browser.session_call("POST", "/element", {"using": "css selector", "value": CAMERA_IMAGE})
            shot = browser.session_call("GET", f"/element/{next(iter(found.values()))}/screenshot")
            pixels = imageio.v3.imread(base64.b64decode(shot))[..., :3].astype(int)
            return [pixels] if pixels.std() > 5 else None  # not the grey it shows until a frame comes

        [pixels] = _wait(image, 20, "a camera frame in the panel")
        imageio.v3.imwrite(tmp_path / "camera.png", pixels.astype(np.uint8))
        size = browser.session_call("POST", "/execute/sync", {"script": IMAGE_SIZE, "args": []})
        assert size == [64, 48]  # the camera's own frame, not a placeholder of another size
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        if browser is not None:
            browser.close()
        release_domain(domain)


CAMERA_IMAGE = "img[src^='blob:']"  # the panel's image, from an object URL of the JPEG viser sends (its logo is an SVG)
IMAGE_SIZE = f"const img = document.querySelector(\"{CAMERA_IMAGE}\"); return [img.naturalWidth, img.naturalHeight];"


def test_a_recording_in_the_view_shows_the_robots_and_scrubs(tmp_path):
    domain, port = domain_id(72), _free_port()
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain)}
    path = tmp_path / "run.mcap"
    try:
        args = ["--worlds", "2", "--quiet", "--controllers", "none", "--rtf", "0", "--duration", "1", "--record", str(path)]
        subprocess.run([sys.executable, "-m", "batchsim.cli", *args], env=env, check=True, capture_output=True, timeout=120)
    finally:
        release_domain(domain)
    log = tmp_path / "log"
    proc = subprocess.Popen([sys.executable, "-m", "batchsim.cli", "view", str(path), "--view-port", str(port)],
                            stdout=open(log, "w"), stderr=subprocess.STDOUT)  # fmt: skip
    browser = None
    try:
        _wait(lambda: "batchsim: view: " in log.read_text(), 60, "the view's line")
        assert re.search(rf"\({re.escape(str(path))}: 2 worlds, sim time 0\.00 \.\. 0\.9\d s\)", log.read_text())
        browser = Browser()
        browser.session_call("POST", "/url", {"url": f"http://localhost:{port}"})
        _wait(lambda: re.search(r"sim time 0\.00 s of 0\.00 \.\. 0\.9\d s", browser.text()), 30, "the recording's panel")
        assert "world_0 (world 0): running" in browser.text()  # the status, from the recording's /diagnostics
        time.sleep(2.0)  # the meshes arrive and are drawn
        assert browser.robot_pixels() > 300, "no robot in the screenshot"
        # scrub: the slider's number field takes 0.5 s, and the page shows that moment
        browser.type_into(SLIDER, "0.5")
        _wait(lambda: re.search(r"sim time 0\.5\d s of", browser.text()), 20, "the scrubbed time")  # the frame at 0.5 s
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        if browser is not None:
            browser.close()


def test_the_view_of_a_fleet_of_groups_shows_every_groups_worlds(tmp_path):
    """A fleet of two groups (2 arms; 2 arms beside a rover): one page of all 4 worlds, each
    drawn with its group's robots, and a picked world of the second group shows its status."""
    import yaml

    depot = tmp_path / "depot.yaml"
    depot.write_text(yaml.safe_dump({"groups": [
        {"name": "arms", "worlds": 2, "robots": [{"name": "arm", "model": "arm"}]},
        {"name": "yard", "worlds": 2, "robots": [{"name": "arm", "model": "arm"},
                                                  {"name": "rover", "model": "rover", "pose": [0.0, 2.0, 0.0, 0.0]}]},
    ]}))  # fmt: skip
    domain, port = domain_id(72), _free_port()
    log = tmp_path / "log"
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain)}
    args = ["--fleet", str(depot), "--backend", "cpu", "--quiet", "--controllers", "none", "--bridge-workers", "1",
            "--view", "--view-port", str(port)]  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-m", "batchsim.cli", *args], env=env, stdout=open(log, "w"), stderr=subprocess.STDOUT)
    browser = None
    try:
        _wait(lambda: "batchsim: view: " in log.read_text(), 60, "the view's line")
        assert log.read_text().count("batchsim: view: ") == 1  # one page for both groups
        browser = Browser()
        browser.session_call("POST", "/url", {"url": f"http://localhost:{port}"})
        _wait(lambda: "4 worlds" in browser.text() and "running 4" in browser.text(), 30, f"the fleet's panel\n{browser.text()}")
        time.sleep(2.0)  # the meshes arrive and are drawn (software WebGL)
        assert browser.robot_pixels(save=tmp_path / "view.png") > 300, "no robot in the screenshot"
        browser.type_into(PICK, "3")
        _wait(lambda: "world_3 (world 3): running" in browser.text(), 20, f"world 3's status\n{browser.text()}")
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        if browser is not None:
            browser.close()
        release_domain(domain)


# the slider's own number field (the second number input of the panel, after the world's)
SLIDER = "const input = document.querySelectorAll('input.mantine-NumberInput-input')[1]; input.focus(); input.select();"
