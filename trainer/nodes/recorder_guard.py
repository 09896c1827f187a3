"""RecorderGuard, the recorder's side of its disk budget (a part of RecorderNode; trainer/nodes/
record_budget.py holds the budget itself, without ROS): what the recorder does with each
message's verdict (drop it, end the recording with a closed bag, flag a flood on /diagnostics);
its options are parameters (recorder_params.py).

It owns the RecordBudget (built before the bag by budget_from_params, so a bad value leaves no
bag behind), the DiskFloor beside the bag and the flood timer; it is handed the node (its logger,
clock, name and timers), the writer, the /diagnostics publisher it flags floods on, the node's
`done` event and stop(exit_code, reason) (the end of the recording), and the node's warn_once and
throttled warning."""
from __future__ import annotations

import threading
import time
from typing import Any, Callable, Mapping

from sim_bridge.nodekit.rosnode import make_status
from trainer.bag.writer import BagWriter
from trainer.nodes.record_budget import BudgetLimits, DiskFloor, RecordBudget, parse_topic_values

#: Exit status when the bag's byte budget or the free-disk floor ended the recording (the bag
#: is closed and valid).
EXIT_BUDGET = 4


def budget_from_params(p: Mapping[str, Any], resolve: Callable[[str], str]) -> RecordBudget:
    """The budget the parameters ask for; the per-topic lists (TOPIC=NUMBER) have their topics
    resolved by `resolve` (the node's resolve_topic_name). ValueError for a bad entry."""
    def per_topic(key: str) -> dict[str, float]:
        return {resolve(t): v for t, v in parse_topic_values(p[key], key).items()}

    return RecordBudget(BudgetLimits(
        max_topic_rate=p["max_topic_rate"], max_topic_bytes=p["max_topic_bytes"],
        max_total_bytes=p["max_total_bytes"], flood_factor=p["flood_factor"],
        rates=per_topic("rate_limits"), topic_bytes=per_topic("byte_budgets"),
        byte_rates=per_topic("byte_rate_limits"), message_bytes=per_topic("message_limits"),
        namespace=p["namespace"]))


class RecorderGuard:
    """Each message's verdict from the budget and the free-disk floor, and what follows from it."""

    def __init__(self, *, node: Any, budget: RecordBudget, writer: BagWriter, min_free_disk: int,
                 diag_pub: Any, done: threading.Event, stop: Callable[[int, str | None], None],
                 warn_once: Callable[[str, str], None], warn_throttled: Callable[[str, str], None]):
        self._node, self.budget, self._writer, self._diag_pub = node, budget, writer, diag_pub
        self._done, self._stop = done, stop
        self._warn_once, self._warn_throttled = warn_once, warn_throttled
        self.disk_floor = DiskFloor(writer.bag_dir, min_free_disk)
        self._flood_timer = None

    def within_budget(self, topic: str, nbytes: int) -> bool:
        """The disk budget (record_budget.py): False drops the message (counted); the bag's
        budget or the free-disk floor end the recording (a closed, valid bag; one line)."""
        now = time.monotonic()
        reason = self.budget.admit(topic, nbytes, now)
        for flooded in self.budget.take_new_floods():
            self._flag_flood(flooded)
        if reason == "total_bytes":
            self._stop_recording(self.budget.stopped or "the bag's byte budget is spent")
            return False
        if reason is not None:
            self._warn_throttled(f"budget:{topic}:{reason}", f"{topic}: messages dropped ({reason} limit; "
                                 f"{self.budget.dropped[topic][reason]} so far)")
            return False
        below = self.disk_floor.below(nbytes, now)
        if below is not None:
            self._stop_recording(below)
            return False
        return True

    def _stop_recording(self, reason: str) -> None:
        if self._done.is_set():
            return
        self._node.get_logger().error(f"recording stopped: {reason}; closing the bag with the "
                                      f"{self._writer.message_count} messages written")
        self._stop(EXIT_BUDGET, reason)

    def _flag_flood(self, topic: str) -> None:
        """A flood: in the bag's metadata at once, a WARNING, and a WARN on /diagnostics, sent
        again every second (the flood may be on /diagnostics itself, and push one status out of
        a reader's history)."""
        figures = self.budget.floods[topic]
        self._writer.custom_data = {**(self._writer.custom_data or {}), **self.budget.metadata()}
        self._node.get_logger().warning(
            f"{topic}: FLOOD: {figures['rate_hz']:g} msg/s ({figures['bytes_per_s']} B/s) against "
            f"{figures['recent_hz']:g} msg/s recently; flagged in the bag's metadata")
        self._publish_floods()
        if self._flood_timer is None:
            self._flood_timer = self._node.create_timer(1.0, self._publish_floods)

    def _publish_floods(self) -> None:
        try:
            from diagnostic_msgs.msg import DiagnosticArray

            arr = DiagnosticArray()
            arr.header.stamp = self._node.get_clock().now().to_msg()
            arr.status = [make_status(f"{self._node.get_name()}: recording {topic}", "recorder",
                                      {"flooded_topic": topic, **figures}, "WARN", f"flood on {topic}")
                          for topic, figures in sorted(dict(self.budget.floods).items())]
            self._diag_pub.publish(arr)
        except Exception as exc:  # noqa: BLE001 - the flag in the bag stands; the status is extra
            self._warn_once("flood-diag", f"cannot publish the flood on /diagnostics: {exc}")

    def metadata(self) -> dict[str, str]:
        """The budget's marks (drops, floods, a stop) as metadata.yaml custom_data."""
        return self.budget.metadata()

    def summary_lines(self) -> list[str]:
        """What the budget dropped and the floods, for the exit summary."""
        lines = []
        if self.budget.dropped:
            lines.append("  DROPPED by the budget (message size / rate / byte rate / topic bytes / bag bytes): " + ", ".join(
                f"{t}: {sum(r.values())} ({', '.join(f'{k} {n}' for k, n in sorted(r.items()))})"
                for t, r in sorted(self.budget.dropped.items())))
        if self.budget.floods:
            lines.append("  FLOOD (marked in the metadata): " + ", ".join(
                f"{t}: {f['rate_hz']:g} msg/s against {f['recent_hz']:g}" for t, f in sorted(self.budget.floods.items())))
        return lines
