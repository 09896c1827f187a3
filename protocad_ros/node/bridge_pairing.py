"""Which `bridge_info` the policy node believes (a part of PolicyNode, as observation_pairing.py
is): only one written by the participant that also writes the observations it reads (image and
step_info in its namespace), that is its bridge. A stranger who publishes one bridge_info naming
another task would otherwise make the node refuse its real bridge ("not answering ...") and a
launcher end the run (issue 54).

rclpy's message info has no writer GID, so the announcement is taken a second time through
sim_bridge.nodekit.sender_gid.SenderSubscription, with the GID of its writer; its first 12 bytes
(the DDS participant's GUID prefix) must be those of a writer of both image and step_info in the
graph. An announcement whose writer is not such a participant (yet: its endpoints may be
discovered a moment later) waits up to BRIDGE_INFO_GRACE_S, then is ignored, counted
(`bridge_info_ignored`) and logged once per writer.

It works on the node's `_on_bridge_info` (observation_pairing.py), `_count` and its logger.
"""
from __future__ import annotations

import time

from sensor_msgs.msg import JointState

from sim_bridge.contract import qos, topics
from sim_bridge.nodekit.sender_gid import PARTICIPANT_BYTES, TAKE_PERIOD_S, SenderSubscription

#: Seconds an announcement may wait for its writer's observation topics to show in the graph.
BRIDGE_INFO_GRACE_S = 5.0


class BridgePairing:
    def _start_bridge_pairing(self) -> None:
        self._announcements = SenderSubscription(self, JointState, self.resolve_topic_name(topics.BRIDGE_INFO),
                                                 qos.announcement_qos())
        self._waiting_announcements: dict[tuple, tuple[object, float]] = {}   # participant -> (msg, since)
        self._ignored_announcers: set[tuple] = set()
        self._announcement_timer = self.create_timer(TAKE_PERIOD_S, self._take_announcements)

    def _on_bridge_info_heard(self, _msg) -> None:
        """The plain subscription's callback: an announcement arrived; it is believed only as
        taken with its writer."""
        self._take_announcements()

    def _observation_writers(self) -> set[tuple]:
        """The participants that write both image and step_info where this node reads them (the
        image where its camera reads it: `image/compressed` with compressed transport)."""
        found = [{tuple(e.endpoint_gid)[:PARTICIPANT_BYTES] for e in self.get_publishers_info_by_topic(t)}
                 for t in (self.camera.topic, self.resolve_topic_name(topics.STEP_INFO))]
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
                self._on_bridge_info(msg)
            elif now - since >= BRIDGE_INFO_GRACE_S:
                del self._waiting_announcements[who]
                first = who not in self._ignored_announcers
                self._ignored_announcers.add(who)
                self._count("bridge_info_ignored", None if not first else (
                    f"ignored a bridge_info (task {msg.header.frame_id!r}) from a writer that publishes no "
                    f"image and step_info here (participant {bytes(who).hex()}): not this node's bridge"))

    def _stop_bridge_pairing(self) -> None:
        self._announcements.destroy()
