"""`BridgePairing`: which `bridge_info` the policy node believes, and whether the bridge it
names fits the served model. A part of the policy node (protocad_ros/node/policy_node.py).

An announcement is believed only when written by the participant that also writes the
observations the node reads (image and step_info in its namespace), that is its bridge. A
stranger who publishes one bridge_info naming another task would otherwise make the node refuse
its real bridge ("not answering ...") and a launcher end the run (issue 54).

rclpy's message info has no writer GID, so the announcement is taken a second time through
sim_bridge.nodekit.sender_gid.SenderSubscription, with the GID of its writer; its first 12 bytes
(the DDS participant's GUID prefix) must be those of a writer of both image and step_info in the
graph. An announcement whose writer is not such a participant (yet: its endpoints may be
discovered a moment later) waits up to BRIDGE_INFO_GRACE_S, then is ignored, counted
(`bridge_info_ignored`) and logged once per writer. A believed announcement is checked against
the served model (task, action size, image size): a bridge that does not fit is refused with the
reason (`mismatch`), and its observations are not answered.

It owns the bridge_info subscriptions and timer, the announcements waiting for their writer, the
believed announcement (`bridge`) and `mismatch`. It is handed the node (graph queries, logger,
subscriptions), the node's `count(key, why)`, the publisher watch's `event_callbacks`, the topic
the camera reads (`image_topic`), and callables: `facts()` (the served ModelFacts), `loaded()`
(a model is configured) and `believed()` (an announcement was believed: ObservationPairing's
observation held for it may go).
"""
from __future__ import annotations

import time
from typing import Any, Callable

from sensor_msgs.msg import JointState

from protocad_ros.node.checkpoint_serving import ModelFacts
from sim_bridge.contract import qos, topics
from sim_bridge.nodekit.sender_gid import PARTICIPANT_BYTES, TAKE_PERIOD_S, SenderSubscription

#: Seconds an announcement may wait for its writer's observation topics to show in the graph.
BRIDGE_INFO_GRACE_S = 5.0


class BridgePairing:
    """The sim bridge's announcement, believed from its writer and checked; see the module docstring."""

    def __init__(self, *, node: Any, count: Callable[..., None], event_callbacks: Callable, image_topic: str,
                 facts: Callable[[], ModelFacts], loaded: Callable[[], bool], believed: Callable[[], None]):
        self._node, self._log, self._count = node, node.get_logger(), count
        self._facts, self._loaded, self._believed = facts, loaded, believed
        topic = node.resolve_topic_name(topics.BRIDGE_INFO)
        self._observation_topics = (image_topic, node.resolve_topic_name(topics.STEP_INFO))
        self.bridge: topics.BridgeInfo | None = None
        self.mismatch: str | None = None
        self._announcer_checked_at, self._announcer_present = -1e9, False
        self.subscription = node.create_subscription(JointState, topics.BRIDGE_INFO, self._on_heard,
                                                     qos.announcement_qos(), event_callbacks=event_callbacks(topic))
        self._announcements = SenderSubscription(node, JointState, topic, qos.announcement_qos())
        self._waiting_announcements: dict[tuple, tuple[object, float]] = {}   # participant -> (msg, since)
        self._ignored_announcers: set[tuple] = set()
        self._announcement_timer = node.create_timer(TAKE_PERIOD_S, self._take_announcements)

    def _on_heard(self, _msg) -> None:
        """The plain subscription's callback: an announcement arrived; it is believed only as
        taken with its writer."""
        self._take_announcements()

    def _observation_writers(self) -> set[tuple]:
        """The participants that write both image and step_info where this node reads them (the
        image where its camera reads it: `image/compressed` with compressed transport)."""
        found = [{tuple(e.endpoint_gid)[:PARTICIPANT_BYTES] for e in self._node.get_publishers_info_by_topic(t)}
                 for t in self._observation_topics]
        return found[0] & found[1]

    def _take_announcements(self) -> None:
        now = time.monotonic()
        for msg, gid in self._announcements.take():
            who = gid[:PARTICIPANT_BYTES]
            self._waiting_announcements[who] = (msg, self._waiting_announcements.get(who, (None, now))[1])
        if not self._waiting_announcements:
            return
        bridges = self._observation_writers()
        for who, (msg, since) in list(self._waiting_announcements.items()):
            if who in bridges:
                del self._waiting_announcements[who]
                self._on_believed(msg)
            elif now - since >= BRIDGE_INFO_GRACE_S:
                del self._waiting_announcements[who]
                first = who not in self._ignored_announcers
                self._ignored_announcers.add(who)
                self._count("bridge_info_ignored", None if not first else (
                    f"ignored a bridge_info (task {msg.header.frame_id!r}) from a writer that publishes no "
                    f"image and step_info here (participant {bytes(who).hex()}): not this node's bridge"))

    def _on_believed(self, msg) -> None:
        """The bridge's announcement: refuse, with the reason, a bridge the checkpoint does not fit."""
        try:
            info = topics.read_bridge_info(msg)
        except ValueError as e:
            return self._count("bridge_info_rejected", f"bridge_info rejected: {e}")
        self.bridge = info
        if self._loaded():   # else configure checks it
            self.check()
        self._believed()

    def check(self) -> None:
        """The believed bridge against the served model: `mismatch` says why it does not fit."""
        info, facts = self.bridge, self._facts()
        why = []
        if info.task != facts.task:
            why.append(f"the checkpoint is for {facts.task}, the bridge runs {info.task}")
        if len(info.action_names) != facts.action_dim:
            why.append(f"the checkpoint acts with {facts.action_dim} value(s) {facts.action_names}, the "
                       f"bridge expects {len(info.action_names)} {info.action_names}")
        if (info.image_size, info.image_size) != tuple(facts.image_hw):
            why.append(f"the checkpoint sees {facts.image_hw[0]}x{facts.image_hw[1]} images, the bridge "
                       f"renders {info.image_size}x{info.image_size}")
        self.mismatch = "; ".join(why) or None
        if self.mismatch:
            self._log.error(f"not answering this sim bridge: {self.mismatch}. Start the bridge "
                            f"with -p task:={facts.task}, or serve a checkpoint trained on {info.task}")
        else:
            self._log.info(f"sim bridge runs {info.task} with actions {info.action_names}: matches")

    def configured(self) -> None:
        """A model was configured: a bridge announced before is checked against it now."""
        if self.bridge is not None:
            self.check()

    def release(self) -> None:
        """No model: nothing to mismatch (the bridge's announcement is kept)."""
        self.mismatch = None

    def unannounced(self) -> bool:
        """A bridge that announces itself is in the graph, but its announcement has not been
        believed yet (a graph query, so asked at most once a second: a source without
        announcements, e.g. a robot driver, pays nothing per observation)."""
        if self.bridge is not None:
            return False
        now = time.monotonic()
        if now - self._announcer_checked_at >= 1.0:
            self._announcer_checked_at = now
            self._announcer_present = self._node.count_publishers(self.subscription.topic_name) > 0
        return self._announcer_present

    def stop(self) -> None:
        """Closing: the taking subscription goes."""
        self._announcements.destroy()
