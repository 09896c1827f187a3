"""The recorder's side of its disk budget (trainer/nodes/record_budget.py holds the budget
itself, without ROS): what RecorderNode does with each message's verdict (drop it, end the
recording with a closed bag, flag a flood on /diagnostics); its options are parameters (recorder_params.py)."""
from __future__ import annotations

import time

from sim_bridge.nodekit.rosnode import make_status

#: Exit status when the bag's byte budget or the free-disk floor ended the recording (the bag
#: is closed and valid).
EXIT_BUDGET = 4


class RecorderGuard:
    """Mixed into RecorderNode: it has budget (RecordBudget), disk_floor (DiskFloor), writer,
    done, exit_code, stop_reason, _diag_pub, _flood_timer, _throttle and _warn_once."""

    def _within_budget(self, topic: str, nbytes: int) -> bool:
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
            self._throttle.warning(f"budget:{topic}:{reason}", f"{topic}: messages dropped ({reason} limit; "
                                   f"{self.budget.dropped[topic][reason]} so far)")
            return False
        below = self.disk_floor.below(nbytes, now)
        if below is not None:
            self._stop_recording(below)
            return False
        return True

    def _stop_recording(self, reason: str) -> None:
        if self.done.is_set():
            return
        self.stop_reason = reason
        self.get_logger().error(f"recording stopped: {reason}; closing the bag with the "
                                f"{self.writer.message_count} messages written")
        self.exit_code = EXIT_BUDGET
        self.done.set()

    def _flag_flood(self, topic: str) -> None:
        """A flood: in the bag's metadata at once, a WARNING, and a WARN on /diagnostics, sent
        again every second (the flood may be on /diagnostics itself, and push one status out of
        a reader's history)."""
        figures = self.budget.floods[topic]
        self.writer.custom_data = {**(self.writer.custom_data or {}), **self.budget.metadata()}
        self.get_logger().warning(
            f"{topic}: FLOOD: {figures['rate_hz']:g} msg/s ({figures['bytes_per_s']} B/s) against "
            f"{figures['recent_hz']:g} msg/s recently; flagged in the bag's metadata")
        self._publish_floods()
        if self._flood_timer is None:
            self._flood_timer = self.create_timer(1.0, self._publish_floods)

    def _publish_floods(self) -> None:
        try:
            from diagnostic_msgs.msg import DiagnosticArray

            arr = DiagnosticArray()
            arr.header.stamp = self.get_clock().now().to_msg()
            arr.status = [make_status(f"{self.get_name()}: recording {topic}", "recorder",
                                      {"flooded_topic": topic, **figures}, "WARN", f"flood on {topic}")
                          for topic, figures in sorted(dict(self.budget.floods).items())]
            self._diag_pub.publish(arr)
        except Exception as exc:  # noqa: BLE001 - the flag in the bag stands; the status is extra
            self._warn_once("flood-diag", f"cannot publish the flood on /diagnostics: {exc}")
