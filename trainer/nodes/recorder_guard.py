"""The recorder's side of its disk budget (trainer/nodes/record_budget.py holds the budget
itself, without ROS): what RecorderNode does with each message's verdict (drop it, end the
recording with a closed bag, flag a flood on /diagnostics) and the command-line options."""
from __future__ import annotations

import argparse
import time

from sim_bridge.nodekit.rosnode import make_status
from trainer.nodes.record_budget import (
    DEFAULT_FLOOD_FACTOR,
    DEFAULT_MIN_FREE_DISK,
    DIAGNOSTICS_BYTE_BUDGET,
    DIAGNOSTICS_MESSAGE_BYTES,
    DIAGNOSTICS_RATE_LIMIT_HZ,
    IMAGE_BYTES_PER_S,
    IMAGE_MESSAGE_BYTES,
    STEP_TOPIC_RATE_HZ,
)

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


def add_budget_options(ap: argparse.ArgumentParser) -> None:
    """The disk budget's options of `ros2 run trainer record` (each also a ROS parameter)."""
    g = ap.add_argument_group("the disk budget (a flood from any participant must not fill the disk)")
    g.add_argument("--max-topic-rate", type=float, default=0.0, metavar="HZ",
                   help="record at most this many messages per second of each topic (2 s of burst); "
                        "the rest are dropped and counted (0: no limit beyond the contract topics' "
                        "defaults; default 0)")
    g.add_argument("--rate-limit", dest="rate_limits", nargs="+", default=[], metavar="TOPIC=HZ",
                   help="a rate limit for one topic, over --max-topic-rate and its default (contract topics: "
                        f"{STEP_TOPIC_RATE_HZ:g} msg/s, /diagnostics {DIAGNOSTICS_RATE_LIMIT_HZ:g}); 0 turns it "
                        "off (with a WARNING)")
    g.add_argument("--max-topic-bytes", type=int, default=0, metavar="BYTES",
                   help="stop recording a topic once it has this many bytes in the bag (counted; "
                        "0: no limit; default 0)")
    g.add_argument("--byte-budget", dest="byte_budgets", nargs="+", default=[], metavar="TOPIC=BYTES",
                   help="a byte budget for one topic, over --max-topic-bytes and its default "
                        f"(/diagnostics {DIAGNOSTICS_BYTE_BUDGET}); 0 turns it off (with a WARNING)")
    g.add_argument("--byte-rate-limit", dest="byte_rate_limits", nargs="+", default=[], metavar="TOPIC=BYTES_PER_S",
                   help="a byte-rate limit for one topic, over its default (image "
                        f"{IMAGE_BYTES_PER_S}, the other contract topics less); 0 turns it off (with a WARNING)")
    g.add_argument("--max-message-bytes", dest="message_limits", nargs="+", default=[], metavar="TOPIC=BYTES",
                   help="the largest message recorded on one topic, over its default (image "
                        f"{IMAGE_MESSAGE_BYTES}, /diagnostics {DIAGNOSTICS_MESSAGE_BYTES}, ...); larger ones "
                        "are dropped and counted; 0 turns it off (with a WARNING)")
    g.add_argument("--max-total-bytes", type=int, default=0, metavar="BYTES",
                   help="end the recording (closed, valid bag; exit 4) once the bag holds this many "
                        "message bytes (0: no limit; default 0)")
    g.add_argument("--min-free-disk", type=int, default=DEFAULT_MIN_FREE_DISK, metavar="BYTES",
                   help="end the recording (closed, valid bag; exit 4) when the disk under the bag "
                        f"has less free space than this (0: off; default {DEFAULT_MIN_FREE_DISK})")
    g.add_argument("--flood-factor", type=float, default=DEFAULT_FLOOD_FACTOR, metavar="X",
                   help="flag a topic whose rate or byte rate over a second is X times its recent "
                        "figure (and at least 100 msg/s or 10 MB/s), or above what its bounds let through "
                        "(unbounded: 5000 msg/s or 64 MiB/s), in the bag's metadata "
                        f"(protocad_floods) and on /diagnostics (0: off; default {DEFAULT_FLOOD_FACTOR:g})")
