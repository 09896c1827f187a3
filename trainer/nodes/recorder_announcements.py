"""RecorderAnnouncements: the bridge's announcement in the bag only from the bridge (a part of
RecorderNode, trainer/nodes/recorder.py). A stranger's `bridge_info` naming another task would otherwise sit in the
bag beside the bridge's, and a reader of the bag could take it for what the bridge ran (issue 54).

rclpy's message info has no writer GID, so a contract `bridge_info` topic is read a second time
through sim_bridge.nodekit.sender_gid.SenderSubscription (raw: the bytes go to the bag
untouched), and a message is recorded only when its writer's participant (the first 12 bytes of
its GID) also writes image and step_info in the same namespace: that namespace's bridge. The
plain subscription stays (it wakes the take and keeps the several-publishers mark); what it
delivers is not written. A message from another writer waits up to ANNOUNCEMENT_GRACE_S for its
writer's endpoints to show in the graph, then is left out, counted (the summary and
custom_data.protocad_ignored_bridge_info) and logged once per writer.

It owns the second subscriptions, the messages held for their writer to show, the count of
those left out (ignored) and its take timer; it is handed the node (its timers, graph queries
and the SenderSubscriptions' node), the writer (the count goes into its custom_data), the node's
lock and warn_once, and on_message (RecorderWriting's: a bridge's message goes into the bag).
RecorderTopics calls filter() for each contract bridge_info topic it subscribes to."""
from __future__ import annotations

import json
import threading
import time
from typing import Any, Callable

from sim_bridge.contract import topics as T
from sim_bridge.nodekit.sender_gid import PARTICIPANT_BYTES, TAKE_PERIOD_S, SenderSubscription
from trainer.bag.writer import BagWriter

#: Seconds a message may wait for its writer's observation topics to show in the graph.
ANNOUNCEMENT_GRACE_S = 5.0
#: custom_data key: {topic: messages left out}.
IGNORED_KEY = "protocad_ignored_bridge_info"


class RecorderAnnouncements:
    """Writes a contract bridge_info message into the bag only when its namespace's bridge wrote it."""

    def __init__(self, *, node: Any, writer: BagWriter, lock: threading.Lock,
                 on_message: Callable[[str, bytes, Any], None], warn_once: Callable[[str, str], None]):
        self._node, self._writer, self._lock = node, writer, lock
        self._on_message, self._warn_once = on_message, warn_once
        self._senders: dict[str, SenderSubscription] = {}
        self._held: dict[str, list[tuple[bytes, tuple, dict, float]]] = {}
        #: {topic: messages left out}.
        self.ignored: dict[str, int] = {}
        self._announcement_timer = None

    def filter(self, topic: str, msg_class: Any, qos: Any) -> None:
        """Record `topic` (a contract bridge_info) from its namespace's bridge only."""
        self._senders[topic] = SenderSubscription(self._node, msg_class, topic, qos)
        if self._announcement_timer is None:
            self._announcement_timer = self._node.create_timer(TAKE_PERIOD_S, self._take_announcements)

    def heard(self, topic: str, _data: bytes, _info: Any) -> None:
        """The plain subscription's callback: its message is taken, with its writer, here."""
        self._take_announcements()

    def _bridges(self, topic: str) -> set[tuple]:
        """Participants that write both image and step_info beside `topic`."""
        ns = topic.rpartition("/")[0] or "/"
        found = [{tuple(e.endpoint_gid)[:PARTICIPANT_BYTES]
                  for e in self._node.get_publishers_info_by_topic(T.topic_name(ns, name))}
                 for name in (T.IMAGE, T.STEP_INFO)]
        return found[0] & found[1]

    def _take_announcements(self, final: bool = False) -> None:
        now = time.monotonic()
        for topic, sender in self._senders.items():
            held = self._held.setdefault(topic, [])
            held += [(data, gid, info, now) for data, gid, info in sender.take_raw()]
            if not held:
                continue
            bridges, keep = self._bridges(topic), []
            for data, gid, info, since in held:
                who = gid[:PARTICIPANT_BYTES]
                if who in bridges:
                    self._on_message(topic, data, info)
                elif final or now - since >= ANNOUNCEMENT_GRACE_S:
                    self._ignore_announcement(topic, who)
                else:
                    keep.append((data, gid, info, since))
            self._held[topic] = keep

    def _ignore_announcement(self, topic: str, who: tuple) -> None:
        with self._lock:
            self.ignored[topic] = self.ignored.get(topic, 0) + 1
            self._writer.custom_data = {**(self._writer.custom_data or {}),
                                        IGNORED_KEY: json.dumps(self.ignored, sort_keys=True)}
        self._warn_once(f"announcement:{topic}:{bytes(who).hex()}",
                        f"{topic}: left a message out of the bag: its writer (participant "
                        f"{bytes(who).hex()}) writes no image and step_info beside it, not the bridge")

    def stop(self) -> None:
        """At close: held messages are decided (the bridge's written, others left out) and the
        second subscriptions go."""
        if self._senders:
            self._take_announcements(final=True)
        for sender in self._senders.values():
            sender.destroy()
        self._senders = {}

    def summary_lines(self) -> list[str]:
        """What was left out, for the exit summary."""
        if not self.ignored:
            return []
        return ["  LEFT OUT (not written by the bridge; marked in the metadata): " + ", ".join(
            f"{t}: {n}" for t, n in sorted(self.ignored.items()))]
