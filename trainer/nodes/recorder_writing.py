"""The recorder's writing (mixed into RecorderNode, trainer/nodes/recorder.py): each received
message into the bag (log time = reception time, never going back), the periodic flush, a write
error ending the recording (EXIT_WRITE_FAILED), and the close after SIGINT/SIGTERM: take what
the middleware still holds, close the bag with the loss in its metadata, print the summary."""
from __future__ import annotations

import threading
import time
from datetime import datetime
from typing import Any, Mapping

from trainer.bag.writer import BagWriteError, BagWriter

#: Longest drain at close (s): a KEEP_ALL backlog of 5000 samples on each of five topics takes a
#: few seconds to write; the processes that stop the recorder give it 20 s.
DRAIN_LIMIT_S = 10.0
#: Exit status when a write error (disk full, ...) ended the recording; the bag holds what was
#: written before it, closed validly where the disk allowed (see BagWriter.close).
EXIT_WRITE_FAILED = 3


def default_output() -> str:
    """rosbag2's default bag name: rosbag2_YYYY_MM_DD-HH_MM_SS."""
    return datetime.now().strftime("rosbag2_%Y_%m_%d-%H_%M_%S")


#: MCAP stores times as uint64 ns; log times stay below this (year 2262) to leave headroom.
_MAX_TIME_NS = 2 ** 63


