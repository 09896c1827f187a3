"""What the sim bridge reports on /diagnostics (msgs_docs/sim_bridge.md#diagnostics): a mixin
of SimBridgeNode, reading its counters and state under its condition variable."""
from __future__ import annotations

import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray

from sim_bridge.nodekit.rosnode import make_status


class BridgeDiagnostics:
    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        others = self._other_publishers()   # first: it counts what it finds
        with self._cond:
            c = dict(self.counters)
            t0, s0 = self._rate_window[0]
            self._rate_window.append((now, c["steps"]))
            episode, step, context = self._episode, self._step, dict(self._obs_context)
            tick = self._tick
        rate = (c["steps"] - s0) / (now - t0) if now > t0 else 0.0
        state = self.lifecycle_state
        values: dict[str, Any] = {
            "task": self.params["task"], "split": self.params["split"],
            "seed": self.params["seed"], "mode": self.params["mode"],
            "steps_per_s": rate,
            "action_latency_ms_p50": self.latency.percentile(50) * 1e3,
            "action_latency_ms_p99": self.latency.percentile(99) * 1e3,
            "episode": episode, "step": step,
            "sim_time_s": max(tick, 0) * self.dt_ns / 1e9,
            "action_publishers": self.sub_action.get_publisher_count(),
            "callback_errors": self.callback_errors,
            "lifecycle_state": state, "transition_errors": self.transition_errors,
            **{f"context/{k}": v for k, v in context.items()},
            **c,
        }
        if not self.lockstep:
            values["control_rate_hz"] = self._control_rate
        # Late actions are a rate, not a state: WARN only while new ones arrive (one late
        # action must not mark the rest of a run).
        late_now = c["late_actions"] - self._late_at_last_diag
        self._late_at_last_diag = c["late_actions"]
        warn = c["actions_rejected"] or c["lockstep_timeouts"] or late_now or self.callback_errors
        unknown = self.unknown_parameters
        values["other_publishers"] = ", ".join(others)
        several = self.publisher_watch.summary()   # on the topics it subscribes to (action)
        values["multiple_publishers"] = several
        values["first_action_publisher_only"] = self.params["first_action_publisher_only"]
        values.update(self.type_watch.diagnostics())
        claimed = values["type_mismatches"]
        status = make_status(self._diag_name, self.params["task"], values,
                             "ERROR" if others or claimed else "WARN" if warn or unknown or several else "OK",
                             f"offered with another type than the contract's: {claimed}" if claimed else
                             f"another publisher on {', '.join(others)} (a second bridge in this "
                             "namespace?)" if others else
                             f"several publishers on {several} (an impostor?)" if several else
                             f"unknown parameters ignored: {unknown}" if unknown else
                             "rejected/late actions or timeouts" if warn else
                             "running" if state == "active" else f"{state}: not stepping")
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [status]
        try:
            self.pub_diag.publish(arr)
        except Exception:  # noqa: BLE001 - context shutting down
            pass

    def _other_publishers(self) -> list[str]:
        """The bridge's own topics that some other node publishes too: two bridges in one
        namespace (or a stray publisher) interleave observations and /clock, so both say so."""
        others = []
        for pub in (self.pub_image, self.pub_info, self.pub_context, self.pub_bridge_info):
            topic = pub.topic_name
            if self.count_publishers(topic) > 1:
                others.append(topic)
        new = set(others) - self._others_now
        self._others_now = set(others)
        if new:   # each time a topic gains another publisher (a second bridge starts)
            with self._cond:
                self.counters["multiple_publishers_detected"] += len(new)
        for topic in others:
            if topic not in self._others_warned:
                self._others_warned.add(topic)
                self.get_logger().error(f"another node also publishes {topic} (a second sim bridge in "
                                        f"{self.get_namespace()}?): its observations interleave with "
                                        "ours; run each bridge in its own namespace and domain")
        return others
