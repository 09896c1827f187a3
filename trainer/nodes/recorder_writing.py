"""RecorderWriting, the recorder's writing (a part of RecorderNode, trainer/nodes/recorder.py):
each received message into the bag (log time = reception time, never going back), the periodic
flush and status line, a write error ending the recording (EXIT_WRITE_FAILED), and the close
after SIGINT/SIGTERM: take what the middleware still holds, close the bag with the marks in its
metadata. open_bag makes the BagWriter the node holds (the other parts add to it too).

It owns the counts of what it received and what failed, and the flush and status timers; it is
handed the node (its logger, timers, executor and context), the parameters, the writer, the
node's lock and `done` event, stop(exit_code, reason) (a write error ends the recording),
warn_once, and RecorderLoss' account and RecorderGuard's within_budget, which see each message
first."""
from __future__ import annotations

import threading
import time
from datetime import datetime
from typing import Any, Callable, Mapping

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


def open_bag(p: Mapping[str, Any], custom_data: Mapping[str, str] | None) -> BagWriter:
    """The bag the parameters ask for (BagWriteError: the directory exists; ValueError: a bad
    option)."""
    return BagWriter(
        p["output"], compression=p["compression"], chunk_size=p["chunk_size"],
        max_bagfile_size=p["max_bagfile_size"],
        max_bagfile_duration_s=p["max_bagfile_duration"],
        flush_interval_s=p["flush_interval"], custom_data=custom_data)


class RecorderWriting:
    """Each received message into the bag, the flush, and the bag's close (see the module docstring)."""

    def __init__(self, *, node: Any, params: Mapping[str, Any], writer: BagWriter, lock: threading.Lock,
                 done: threading.Event, stop: Callable[[int, str | None], None],
                 warn_once: Callable[[str, str], None], account: Callable[[str, int], None],
                 within_budget: Callable[[str, int], bool]):
        self._node, self._params, self._writer, self._lock, self._done = node, params, writer, lock, done
        self._stop, self._warn_once, self._account, self._within_budget = stop, warn_once, account, within_budget
        self.received = 0
        self._last_log_time = 0   # ns; the newest log time written (see on_message)
        self.errors = 0
        self._flush_timer = self._status_timer = None

    def start(self) -> None:
        """The flush and status timers the parameters ask for (0: none)."""
        if self._params["flush_interval"] > 0:
            self._flush_timer = self._node.create_timer(self._params["flush_interval"], self._flush_if_due)
        if self._params["status_interval"] > 0:
            self._status_timer = self._node.create_timer(self._params["status_interval"], self._status)

    def on_message(self, topic: str, data: bytes, info: Any) -> None:
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
            if self._writer.closed:
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
                self._writer.write(topic, data, recv, src if src else recv, sequence=seq)
                self.received += 1
            except Exception as exc:  # noqa: BLE001 - any write failure is counted and reported; _check_failure decides
                self.errors += 1
                self._warn_once(f"write:{type(exc).__name__}", f"write to bag failed: {exc}")
                self._check_failure()

    def _flush_if_due(self) -> None:
        with self._lock:
            try:
                self._writer.flush_if_due()
            except BagWriteError as exc:
                self._warn_once("flush", f"flushing the bag failed: {exc}")
                self._check_failure()

    def _check_failure(self) -> None:
        """A write error (disk full, file too large, permission lost, file removed) ends the
        recording: the bag is closed with what it holds and the recorder exits with
        EXIT_WRITE_FAILED."""
        if self._writer.failure is not None and not self._done.is_set():
            self._node.get_logger().error(f"recording stopped: {self._writer.failure}; closing the bag with the "
                                          f"{self._writer.message_count} messages written")
            self._stop(EXIT_WRITE_FAILED, None)

    def _status(self) -> None:
        counts = ", ".join(f"{t}: {n}" for t, n in self._writer.topic_counts.items())
        self._node.get_logger().info(f"{self._writer.message_count} messages ({counts})")

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

    def drain_held(self) -> None:
        """At close, unless the recording ended by itself (the bag is full, or failed): take
        what the middleware still holds (see drain)."""
        executor = self._node.executor
        if executor is not None and not self._done.is_set() and self._node.context.ok():
            self.drain(executor)

    def close(self, marks: Callable[[], dict[str, str]]) -> None:
        """Close the bag (footer, summary, metadata.yaml) with `marks()` (the other parts'
        custom_data: the loss, several publishers, the budget, a stop) added to its metadata."""
        with self._lock:
            added = marks()
            if added:
                self._writer.custom_data = {**(self._writer.custom_data or {}), **added}
            self._writer.close()

    def recorded_lines(self) -> list[str]:
        """What was recorded, for the exit summary's head."""
        w, counts = self._writer, self._writer.topic_counts
        lines = [f"recorder: recorded {sum(counts.values())} messages to {w.bag_dir} ({len(w.files)} file(s))"]
        lines += [f"  {t}: {n}" for t, n in counts.items()]
        if self.errors:
            lines.append(f"  write errors: {self.errors}")
        return lines

    def failure_lines(self) -> list[str]:
        """How a write error ended the recording, for the exit summary's tail."""
        w = self._writer
        if w.failure is None:
            return []
        return [f"  RECORDING STOPPED EARLY: {w.failure}",
                f"  messages lost (received, not in the bag: the open chunk and everything after): "
                f"{w.lost_after_failure}",
                *(f"  {note}" for note in w.salvage_notes),
                f"  metadata.yaml: {'written' if (w.bag_dir / 'metadata.yaml').exists() else 'NOT written'}"]
