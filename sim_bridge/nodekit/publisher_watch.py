"""Impostor detection for the contract topics (msgs_docs/topics.md#one-publisher-per-topic).

Every contract topic has one writer per namespace: the bridge's observations and announcement,
the policy's actions. A second one (a stray `ros2 topic pub`, a second bridge, an impostor)
interleaves its samples with the real ones, so the nodes say so:

- `PublisherWatch` follows the matched-publisher count of subscriptions (the DDS matched event:
  no polling, a publisher that comes and goes between two diagnostics periods is seen too),
  warns once per topic and counts every time a topic gains a second publisher.
- `FirstPublisherLock` lets a node take samples from the first publisher only. rclpy (Jazzy,
  7.1) gives no publisher id with a message (rmw has one, rclpy's MessageInfo lacks it:
  ros2/rclpy#1465), so the lock tells writers apart by their publication sequence numbers:
  a reliable KEEP_ALL writer (the contract's action profile) numbers its samples 1, 2, 3, ...
  and a reliable reader gets every one, in order, so the first publisher's next sample is
  always `last + 1`; anything else comes from another writer. A writer whose numbers happen
  to continue the first one's is taken for it: this is detection, not authentication (ROS 2
  security, SROS2, is what authenticates writers).

The lock is plain arithmetic (its tests make no node); the watch is handed to a subscription.
"""
from __future__ import annotations

import threading
from typing import Any, Callable

from rclpy.event_handler import SubscriptionEventCallbacks


class PublisherWatch:
    """Subscribed topics with more than one matched publisher, from matched events."""

    def __init__(self, on_new: Callable[[str, int, bool], None]):
        # on_new(topic, publishers, first_time): each time a topic gains a second publisher
        # (first_time: never before on this topic, the time to warn), outside the lock.
        self._on_new = on_new
        self._lock = threading.Lock()
        self._now: dict[str, int] = {}         # topic -> matched publishers, while more than one
        self._max: dict[str, int] = {}         # topic -> most publishers seen at once (> 1)
        self._warned: set[str] = set()
        self.detected = 0                      # times a topic went from <= 1 to > 1 publishers

    def callbacks(self, topic: str, also: Callable[[Any], None] | None = None):
        """SubscriptionEventCallbacks for a subscription to `topic` (`also` gets the event too)."""
        def matched(info: Any) -> None:
            try:
                self.update(topic, int(info.current_count))
            finally:
                if also is not None:
                    also(info)

        return SubscriptionEventCallbacks(matched=matched)

    def update(self, topic: str, publishers: int) -> bool:
        """Record the topic's current publisher count; True when it just gained a second one."""
        with self._lock:
            rising = publishers > 1 and topic not in self._now
            if publishers > 1:
                self._now[topic] = publishers
                self._max[topic] = max(publishers, self._max.get(topic, 0))
            else:
                self._now.pop(topic, None)
            first = rising and topic not in self._warned
            if rising:
                self.detected += 1
                self._warned.add(topic)
        if rising:
            self._on_new(topic, publishers, first)
        return rising

    @property
    def now(self) -> dict[str, int]:
        """Topics with several publishers at present."""
        with self._lock:
            return dict(self._now)

    @property
    def ever(self) -> dict[str, int]:
        """Every topic that had several publishers at some point: the most seen at once."""
        with self._lock:
            return dict(self._max)

    def summary(self) -> str:
        """'/ns/action (2)' for diagnostics; empty while every topic has one publisher or none."""
        return ", ".join(f"{t} ({n})" for t, n in sorted(self.now.items()))


class FirstPublisherLock:
    """Takes samples from one writer only: the first that sent while it was the only one
    matched, identified by its consecutive sequence numbers (see the module docstring).
    `release()` when no publisher is matched any more: the next one to send alone takes the
    lock (a restarted policy). Not thread-safe: call it under the node's lock."""

    def __init__(self) -> None:
        self.last: int | None = None           # the locked writer's newest sequence number

    def release(self) -> None:
        self.last = None

    def admit(self, seq: int, matched: int) -> str | None:
        """None when the sample (publication sequence number `seq`, `matched` publishers now)
        comes from the locked writer (taking the lock if it is free), else why not."""
        if seq <= 0:
            # An rmw without sequence numbers: nothing to tell writers apart by.
            return None if matched <= 1 else "no sequence number to tell the publishers apart"
        if self.last is None:
            if matched > 1:
                return (f"{matched} action publishers were matched before any action arrived: "
                        "which one was first cannot be told")
            self.last = seq
            return None
        if seq == self.last + 1:
            self.last = seq
            return None
        return (f"its sequence number {seq} does not continue the first publisher's ({self.last}): "
                "another publisher")
