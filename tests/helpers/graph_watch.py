"""A ROS participant that only watches the graph: `python tests/helpers/graph_watch.py [--server
HOST:PORT]` collects every topic and node it sees until SIGINT, then prints them as one JSON
line. Without --server it discovers the usual way (LOCALHOST, no Discovery Server), with it as
a Discovery Server super client (it sees every endpoint the server knows of)."""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--server", default=None)
    ap.add_argument("--name", default="graph_watch")
    a = ap.parse_args()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.pop("ROS_DISCOVERY_SERVER", None)
    os.environ.pop("ROS_SUPER_CLIENT", None)
    if a.server:
        os.environ.update(ROS_DISCOVERY_SERVER=a.server, ROS_SUPER_CLIENT="TRUE")
    import rclpy
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = Node(a.name)
    topics, nodes = set(), set()
    print("watching", flush=True)
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.1)
        topics.update(t for t, _ in node.get_topic_names_and_types())
        nodes.update(f"{ns.rstrip('/')}/{n}" for n, ns in node.get_node_names_and_namespaces())
    print(json.dumps({"topics": sorted(topics), "nodes": sorted(nodes)}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
