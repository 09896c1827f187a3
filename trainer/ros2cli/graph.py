"""The one short-lived rclpy node every graph verb uses, and ROS name helpers.

Like ros2cli without its daemon (`--no-daemon`): the node is created, spun for `--spin-time`
seconds so that discovery fills its view of the graph, and then asked. ros2cli stops after the
spin time; a listing here also keeps spinning (at most four more seconds) until the graph has
not changed for a second, and a verb about one named node or topic (param, lifecycle, echo,
hz) skips that and waits (as long) for its target instead, so that no verb answers from a
half-discovered graph (with Fast DDS's default 3 s participant announcements a running node
was found at once or after 1.8-2.8 s (scripts/bench_discovery.py); the environment's sim_bridge/fastdds_discovery.xml
announces every 0.5 s, bounding it to about 0.6 s).
"""
from __future__ import annotations

import argparse
import os
import time
from contextlib import contextmanager
from typing import Callable, Iterator, NamedTuple

import rclpy
from rclpy.parameter import Parameter

HIDDEN_PREFIX = "_"
NODE_NAME_PREFIX = "_ros2cli"
DEFAULT_SPIN_TIME = 0.5
SETTLE_MAX_S = 4.0
SETTLE_QUIET_S = 1.0
#: With no other participant heard of by spin time + this, the graph is taken as empty: the
#: environment's Fast DDS profile announces participants every 0.5 s, so a running node would
#: have been heard of by then (an empty graph took the whole SETTLE_MAX_S, 4.9 s in all).
EMPTY_GRAPH_S = 1.0


class NodeName(NamedTuple):
    name: str
    namespace: str
    full_name: str


def add_node_arguments(parser: argparse.ArgumentParser) -> None:
    """The options ros2cli's node strategy adds to every graph verb."""
    parser.add_argument("--spin-time", type=float, default=DEFAULT_SPIN_TIME,
                        help="Spin time in seconds to wait for discovery (there is no daemon here)")
    parser.add_argument("-s", "--use-sim-time", action="store_true", help="Enable ROS simulation time")
    parser.add_argument("--no-daemon", action="store_true",
                        help="Accepted for ros2cli compatibility: this front-end never uses a daemon")


def is_hidden(name: str) -> bool:
    return any(part.startswith(HIDDEN_PREFIX) for part in name.split("/"))


def absolute(name: str | None) -> str | None:
    if not name:
        return None
    return name if name.startswith("/") else "/" + name


def parse_node_name(full: str) -> NodeName:
    full = absolute(full) or "/"
    namespace, base = full.rsplit("/", 1)
    return NodeName(base, namespace or "/", full)


def node_names(node, include_hidden: bool = False) -> list[NodeName]:
    return [NodeName(n, ns, ns + ("" if ns.endswith("/") else "/") + n)
            for n, ns in node.get_node_names_and_namespaces()
            if include_hidden or (n and not n.startswith(HIDDEN_PREFIX))]


def wait_for(predicate: Callable[[], bool], node, timeout: float = SETTLE_MAX_S) -> bool:
    """Spin `node` until `predicate()` holds or `timeout` passes."""
    deadline = time.monotonic() + timeout
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline:
            return False
        rclpy.spin_once(node, timeout_sec=0.05)


def wait_for_node(node, full_name: str | None, include_hidden: bool = False,
                  timeout: float = SETTLE_MAX_S) -> bool:
    return bool(full_name) and wait_for(
        lambda: full_name in {n.full_name for n in node_names(node, include_hidden)}, node, timeout)


def _graph_signature(node) -> tuple:
    return (tuple(sorted(node.get_node_names_and_namespaces())),
            tuple(sorted((n, tuple(t)) for n, t in node.get_topic_names_and_types())),
            tuple(sorted((n, tuple(t)) for n, t in node.get_service_names_and_types())))


def _settle(node, spin_time: float) -> None:
    """Spin `spin_time`, then until the graph was quiet for SETTLE_QUIET_S (the quiet only counts
    once another node is known: a participant's first announcement can take over a second)."""
    start = time.monotonic()
    while time.monotonic() - start < spin_time:
        rclpy.spin_once(node, timeout_sec=0.05)
    deadline = time.monotonic() + SETTLE_MAX_S
    last, quiet_since = _graph_signature(node), time.monotonic()
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
        now = _graph_signature(node)
        if now != last:
            last, quiet_since = now, time.monotonic()
        others = len(now[0]) > 1
        if others and time.monotonic() - quiet_since >= SETTLE_QUIET_S:
            return
        if not others and time.monotonic() - start >= spin_time + EMPTY_GRAPH_S:
            return


@contextmanager
def direct_node(args: argparse.Namespace | None = None, *, name: str | None = None,
                discover: bool = True) -> Iterator:
    """rclpy initialised, a hidden node in the default context, shut down on exit."""
    rclpy.init(args=[])
    spin_time = getattr(args, "spin_time", DEFAULT_SPIN_TIME)
    node = rclpy.create_node(
        name or f"{NODE_NAME_PREFIX}_{os.getpid()}", start_parameter_services=False,
        parameter_overrides=[Parameter("use_sim_time", value=bool(getattr(args, "use_sim_time", False)))],
        automatically_declare_parameters_from_overrides=True)
    try:
        if discover:
            _settle(node, spin_time)
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def spin_until_future(node, future, timeout: float | None = None):
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    if not future.done():
        return None
    return future.result()
