"""What reaches the policy node on its executor thread: the camera's model image (decoded,
cropped and resized by protocad_ros/robot/camera_input.py) and step_info (checked here), paired
with each other by header stamp (they may arrive in any order), and the sim bridge's
announcement (bridge_info), checked against what the node serves; an observation whose bridge
has not announced itself yet waits for it. A paired observation from a bridge that fits goes to
ActionPublishing (protocad_ros/node/action_publishing.py) unless it is a re-sent one (answered
again as before) or older than the last answered one. A part of PolicyNode: it works on the
node's per-episode state (`_unpaired`, `_last_stamp`, `_last_answer`, `_held_for_bridge_info`),
`bridge`, `mismatch` and counters (`_count`)."""
from __future__ import annotations

import time
from typing import Any

from sim_bridge.contract import topics

#: Observations whose image and step_info have not both arrived yet (oldest dropped beyond).
MAX_UNPAIRED = 64


class ObservationPairing:
    def _inactive(self) -> bool:
        """Observations are answered only while active (counted, not kept, otherwise)."""
        if self.is_active:
            return False
        self._count("observations_while_inactive")
        return True

    def _on_model_image(self, stamp: int, image, t: float) -> None:
        """A camera frame, already the model's image (protocad_ros/robot/camera_input.py)."""
        self._arrive(stamp, "image", image, t)

    def _on_info(self, msg) -> None:
        if self._inactive():
            return
        t = time.monotonic()
        stamp = topics.stamp_to_ns(msg.header.stamp)
        self._count("step_info_received")
        try:
            info = topics.read_step_info(msg)
        except (ValueError, TypeError, IndexError) as e:
            return self._count("step_info_rejected", f"step_info rejected (stamp {topics.format_stamp(stamp)}): {e}")
        self._arrive(stamp, "info", info, t)

    def _on_bridge_info(self, msg) -> None:
        """The bridge's announcement: refuse, with the reason, a bridge the checkpoint does not fit."""
        try:
            info = topics.read_bridge_info(msg)
        except ValueError as e:
            return self._count("bridge_info_rejected", f"bridge_info rejected: {e}")
        self.bridge = info
        if self.policy is not None:   # else configure checks it
            self._check_bridge()
        held, self._held_for_bridge_info = self._held_for_bridge_info, None
        if held is not None and self.mismatch is None and self.policy is not None and self.is_active:
            self._answer_paired(*held)

    def _check_bridge(self) -> None:
        info = self.bridge
        why = []
        if info.task != self.task:
            why.append(f"the checkpoint is for {self.task}, the bridge runs {info.task}")
        if len(info.action_names) != self.action_dim:
            why.append(f"the checkpoint acts with {self.action_dim} value(s) {self.action_names}, the "
                       f"bridge expects {len(info.action_names)} {info.action_names}")
        if (info.image_size, info.image_size) != tuple(self.image_hw):
            why.append(f"the checkpoint sees {self.image_hw[0]}x{self.image_hw[1]} images, the bridge "
                       f"renders {info.image_size}x{info.image_size}")
        self.mismatch = "; ".join(why) or None
        if self.mismatch:
            self.get_logger().error(f"not answering this sim bridge: {self.mismatch}. Start the bridge "
                                    f"with -p task:={self.task}, or serve a checkpoint trained on {info.task}")
        else:
            self.get_logger().info(f"sim bridge runs {info.task} with actions {info.action_names}: matches")

    def _announcing_bridge(self) -> bool:
        """Whether a bridge that announces itself is in the graph (a graph query, so asked at
        most once a second: a source without announcements, e.g. a robot driver, pays nothing
        per observation)."""
        now = time.monotonic()
        if now - self._announcer_checked_at >= 1.0:
            self._announcer_checked_at = now
            self._announcer_present = self.count_publishers(self.sub_bridge_info.topic_name) > 0
        return self._announcer_present

    def _arrive(self, stamp: int, kind: str, value: Any, t: float) -> None:
        entry = self._unpaired.get(stamp)
        if entry is None:
            entry = self._unpaired[stamp] = {}
            while len(self._unpaired) > MAX_UNPAIRED:
                old, _ = self._unpaired.popitem(last=False)
                self._count("unpaired_dropped", f"observation {old} never got both image and "
                            "step_info: dropped")
        entry[kind] = value
        if len(entry) < 2:
            return
        del self._unpaired[stamp]
        if self.mismatch is not None:
            return self._count("mismatched_observations", f"observation {topics.format_stamp(stamp)} not answered: {self.mismatch}")
        if self.bridge is None and self._announcing_bridge():
            # A bridge that announces itself is there but its announcement has not arrived yet:
            # answering now could send it actions of the wrong size. Hold the newest such
            # observation and answer it when the announcement comes (it usually follows within
            # milliseconds; a lock-step bridge would otherwise wait its timeout to re-send).
            self._held_for_bridge_info = (stamp, entry, t)
            return self._count("awaiting_bridge_info", f"observation {topics.format_stamp(stamp)} held: waiting "
                               "for the bridge's announcement")
        self._answer_paired(stamp, entry, t)

    def _answer_paired(self, stamp: int, entry: dict, t: float) -> None:
        """An observation with both image and step_info, from a bridge that fits: answer it."""
        if stamp == self._last_stamp and self._last_answer is not None:
            # The bridge published it again (its lock-step timeout): answer it again, same
            # action, without filtering it a second time.
            self._count("duplicate_observations")
            for pub, msg in zip((self.pub_action, self.pub_features), self._last_answer):
                pub.publish(msg)
            return
        if self._last_stamp is not None and stamp < self._last_stamp:
            if not entry["info"].is_first:
                return self._count("stale_observations", f"observation {topics.format_stamp(stamp)} is older than "
                                   f"the last answered one ({topics.format_stamp(self._last_stamp)}): not answered")
            # Sim time went back at an episode start: a new bridge run (its clock starts at 0
            # again), as in the collect-train-reload loop. Lone pieces of the old run could
            # pair with the new run's equal stamps, so they go.
            self._count("sim_time_restarts", f"sim time went back to {topics.format_stamp(stamp)} at an episode "
                        f"start (last answered {topics.format_stamp(self._last_stamp)}): a new sim run")
            self._unpaired.clear()
            self._last_stamp = self._last_answer = None
        self._answer(stamp, entry["image"], entry["info"], t)