class BagWriting:
    """Mixed into RecorderNode: it has budget, stop_reason, stall_watch, publisher_watch, _lock
    and _warn_once; _account (the loss) and _within_budget (the disk budget) see each message
    first; loss_summary, _loss_lines and publishers_summary go into the close; executor and
    context are rclpy's."""

    def _open_bag(self, p: Mapping[str, Any], custom_data: Mapping[str, str] | None) -> None:
        self.writer = BagWriter(
            p["output"], compression=p["compression"], chunk_size=p["chunk_size"],
            max_bagfile_size=p["max_bagfile_size"],
            max_bagfile_duration_s=p["max_bagfile_duration"],
            flush_interval_s=p["flush_interval"], custom_data=custom_data)
        self.received = 0
        self._last_log_time = 0   # ns; the newest log time written (see _on_message)
        self.errors = 0
        self.done = threading.Event()    # set when recording cannot go on (write failure)
        self.exit_code = 0

    def _on_message(self, topic: str, data: bytes, info: Any) -> None:
        """raw=True + two-argument callback: CDR bytes and the rmw message info."""
        if isinstance(info, dict):
            recv, src = info.get("received_timestamp"), info.get("source_timestamp")
            seq = info.get("publication_sequence_number") or 0
        else:
            recv = getattr(info, "received_timestamp", None)
            src = getattr(info, "source_timestamp", None)
            seq = getattr(info, "publication_sequence_number", 0) or 0
        # An MCAP time is an unsigned 64-bit count of ns: a time outside it (a forged or broken
        # message info) would fail the chunk's close and with it the whole bag's.
        if not isinstance(recv, int) or not 0 < recv < _MAX_TIME_NS:
            recv = time.time_ns()
        if not isinstance(src, int) or not 0 < src < _MAX_TIME_NS:
            src = None
        with self._lock:
            if self.writer.closed:
                return
            self._account(topic, int(seq) if isinstance(seq, int) else 0)
            if not self._within_budget(topic, len(data)):
                return
            # Reception times of different topics come from different DDS readers and can run
            # a little behind the order the callbacks write in. Log time never goes back in the
            # bag, so a file cut short (no index: a full disk, a kill) is still in time order
            # as written, which streaming readers such as rosbags require.
            recv = self._last_log_time = max(int(recv), self._last_log_time)
            try:
                self.writer.write(topic, data, recv, src if src else recv, sequence=seq)
                self.received += 1
            except Exception as exc:  # noqa: BLE001 - any write failure is counted and reported; _check_failure decides
                self.errors += 1
                self._warn_once(f"write:{type(exc).__name__}", f"write to bag failed: {exc}")
                self._check_failure()

    def _flush_if_due(self) -> None:
        with self._lock:
            try:
                self.writer.flush_if_due()
            except BagWriteError as exc:
                self._warn_once("flush", f"flushing the bag failed: {exc}")
                self._check_failure()

    def _check_failure(self) -> None:
        """A write error (disk full, file too large, permission lost, file removed) ends the
        recording: the bag is closed with what it holds and the recorder exits with
        EXIT_WRITE_FAILED."""
        if self.writer.failure is not None and not self.done.is_set():
            self.get_logger().error(f"recording stopped: {self.writer.failure}; closing the bag with the "
                                    f"{self.writer.message_count} messages written")
            self.exit_code = EXIT_WRITE_FAILED
            self.done.set()

    def _status(self) -> None:
        counts = ", ".join(f"{t}: {n}" for t, n in self.writer.topic_counts.items())
        self.get_logger().info(f"{self.writer.message_count} messages ({counts})")

    def drain(self, executor: Any, quiet_s: float = 0.3, limit_s: float = DRAIN_LIMIT_S) -> None:
        """Take what the middleware already holds before closing (used after SIGINT/SIGTERM):
        a KEEP_ALL reader may hold thousands of samples its writers already count as delivered
        (a backlog after a stall), which closing without taking them would lose."""
        deadline = time.monotonic() + limit_s
        last, quiet_since = self.received, time.monotonic()
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
            if self.received != last:
                last, quiet_since = self.received, time.monotonic()
            elif time.monotonic() - quiet_since >= quiet_s:
                break

    def close(self) -> dict[str, int]:
        """Take what the middleware still holds (when stopped by a signal, not by a write
        failure), close the bag (footer, summary, metadata.yaml with the loss), print the
        summary; returns the per-topic counts."""
        executor = self.executor
        if executor is not None and not self.done.is_set() and self.context.ok():
            self.drain(executor)
        self._stop_announcement_filter()   # held announcements: the bridge's written, others left out
        if self.stall_watch is not None:
            self.stall_watch.stop()
        with self._lock:
            marks = {**self.loss_summary(), **self.publishers_summary(), **self.budget.metadata()}
            if self.stop_reason:
                marks["protocad_recording_stopped"] = self.stop_reason
            if marks:
                self.writer.custom_data = {**(self.writer.custom_data or {}), **marks}
            self.writer.close()
        print(self.summary(), flush=True)
        return self.writer.topic_counts

    def summary(self) -> str:
        """What was recorded and what was lost, for the exit message."""
        w, counts = self.writer, self.writer.topic_counts
        lines = [f"recorder: recorded {sum(counts.values())} messages to {w.bag_dir} ({len(w.files)} file(s))"]
        lines += [f"  {t}: {n}" for t, n in counts.items()]
        if self.errors:
            lines.append(f"  write errors: {self.errors}")
        lines += self._loss_lines()
        if self.budget.dropped:
            lines.append("  DROPPED by the budget (message size / rate / byte rate / topic bytes / bag bytes): " + ", ".join(
                f"{t}: {sum(r.values())} ({', '.join(f'{k} {n}' for k, n in sorted(r.items()))})"
                for t, r in sorted(self.budget.dropped.items())))
        if self.budget.floods:
            lines.append("  FLOOD (marked in the metadata): " + ", ".join(
                f"{t}: {f['rate_hz']:g} msg/s against {f['recent_hz']:g}" for t, f in sorted(self.budget.floods.items())))
        if self.stop_reason:
            lines.append(f"  RECORDING STOPPED: {self.stop_reason}")
        if self.ignored_announcements:
            lines.append("  LEFT OUT (not written by the bridge; marked in the metadata): " + ", ".join(
                f"{t}: {n}" for t, n in sorted(self.ignored_announcements.items())))
        several = self.publisher_watch.ever
        if several:
            lines.append("  SEVERAL PUBLISHERS (marked in the metadata): " + ", ".join(
                f"{t}: {n}" for t, n in sorted(several.items())))
        if w.failure is not None:
            lines.append(f"  RECORDING STOPPED EARLY: {w.failure}")
            lines.append(f"  messages lost (received, not in the bag: the open chunk and everything after): "
                         f"{w.lost_after_failure}")
            lines += [f"  {note}" for note in w.salvage_notes]
            lines.append(f"  metadata.yaml: {'written' if (w.bag_dir / 'metadata.yaml').exists() else 'NOT written'}")
        return "\n".join(lines)
