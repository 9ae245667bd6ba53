"""Test helper: a `batchsim` process on its own ROS domain, and an rclpy client beside it.

    with Fleet(domain=20, args=["--worlds", "4"], log=tmp_path / "fleet.log") as fleet:
        js = fleet.latest(JointState, "/world_2/joint_states")
        fleet.wait(lambda: js.count > 3)

Each fleet runs on its own ROS_DOMAIN_ID (`domain_id()` hands out one that no other test
process on the machine holds) with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, so tests never
see each other's fleets or anything else on the machine. The process is
always stopped (SIGINT, then SIGKILL) when the fleet closes.
"""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from conftest import need

# a test file that imports this one skips where ROS is absent, and fails under the force flag
rclpy = need("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402

LOCALHOST = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


def stack_messages() -> dict[str, Any]:
    """The message modules of the ROS stack's tests (tf, actions, controller_manager), imported
    here: a missing interface package fails those tests, never skips them."""
    import control_msgs.action
    import controller_manager_msgs.srv
    import tf2_msgs.msg
    from builtin_interfaces.msg import Duration
    from nav_msgs.msg import Odometry
    from rclpy.action import ActionClient
    from rclpy.qos import DurabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    return dict(
        Duration=Duration, ActionClient=ActionClient, QoSProfile=QoSProfile, DurabilityPolicy=DurabilityPolicy,
        JointState=JointState, String=String, JointTrajectory=JointTrajectory, JointTrajectoryPoint=JointTrajectoryPoint,
        FJT=control_msgs.action.FollowJointTrajectory, srv=controller_manager_msgs.srv, TFMessage=tf2_msgs.msg.TFMessage,
        Odometry=Odometry,
    )  # fmt: skip


_DOMAIN_LOCKS = Path(tempfile.gettempdir()) / "batchsim-ros-domains"
_held: dict[int, int] = {}  # domain -> the locked file's descriptor, for as long as it is in use


def domain_id(base: int = 1) -> int:
    """A ROS domain no other test, pytest worker or concurrent test run on this machine is
    using: the first one from `base` up whose lock file this process can take. It stays
    taken until `release_domain` (Fleet.close calls it) or this process exits."""
    _DOMAIN_LOCKS.mkdir(exist_ok=True)
    for domain in [*range(base, 102), *range(1, base)]:  # 0..101: no clash with ephemeral ports
        if domain in _held:
            continue
        fd = os.open(_DOMAIN_LOCKS / f"{domain}.lock", os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        _held[domain] = fd
        return domain
    raise RuntimeError("no free ROS domain in 1..101: too many ROS tests running on this machine")


def release_domain(domain: int) -> None:
    fd = _held.pop(domain, None)
    if fd is not None:
        os.close(fd)  # closing the descriptor drops the lock


def children(pid: int) -> list[int]:
    """The processes whose parent is `pid` (Linux /proc)."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append(int(entry.name))
    return out


def cmdline(pid: int) -> list[str]:
    """A process's arguments; empty once it is gone (it may go while we look)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_text().split("\0")
    except OSError:
        return []


def bridge_workers(pid: int) -> dict[int, int]:
    """The bridge worker processes of batchsim process `pid`: worker index -> pid."""
    out = {}
    for child in children(pid):
        argv = cmdline(child)
        if "ros_bridge.worker" in argv:
            out[int(argv[argv.index("ros_bridge.worker") + 1])] = child
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def segments(pid: int) -> list[str]:
    """batchsim's shared-memory segments created by process `pid`."""
    return sorted(p.name for p in Path("/dev/shm").glob(f"batchsim_{pid}_*"))


class Latest:
    """A subscription that keeps the last message and counts them."""

    def __init__(self) -> None:
        self.msg: Any = None
        self.count = 0
        self.history: list[Any] = []
        self.keep = 0

    def __call__(self, msg: Any) -> None:
        self.msg = msg
        self.count += 1
        if self.keep:
            self.history.append(msg)
            del self.history[: -self.keep]


class Diagnostics:
    """A /diagnostics subscription keeping each world's last status: every bridge worker
    publishes its own worlds' DiagnosticArray."""

    def __init__(self) -> None:
        self.by_world: dict[str, Any] = {}
        self.count = 0

    def __call__(self, msg: Any) -> None:
        for status in msg.status:
            self.by_world[status.hardware_id] = status
        self.count += 1

    def world(self, namespace: str) -> Any:
        return self.by_world.get(namespace)

    def value(self, namespace: str, key: str, default: str = "") -> str:
        status = self.by_world.get(namespace)
        if status is None:
            return default
        return next((v.value for v in status.values if v.key == key), default)


class Fleet:
    """A `batchsim` subprocess and a client node on the same, private ROS domain."""

    def __init__(self, domain: int, args: Sequence[str], log: Path):
        self.domain = domain
        self.log_path = log
        env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
        self._log = open(log, "w+")
        self.proc = subprocess.Popen(
            # --controllers none: the raw bridge, without a shipped model's default controllers
            [sys.executable, "-m", "batchsim.cli", "--quiet", "--controllers", "none", *args],
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )
        os.environ.update(LOCALHOST)  # for this process's context, before init
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node(f"test_client_{domain}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._running = True
        self.spinning = threading.Lock()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()
        self._publishers: dict[str, Any] = {}

    def _spin(self) -> None:
        while self._running:
            try:
                with self.spinning:  # not while send_goal_async fills in its request (see send_goal)
                    self.executor.spin_once(timeout_sec=0.05)
            except (ExternalShutdownException, rclpy.executors.ShutdownException):
                return
            except Exception:
                if not self._running:
                    return

    def __enter__(self) -> Fleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def latest(self, msg_type: type, topic: str, keep: int = 0, qos: QoSProfile | int = 10) -> Latest:
        sink = Latest()
        sink.keep = keep
        self.node.create_subscription(msg_type, topic, sink, qos)
        return sink

    def diagnostics(self) -> Diagnostics:
        from diagnostic_msgs.msg import DiagnosticArray

        sink = Diagnostics()
        self.node.create_subscription(DiagnosticArray, "/diagnostics", sink, 10)
        return sink

    def publish(self, msg_type: type, topic: str, msg: Any, qos: QoSProfile | int = 10) -> None:
        self.advertise(msg_type, topic, qos).publish(msg)

    def advertise(self, msg_type: type, topic: str, qos: QoSProfile | int = 10) -> Any:
        """The publisher of `topic`, made on first use, without a message (wait_subscribed
        then waits for the fleet to match it): a message sent to make it may reach only
        some worlds, and under --lockstep it counts as a world's command."""
        pub = self._publishers.get(topic)
        if pub is None:
            pub = self._publishers[topic] = self.node.create_publisher(msg_type, topic, qos)
        return pub

    def publish_until(
        self, msg_type: type, topic: str, msg: Any, predicate: Callable[[], Any], timeout: float = 20.0, what: str = ""
    ) -> None:
        """Publish `msg` every 50 ms until `predicate()` holds: the first messages after
        discovery may be lost (best_effort), and a command is meant to be held anyway."""
        deadline = time.monotonic() + timeout
        while True:
            self.publish(msg_type, topic, msg)
            if predicate():
                return
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.wait(predicate, 0.0, what or f"the effect of {topic}")
            time.sleep(0.05)

    def send_goal(self, client: Any, goal: Any, feedback: Callable[[Any], None] | None = None, timeout: float = 40.0) -> Any:
        """An action goal's handle, once the server answered. A goal answered before the
        server had matched this client's reader is dropped by rmw_fastrtps ("failed to send
        response"), more often on a loaded machine: a goal with no answer in 10 s is sent
        again (a newer goal preempts a lost one that was accepted), up to `timeout`."""
        deadline = time.monotonic() + timeout
        while True:
            # rclpy's send_goal_async sends first and registers the answer's future after: an answer
            # the spinning thread takes in between raised ValueError in the future's done callback
            with self.spinning:
                sent = client.send_goal_async(goal, feedback_callback=feedback)
            try:
                self.wait(sent.done, min(10.0, max(0.0, deadline - time.monotonic())), "the goal's acceptance")
                return sent.result()
            except TimeoutError:
                if time.monotonic() >= deadline:
                    raise

    def wait_subscribed(self, topic: str, timeout: float = 20.0) -> None:
        """Wait until the fleet subscribes to `topic` (our publisher matched it)."""
        self.wait(lambda: self._publishers[topic].get_subscription_count() > 0, timeout, f"{topic} matched")

    def call(self, srv_type: type, name: str, request: Any, timeout: float = 20.0) -> Any:
        client = self.node.create_client(srv_type, name)
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                raise TimeoutError(f"service {name} did not appear in {timeout} s\n{self.log()}")
            future = client.call_async(request)
            self.wait(future.done, timeout, f"a reply from {name}")
            return future.result()
        finally:
            self.node.destroy_client(client)

    def wait_started(self, timeout: float = 60.0) -> None:
        """Until batchsim printed its start line: its workers are up."""
        self.wait(lambda: " x " in self.log() and "batchsim: " in self.log(), timeout, "the start line")

    def wait(self, predicate: Callable[[], Any], timeout: float = 20.0, what: str = "condition") -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            if self.proc.poll() is not None:
                raise RuntimeError(f"batchsim exited with {self.proc.returncode} while waiting for {what}\n{self.log()}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"no {what} within {timeout} s\n{self.log()[-3000:]}")
            time.sleep(0.02)

    def log(self) -> str:
        self._log.flush()
        return self.log_path.read_text()

    def close(self) -> int | None:
        """Stop batchsim (SIGINT, as Ctrl-C) and the client; the process's exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        if self._running:
            self._running = False
            self.executor.shutdown(timeout_sec=1.0)
            self._thread.join(timeout=2.0)
            self.node.destroy_node()
            rclpy.try_shutdown(context=self.context)
            self._log.close()
            release_domain(self.domain)
        return self.proc.returncode


def batchsim_process(args: Sequence[str], domain: int, log: Path) -> subprocess.Popen:
    """`batchsim ARGS` in its own process on `domain` (LOCALHOST discovery), its output into `log`."""
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", "batchsim.cli", *args], env=env, stdout=open(log, "w"), stderr=subprocess.STDOUT
    )


def spin_until_exit(executor: Any, proc: subprocess.Popen, timeout: float = 60.0, grace: float = 1.0) -> None:
    """Spin `executor` while `proc` runs (at most `timeout` s), then `grace` s more for what is in flight."""
    deadline = time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    end = time.monotonic() + grace
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)


def list_controllers(fleet: Fleet, controller_manager: str, timeout: float) -> Any:
    """controller_manager.controller_manager_services.list_controllers (its Python package is not
    on PyPI): the ListControllers service of `controller_manager` (a name relative to the root, as
    the client node there resolves it)."""
    from controller_manager_msgs.srv import ListControllers

    name = controller_manager if controller_manager.startswith("/") else "/" + controller_manager
    return fleet.call(ListControllers, f"{name}/list_controllers", ListControllers.Request(), timeout=timeout)


def check_controllers_running(fleet: Fleet, cnames: Sequence[str], namespace: str = "", state: str = "active") -> None:
    """controller_manager/test_utils.py's check_controllers_running (jazzy), line for line, the
    helper mujoco_ros2_control's launch tests call: it waits up to 10 s for a node named after
    each controller in the manager's namespace, then up to 10 s for list_controllers to show each
    in `state`. `fleet` stands for upstream's `node` (the graph query is its node's)."""
    node = fleet.node
    # wait for controller to be loaded before we call the CM services
    found = {cname: False for cname in cnames}  # Define 'found' as a dictionary
    start = time.time()
    # namespace is either "/" (empty) or "/ns" if set
    if namespace:
        namespace_api = namespace
        if not namespace_api.startswith("/"):
            namespace_api = "/" + namespace_api
        if namespace.endswith("/"):
            namespace_api = namespace_api[:-1]
    else:
        namespace_api = "/"

    while time.time() - start < 10.0 and not all(found.values()):
        node_names_namespaces = node.get_node_names_and_namespaces()
        for cname in cnames:
            if any(name == cname and ns == namespace_api for name, ns in node_names_namespaces):
                found[cname] = True
        time.sleep(0.1)
    assert all(found.values()), (
        f"Controller node(s) not found: {', '.join(['ns: ' + namespace_api + ', ctrl:' + cname for cname, is_found in found.items() if not is_found])}"
        f", but seeing {node.get_node_names_and_namespaces()}"
    )

    found = {cname: False for cname in cnames}  # Define 'found' as a dictionary
    start = time.time()
    # namespace is either "/" (empty) or "/ns" if set
    if not namespace:
        cm = "controller_manager"
    else:
        if namespace.endswith("/"):
            cm = namespace + "controller_manager"
        else:
            cm = namespace + "/controller_manager"
    while time.time() - start < 10.0 and not all(found.values()):
        controllers = list_controllers(fleet, cm, 5.0).controller
        assert controllers, "No controllers found!"
        for c in controllers:
            for cname in cnames:
                if c.name == cname and c.state == state:
                    found[cname] = True
                    break
        time.sleep(0.1)

    assert all(found.values()), (
        f"Controller(s) not found or not {state}: {', '.join([cname for cname, is_found in found.items() if not is_found])}"
    )

