"""JointState messages per second from one Python process: message objects against bulk bytes.

    .venv/bin/python benchmarks/messages.py                       # 256 topics, one subscriber process
    .venv/bin/python benchmarks/messages.py --topics 1024 --subscribers 0

Two ways to publish every world's joint_states each period, interleaved in rounds in one
process (what a bridge worker does for its worlds):

  objects  a preallocated sensor_msgs/JointState per world whose float64 sequences are
           NumPy views of the message's own storage, filled in place, then publish(msg):
           rclpy converts the Python message to C and serializes it, per world
  bulk     ros_bridge.messages.BulkMessages: every world's message as a CDR byte row, all
           rows filled with one NumPy assignment, then publish(bytes): no conversion, no
           serialization in publish

A subscriber process (raw, counting) takes every topic unless --subscribers 0, so publish
does the work it does in a fleet. Prints messages/s per process, median of the rounds.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

JOINTS = tuple(f"joint{i}" for i in range(1, 7))


def subscribe(domain: int, topics: int) -> None:
    """Count raw messages on every topic until stdin closes; print the count."""
    import rclpy
    from rclpy.context import Context
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import JointState

    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = Node("messages_benchmark_sub", context=context)
    count = [0]

    def callback(msg: bytes) -> None:
        count[0] += 1

    for w in range(topics):
        node.create_subscription(JointState, f"/world_{w}/joint_states", callback, 10, raw=True)
    executor = EventsExecutor(context=context)
    executor.add_node(node)
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    print("ready", flush=True)
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
    print(count[0], flush=True)
    rclpy.try_shutdown(context=context)


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--subscribe":
        subscribe(int(sys.argv[2]), int(sys.argv[3]))
        return
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--topics", type=int, default=256)
    p.add_argument("--subscribers", type=int, default=1, choices=(0, 1))
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--seconds", type=float, default=1.5, help="per round and way")
    p.add_argument("--domain", type=int, default=72)
    args = p.parse_args()

    import numpy as np
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from sensor_msgs.msg import JointState

    from batchsim.controllers.topics import MessageKind, Output
    from ros_bridge.plan import Field, OutputSpec
    from ros_bridge.worker.messages import BulkMessages, new_message

    n = args.topics
    context = Context()
    rclpy.init(context=context, domain_id=args.domain)
    node = Node("messages_benchmark", context=context)
    pubs = [node.create_publisher(JointState, f"/world_{w}/joint_states", 10) for w in range(n)]
    sub = None
    if args.subscribers:
        sub = subprocess.Popen(
            [sys.executable, __file__, "--subscribe", str(args.domain), str(n)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert sub.stdout.readline().strip() == "ready"
        deadline = time.monotonic() + 60
        while not all(p.get_subscription_count() for p in pubs) and time.monotonic() < deadline:
            time.sleep(0.1)

    state = np.random.default_rng(0).random((n, 18))
    namespaces = [f"world_{w}" for w in range(n)]
    output = Output("joint_states", MessageKind.JOINT_STATE, dict, names=JOINTS)
    built = [new_message(output, ns) for ns in namespaces]
    views = [(b.msg, b.views["position"], b.views["velocity"], b.views["effort"]) for b in built]
    spec = OutputSpec(
        "joint_states", "sensor_msgs/msg/JointState",
        tuple(Field(f, 0, tuple(range(6 * k, 6 * k + 6))) for k, f in enumerate(("position", "velocity", "effort"))),
        names=JOINTS,
    )  # fmt: skip
    bulk = BulkMessages(spec, namespaces)

    def objects(k: int) -> None:
        pos, vel, eff = state[:, 0:6], state[:, 6:12], state[:, 12:18]
        for w, (msg, vp, vv, ve) in enumerate(views):
            msg.header.stamp.sec = k
            vp[:] = pos[w]
            vv[:] = vel[w]
            ve[:] = eff[w]
            pubs[w].publish(msg)

    def in_bulk(k: int) -> None:
        bulk.fill(state, k, 0)
        payload = bulk.payload
        for w, pub in enumerate(pubs):
            pub.publish(payload(w))

    rates: dict[str, list[float]] = {"objects": [], "bulk": []}
    for _ in range(args.rounds):
        for name, way in (("objects", objects), ("bulk", in_bulk)):
            k, start = 0, time.perf_counter()
            while time.perf_counter() - start < args.seconds:
                way(k)
                k += 1
            rates[name].append(k * n / (time.perf_counter() - start))
    received = None
    if sub is not None:
        sub.stdin.close()
        received = int(sub.stdout.readline() or 0)
        sub.wait(timeout=20)
    print(
        f"# {platform.node() or 'host'}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}, "
        f"{n} topics, {'one subscriber process' if sub else 'no subscriber'}, {args.rounds} rounds of {args.seconds:g} s, "
        f"load {os.getloadavg()[0]:.1f}, {time.strftime('%Y-%m-%d')}"
    )
    for name, values in rates.items():
        median = statistics.median(values)
        print(f"{name:8s} {median:10,.0f} messages/s  {1e6 / median:6.1f} us each  (rounds {min(values):,.0f} .. {max(values):,.0f})")
    print(f"bulk / objects {statistics.median(rates['bulk']) / statistics.median(rates['objects']):.2f}")
    if received is not None:
        print(f"the subscriber received {received:,} of {int(sum(sum(v) * args.seconds for v in rates.values())):,} published")
    rclpy.try_shutdown(context=context)


if __name__ == "__main__":
    main()
