"""RecorderLoss, the recorder's loss accounting (a part of RecorderNode, trainer/nodes/recorder.py):
what the middleware dropped before the recorder took it, counted from each writer's publication
sequence numbers, and stalls of the recorder's own process past its DDS lease (StallWatch). Both
go into the bag's metadata (metadata()) and the exit summary (summary_lines()).

It owns the counts (lost, missed_before_subscribing, untracked, stalls) and its StallWatch; it is
handed the node (its logger, count_publishers), the node's lock (the stall thread appends under
it) and the node's warn_once and throttled warning."""
from __future__ import annotations

import json
import threading
import time
from typing import Any, Callable

#: The DDS lease the recorder's participant announces (s): how long its writers keep it matched,
#: and keep what it has not acknowledged, while it does not run (sim_bridge/nodekit/
#: fastdds_profile.py). Fast DDS's 20 s default lost the whole backlog of a longer stall.
DEFAULT_LEASE_S = 120.0


class StallWatch:
    """Notices when this process did not run for longer than its DDS lease (SIGSTOP, Ctrl-Z, a
    debugger, a swap storm, a machine too loaded to schedule it): its writers may then have
    dropped the recorder with every sample it had not acknowledged, a loss that shows as a
    sequence gap only if a later sample reaches it. A thread, not a node timer: a busy
    executor is no stall (DDS's own threads keep announcing the participant); a process that
    does not run at all stops this thread too."""

    def __init__(self, lease_s: float, on_stall: Callable[[float], None], interval_s: float = 0.5):
        self.lease_s = lease_s
        self._on_stall, self._interval = on_stall, interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="stall-watch", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        last = time.monotonic()   # CLOCK_MONOTONIC runs on while the process is stopped
        while not self._stop.wait(self._interval):
            now = time.monotonic()
            if now - last > self.lease_s:
                self._on_stall(now - last)
            last = now

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


class RecorderLoss:
    """What was lost before the recorder took it: sequence gaps per topic, stalls past the lease."""

    def __init__(self, *, node: Any, lock: threading.Lock, warn_once: Callable[[str, str], None],
                 warn_throttled: Callable[[str, str], None]):
        self._node, self._lock = node, lock
        self._warn_once, self._warn_throttled = warn_once, warn_throttled
        # Loss accounting from each writer's publication sequence numbers (1, 2, 3, ... per
        # publisher): a jump is messages the middleware dropped before we took them (a stalled
        # recorder, a KEEP_LAST writer overwriting what it held); a first number above 1 is what
        # was published before we subscribed. Exact for a topic with one publisher; a topic with
        # several is not tracked (their numbers interleave), and says so.
        self.lost: dict[str, int] = {}
        self.missed_before_subscribing: dict[str, int] = {}
        self.untracked: set[str] = set()
        self._last_seq: dict[str, int] = {}
        # Stalls longer than the participant's lease (watch_stalls): seconds each.
        self.stalls: list[float] = []
        self.stall_lease_s = 0.0
        self.stall_watch: StallWatch | None = None

    def account(self, topic: str, seq: int) -> None:
        """A message of `topic` with publication sequence number `seq` (0: unknown) arrived."""
        if seq <= 0 or topic in self.untracked:
            return
        last = self._last_seq.get(topic)
        if last is None or seq <= last:
            if last is not None or self._node.count_publishers(topic) > 1:
                # several writers (or one restarted): their numbers say nothing about loss
                self.untracked.add(topic)
                self._warn_once(f"untracked:{topic}", f"{topic} has several publishers: its losses "
                                "cannot be counted from sequence numbers")
                return
            if seq > 1:
                self.missed_before_subscribing[topic] = seq - 1
                self._node.get_logger().warning(f"{topic}: {seq - 1} message(s) were published before the "
                                                "recorder subscribed (start the recorder first)")
        elif seq > last + 1:
            n = seq - last - 1
            self.lost[topic] = self.lost.get(topic, 0) + n
            self._warn_throttled(f"lost:{topic}", f"{topic}: {n} message(s) lost before the recorder took "
                                 f"them (sequence {last} -> {seq}; {self.lost[topic]} on this topic so far)")
        self._last_seq[topic] = seq

    def watch_stalls(self, lease_s: float) -> None:
        """Report every stall of this process longer than `lease_s`, its participant's lease."""
        self.stall_lease_s = lease_s   # before the thread starts: it may report at once
        self.stall_watch = StallWatch(lease_s, self._on_stall)

    def _on_stall(self, seconds: float) -> None:
        with self._lock:
            self.stalls.append(round(seconds, 1))
        self._node.get_logger().warning(
            f"the recorder did not run for {seconds:.1f} s, longer than its DDS lease "
            f"({self.stall_lease_s:g} s): writers may have dropped it with what it had not "
            "taken; that loss is counted only where a later sample shows the gap")

    def stop(self) -> None:
        """Stop watching for stalls (at close)."""
        if self.stall_watch is not None:
            self.stall_watch.stop()

    def metadata(self) -> dict[str, str]:
        """The loss as metadata.yaml custom_data (rosbag2 keeps str -> str)."""
        out = {}
        if self.stalls:
            out["protocad_stalls_past_lease"] = json.dumps(
                {"lease_s": self.stall_lease_s, "stalls_s": self.stalls})
        if self.lost:
            out["protocad_lost_messages"] = json.dumps(self.lost, sort_keys=True)
        if self.missed_before_subscribing:
            out["protocad_missed_before_subscribing"] = json.dumps(self.missed_before_subscribing, sort_keys=True)
        if self.untracked:
            out["protocad_loss_untracked_topics"] = json.dumps(sorted(self.untracked))
        return out

    def summary_lines(self) -> list[str]:
        """The loss, for the exit summary."""
        lines = []
        if self.lost:
            lines.append(f"  LOST before the recorder took them (sequence gaps): {sum(self.lost.values())} "
                         f"({', '.join(f'{t}: {n}' for t, n in sorted(self.lost.items()))})")
        if self.missed_before_subscribing:
            lines.append("  published before the recorder subscribed: " + ", ".join(
                f"{t}: {n}" for t, n in sorted(self.missed_before_subscribing.items())))
        if self.untracked:
            lines.append(f"  loss not tracked (several publishers): {', '.join(sorted(self.untracked))}")
        if self.stalls:
            lines.append(f"  STALLED past the DDS lease ({self.stall_lease_s:g} s): "
                         f"{', '.join(f'{x:g} s' for x in self.stalls)}; samples sent meanwhile may be "
                         "lost, counted above only where a later sample showed the gap")
        return lines
