"""The fleet's services, in rclpy (the pip install has no `ros2` CLI): reset a world or every
world, pause and resume, step one period while paused, start and stop a recording.

    python examples/fleet_services.py reset --world 3     # ros2 service call /world_3/reset std_srvs/srv/Trigger
    python examples/fleet_services.py reset               # /batchsim/reset: every world
    python examples/fleet_services.py pause               # /batchsim/pause {data: true}
    python examples/fleet_services.py step                # /batchsim/step: one control period
    python examples/fleet_services.py resume              # /batchsim/pause {data: false}
    python examples/fleet_services.py record              # /batchsim/record {data: true}
    python examples/fleet_services.py stop-recording      # /batchsim/record {data: false}

Prints the service's answer; exit 0 when it succeeded.
"""

from __future__ import annotations

import argparse
import sys

import rclpy
from rclpy.node import Node
from std_srvs.srv import SetBool, Trigger

TIMEOUT = 30.0  # s to find the service, and for its answer

SERVICES = {  # what -> (type, name, request)
    "pause": (SetBool, "/batchsim/pause", lambda: SetBool.Request(data=True)),
    "resume": (SetBool, "/batchsim/pause", lambda: SetBool.Request(data=False)),
    "step": (Trigger, "/batchsim/step", Trigger.Request),
    "record": (SetBool, "/batchsim/record", lambda: SetBool.Request(data=True)),
    "stop-recording": (SetBool, "/batchsim/record", lambda: SetBool.Request(data=False)),
}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=["reset", *SERVICES])
    p.add_argument("--world", type=int, default=None, help="reset: this world only")
    p.add_argument("--namespace", default="world_{i}", help="as batchsim's --namespace")
    opts = p.parse_args()
    if opts.what == "reset":
        name = "/batchsim/reset" if opts.world is None else f"/{opts.namespace.format(i=opts.world)}/reset"
        srv_type, make = Trigger, Trigger.Request
    else:
        srv_type, name, make = SERVICES[opts.what]
    rclpy.init()
    node = Node("batchsim_example_services")
    try:
        client = node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=TIMEOUT):
            sys.exit(f"no service {name}")
        future = client.call_async(make())
        rclpy.spin_until_future_complete(node, future, timeout_sec=TIMEOUT)
        if not future.done():
            sys.exit(f"{name}: no answer within {TIMEOUT:g} s")
        answer = future.result()
        print(f"{name}: {'ok' if answer.success else 'failed'}: {answer.message}")
        return 0 if answer.success else 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
