"""Browsers on a view's page, stood in for by websocket clients speaking viser's own protocol
(no browser, no ROS): a `PageClient` connects to the page's server and says where its camera
is (viser counts a connection as a client from its first camera message, and then runs the
page's on_client_connect: the view makes the browser's own pick), then sends what a browser
sends when its user types a world's number into the panel (`type_world`) or clicks a world in
the scene (`click`). What the page sent it is read but not kept: the tests look at the browser's
pick on the server's side (ros_bridge/worker/view_scene.py's Pick), made in its scope alone."""

from __future__ import annotations

import contextlib
import threading
import time

import msgspec.msgpack
import viser
import websockets.exceptions
import websockets.sync.client as ws_client
import zstandard


class PageClient:
    """One browser's connection to the page served on 127.0.0.1:`port`."""

    def __init__(self, port: int):
        self.ws = ws_client.connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                                    open_timeout=10, max_size=None)  # fmt: skip
        self.messages: list[dict] = []  # what the page sent it (their binary arrays left out), in order
        self._reader = threading.Thread(target=self._drain, daemon=True)
        self._reader.start()
        self.send({"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.0, 10.0], "fov": 1.3,
                   "near": 0.01, "far": 1000.0, "image_height": 480, "image_width": 640, "look_at": [0.0, 0.0, 0.0],
                   "up_direction": [0.0, 0.0, 1.0]})  # fmt: skip

    def _drain(self) -> None:
        """The page's messages, as its page decodes them: a window of messages is a zstd-compressed
        msgpack map (after its two sizes, 8 bytes each), then its binary arrays."""
        with contextlib.suppress(websockets.exceptions.ConnectionClosed, OSError):
            for raw in self.ws:
                size = int.from_bytes(raw[8:16], "little")
                window = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(raw[16 : 16 + size]))
                self.messages += window["messages"]

    def gui(self, kind: str, label: str) -> dict | None:
        """The newest GUI element of message type `kind` (e.g. "GuiNumberMessage") labelled `label` the page made here."""
        return next((m for m in reversed(self.messages) if m["type"] == kind and m.get("props", {}).get("label") == label), None)

    def send(self, message: dict) -> None:
        self.ws.send(msgspec.msgpack.encode(message))

    def scene_node(self, name: str) -> dict:
        """What this browser was last told of scene node `name`: its `position`, its props (`text`, ...)."""
        out: dict = {}
        for m in list(self.messages):
            if m.get("name") == name:
                out.update(m.get("props", {}), **m.get("updates", {}), **({"position": m["position"]} if "position" in m else {}))
        return out

    def type_world(self, world: int) -> None:
        """A world's number typed into the panel's world field."""
        picker = wait(lambda: self.gui("GuiNumberMessage", "world"), 10, "the panel's world field")
        self.send({"type": "GuiUpdateMessage", "uuid": picker["uuid"], "updates": {"value": world}})

    def click(self, node: str, instance: int) -> None:
        """A click on instance `instance` of the page's (server-wide) scene node `node`."""
        self.send({"type": "SceneNodeClickMessage", "name": node, "instance_index": instance, "ray_origin": [0.0, 0.0, 10.0],
                   "ray_direction": [0.0, 0.0, -1.0], "screen_pos": [0.5, 0.5], "modifier": None, "owner": ""})  # fmt: skip

    def close(self) -> None:
        self.ws.close()
        self._reader.join(timeout=5)


def connect(scene, timeout: float = 20.0):
    """A new PageClient on `scene`'s page (a FleetScene) and its pick, once the page made it."""
    before = {p.client.client_id for p in scene.picks()}
    client = PageClient(scene.server.get_port())
    pick = wait(lambda: next((p for p in scene.picks() if p.client.client_id not in before), None), timeout, "the new browser's pick")
    return client, pick


def wait(predicate, timeout: float, what: str):
    """`predicate()`'s first true value, tried every 20 ms; TimeoutError naming `what` after `timeout` s."""
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.02)
    return value
