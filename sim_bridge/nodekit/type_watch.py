"""Contract topics claimed with another type (issue 54, point 4; msgs_docs/security.md).

DDS matches a reader and a writer only when their types agree, so a stranger who advertises a
contract topic with another type (`/protocad/action` as `std_msgs/msg/String`) never reaches a
node, and nothing says why: a bridge waiting for its policy's actions waits on. `TopicTypeWatch`
makes it a clear error. Once a period (TYPE_CHECK_PERIOD_S, on a node timer; the graph is a
local cache, so a check costs no traffic) it compares the types the ROS graph shows for each
contract topic the node subscribes to or publishes (its own endpoints, whatever they are, so
each node declares nothing) with the contract's type (sim_bridge.contract.topics.TYPES); a topic
offered with any other type is:

- one ERROR line per topic, naming the topic, the types seen and the contract's;
- on /diagnostics while it lasts: `type_mismatches` (the topics and their other types; the
  node's level is ERROR while it is not empty) and `type_mismatches_detected` (times a topic
  was found offered with another type);
- nothing more: the node goes on (its own endpoints still match every endpoint of the right
  type), and the report clears when the stranger leaves.
"""
from __future__ import annotations

import threading
from typing import Any

from sim_bridge.contract import topics

#: Seconds between two looks at the graph.
TYPE_CHECK_PERIOD_S = 1.0


class TopicTypeWatch:
    """The contract topics a node joins that the graph shows with another type (see the module
    docstring). `check()` runs on the node's timer; the rest is read by its diagnostics."""

    def __init__(self, node: Any, period_s: float = TYPE_CHECK_PERIOD_S):
        self._node = node
        self._lock = threading.Lock()
        self._now: dict[str, tuple[str, ...]] = {}   # topic -> the other types it is offered with
        self._logged: set[str] = set()
        self.detected = 0                             # times a topic went from right to wrong
        self.timer = node.create_timer(period_s, self.check)

    def joined(self) -> dict[str, str]:
        """{topic: contract type} for the contract topics of the node's own endpoints."""
        ns = self._node.get_namespace()
        out = {}
        for endpoint in (*self._node.publishers, *self._node.subscriptions):
            expected = topics.contract_topic_type(endpoint.topic_name, ns)
            if expected is not None:
                out[endpoint.topic_name] = expected
        return out

    def check(self) -> None:
        joined = self.joined()
        now = {}
        for topic, types in self._node.get_topic_names_and_types():
            expected = joined.get(topic)
            if expected is not None and set(types) - {expected}:
                now[topic] = tuple(sorted(set(types) - {expected}))
        with self._lock:
            new = [t for t in now if t not in self._now]
            self._now = now
            self.detected += len(new)
            first = [t for t in new if t not in self._logged]
            self._logged.update(first)
        for topic in first:
            seen = ", ".join(sorted({*now[topic], joined[topic]}))
            self._node.get_logger().error(
                f"{topic} is offered as {seen}, but its contract type is {joined[topic]}: another "
                f"participant claimed the topic as {', '.join(now[topic])}, and those endpoints never "
                "match this node's (type_mismatches on /diagnostics)")

    def summary(self) -> str:
        """'/ns/action (std_msgs/msg/String)' while a topic is offered with another type, else ''."""
        with self._lock:
            return ", ".join(f"{t} ({', '.join(types)})" for t, types in sorted(self._now.items()))

    def diagnostics(self) -> dict[str, Any]:
        """The node's /diagnostics keys (the level is ERROR while `type_mismatches` is not empty)."""
        with self._lock:
            detected = self.detected
        return {"type_mismatches": self.summary(), "type_mismatches_detected": detected}
