"""Discovery time against endpoints: how long until every world's joint_states reach the
subscribers, with the default endpoints and with every topic created at start; and what a node
per controller costs (`--controller-nodes`, ros_bridge/worker/controller_nodes.py).

    .venv/bin/python benchmarks/discovery.py --worlds 256,1024
    .venv/bin/python benchmarks/discovery.py --worlds 1024 --bridge-workers 8 --subscriber-processes 8
    .venv/bin/python benchmarks/discovery.py --worlds 16,64,256 --controllers default --variants nodes-off,nodes-on

Per size and variant: K subscriber processes (joint_states of every world, counted raw)
start first; then `batchsim --rtf 1 --publish-rate 10` (the arm, no controllers unless
--controllers). "heard after" is from batchsim's start line (its workers up) until every
world was heard; "up after" from the process's start to that line. The endpoints per world are
counted from the ROS graph by a probe node once every world was heard (publishers +
subscriptions of the world's topics + 2 per service), and so are the nodes in the graph.
Variants: default, all-topics (--all-topics), nodes-on and nodes-off (--controller-nodes).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet import LOCALHOST, Batchsim, Subscribers  # noqa: E402


def endpoints_per_world(domain: int, worlds: int) -> tuple[float, int]:
    """Endpoints batchsim serves per world, from the graph (its topics under world_<i>/), and the
    nodes in the graph."""
    os.environ.update(LOCALHOST)
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node

    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = Node("discovery_probe", context=context)
    try:
        time.sleep(3.0)  # the probe's own discovery
        probe = ["/world_0", f"/world_{worlds // 2}", f"/world_{worlds - 1}"]
        total = 0
        for name, _types in node.get_topic_names_and_types():
            if any(name.startswith(p + "/") for p in probe):
                total += sum(1 for i in node.get_publishers_info_by_topic(name) if i.node_name.startswith("batchsim"))
                total += sum(1 for i in node.get_subscriptions_info_by_topic(name) if i.node_name.startswith("batchsim"))
        for name, _types in node.get_service_names_and_types():
            if any(name.startswith(p + "/") for p in probe):
                total += 2  # a request reader and a reply writer
        return total / len(probe), len(node.get_node_names()) - 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", default="256")
    p.add_argument("--backend", default="cpu")
    p.add_argument("--controllers", default="none")
    p.add_argument("--bridge-workers", type=int, default=None)
    p.add_argument("--subscriber-processes", type=int, default=max(1, min(8, (os.cpu_count() or 2) // 2)))
    p.add_argument("--variants", default="default,all-topics")
    p.add_argument("--timeout", type=float, default=300.0)
    p.add_argument("--domain", type=int, default=73)
    args = p.parse_args()
    print(
        f"# {platform.node() or 'host'}, {os.cpu_count()} cores, Python {platform.python_version()}, {args.backend} arm, "
        f"controllers {args.controllers}, {args.subscriber_processes} subscriber processes, "
        f"bridge workers {args.bridge_workers if args.bridge_workers is not None else 'default'}, "
        f"load {os.getloadavg()[0]:.1f}, {time.strftime('%Y-%m-%d')}"
    )
    print("| worlds | variant | nodes | endpoints per world | up after s | all worlds heard after s |")
    print("| --- | --- | --- | --- | --- | --- |", flush=True)
    for worlds in (int(w) for w in args.worlds.split(",")):
        for variant in args.variants.split(","):
            cmd = ["--worlds", str(worlds), "--backend", args.backend, "--controllers", args.controllers, "--rtf", "1"]
            cmd += ["--publish-rate", "10", "--quiet"]
            if args.bridge_workers is not None:
                cmd += ["--bridge-workers", str(args.bridge_workers)]
            if variant == "all-topics":
                cmd.append("--all-topics")
            elif variant.startswith("nodes-"):
                cmd += ["--controller-nodes", variant.removeprefix("nodes-")]
            subs = Subscribers(args.domain, worlds, args.subscriber_processes, "world_{i}")
            try:
                time.sleep(1.0)
                launched = time.time()
                b = Batchsim(cmd, args.domain)
                try:
                    b.wait_started(args.timeout)
                    deadline = time.time() + args.timeout
                    while subs.all_heard() is None and time.time() < deadline and b.proc.poll() is None:
                        time.sleep(0.05)
                    heard = subs.all_heard()
                    after = (heard - b.started) if heard is not None else float("nan")
                    per_world, nodes = endpoints_per_world(args.domain, worlds)
                    up = (b.started or float("nan")) - launched
                finally:
                    b.stop()
            finally:
                subs.close()
            print(f"| {worlds} | {variant} | {nodes} | {per_world:.0f} | {up:.1f} | {after:.1f} |", flush=True)


if __name__ == "__main__":
    main()
