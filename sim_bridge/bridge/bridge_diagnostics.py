"""What the sim bridge reports on /diagnostics (msgs_docs/sim_bridge.md#diagnostics).

BridgeDiagnostics (the node's `bridge_diagnostics`) owns the step-rate window, the late-action
count at its last report and which of the bridge's topics another node publishes too. It is
handed BridgeShared (sim_bridge/bridge/handover.py: the node, for its lifecycle state, error
counts, unknown parameters, clock, logger and the ROS graph; the parameters; the Handover's lock
and the counters), /diagnostics' publisher and the bridge's own publishers to watch, the type
watch, ActionIntake (its latency, `action_publishers` and its publisher watch's `summary`),
ObservationPublishing's `progress` and the stepping thread's control rate."""
from __future__ import annotations

import collections
import time
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.publisher import Publisher

from sim_bridge.bridge.action_intake import ActionIntake
from sim_bridge.bridge.handover import BridgeShared
from sim_bridge.nodekit.rosnode import make_status
from sim_bridge.nodekit.type_watch import TopicTypeWatch


class BridgeDiagnostics:
    """One DiagnosticStatus per call of `publish`; see the module docstring."""

    def __init__(self, shared: BridgeShared, *, pub_diag: Publisher, own_pubs: tuple[Publisher, ...],
                 type_watch: TopicTypeWatch, intake: ActionIntake, progress: Callable[[], tuple],
                 control_rate: Callable[[], float]):
        self.node, self.params, self.handover = shared.node, shared.params, shared.handover
        self.counters, self.lockstep = shared.counters, shared.lockstep
        self.pub_diag = pub_diag
        self.own_pubs = own_pubs   # image, step_info, context, bridge_info
        self.type_watch = type_watch
        # ActionIntake's figures: latency, who publishes actions, a second publisher's summary.
        self.latency = intake.latency
        self._action_publishers = intake.action_publishers
        self._multiple_publishers = intake.publisher_watch.summary
        self._progress = progress   # ObservationPublishing.progress
        self._control_rate = control_rate
        self.name = self.node.get_fully_qualified_name()   # -r __node:=... renames it too
        self._late_at_last_diag = 0
        self._rate_window: collections.deque[tuple[float, int]] = collections.deque(maxlen=2)
        self._rate_window.append((time.monotonic(), 0))
        self._others_warned: set[str] = set()
        self._others_now: set[str] = set()

    def publish(self) -> None:
        now = time.monotonic()
        others = self._other_publishers()   # first: it counts what it finds
        with self.handover.cond:
            c = dict(self.counters)
            t0, s0 = self._rate_window[0]
            self._rate_window.append((now, c["steps"]))
            episode, step, context, sim_time_s = self._progress()
        rate = (c["steps"] - s0) / (now - t0) if now > t0 else 0.0
        node, p = self.node, self.params
        state = node.lifecycle_state
        values: dict[str, Any] = {
            "task": p["task"], "split": p["split"],
            "seed": p["seed"], "mode": p["mode"],
            "steps_per_s": rate,
            "action_latency_ms_p50": self.latency.percentile(50) * 1e3,
            "action_latency_ms_p99": self.latency.percentile(99) * 1e3,
            "episode": episode, "step": step,
            "sim_time_s": sim_time_s,
            "action_publishers": self._action_publishers(),
            "callback_errors": node.callback_errors,
            "lifecycle_state": state, "transition_errors": node.transition_errors,
            **{f"context/{k}": v for k, v in context.items()},
            **c,
        }
        if not self.lockstep:
            values["control_rate_hz"] = self._control_rate()
        # Late actions are a rate, not a state: WARN only while new ones arrive (one late
        # action must not mark the rest of a run).
        late_now = c["late_actions"] - self._late_at_last_diag
        self._late_at_last_diag = c["late_actions"]
        warn = c["actions_rejected"] or c["lockstep_timeouts"] or late_now or node.callback_errors
        unknown = node.unknown_parameters
        values["other_publishers"] = ", ".join(others)
        several = self._multiple_publishers()   # on the topics it subscribes to (action)
        values["multiple_publishers"] = several
        values["first_action_publisher_only"] = p["first_action_publisher_only"]
        values.update(self.type_watch.diagnostics())
        claimed = values["type_mismatches"]
        status = make_status(self.name, p["task"], values,
                             "ERROR" if others or claimed else "WARN" if warn or unknown or several else "OK",
                             f"offered with another type than the contract's: {claimed}" if claimed else
                             f"another publisher on {', '.join(others)} (a second bridge in this "
                             "namespace?)" if others else
                             f"several publishers on {several} (an impostor?)" if several else
                             f"unknown parameters ignored: {unknown}" if unknown else
                             "rejected/late actions or timeouts" if warn else
                             "running" if state == "active" else f"{state}: not stepping")
        arr = DiagnosticArray()
        arr.header.stamp = node.get_clock().now().to_msg()
        arr.status = [status]
        try:
            self.pub_diag.publish(arr)
        except Exception:  # noqa: BLE001 - context shutting down
            pass

    def _other_publishers(self) -> list[str]:
        """The bridge's own topics that some other node publishes too: two bridges in one
        namespace (or a stray publisher) interleave observations and /clock, so both say so."""
        others = []
        for pub in self.own_pubs:
            topic = pub.topic_name
            if self.node.count_publishers(topic) > 1:
                others.append(topic)
        new = set(others) - self._others_now
        self._others_now = set(others)
        if new:   # each time a topic gains another publisher (a second bridge starts)
            with self.handover.cond:
                self.counters["multiple_publishers_detected"] += len(new)
        for topic in others:
            if topic not in self._others_warned:
                self._others_warned.add(topic)
                self.node.get_logger().error(f"another node also publishes {topic} (a second sim bridge in "
                                             f"{self.node.get_namespace()}?): its observations interleave with "
                                             "ours; run each bridge in its own namespace and domain")
        return others
