"""`ObservationPairing`: what reaches the policy node on its executor thread, paired into
observations. The camera's model image (decoded, cropped and resized by
protocad_ros/robot/camera_input.py) and step_info (checked here) are paired with each other by
header stamp (they may arrive in any order). An observation whose bridge has not announced
itself yet waits for it (BridgePairing, bridge_pairing.py); one from a bridge that does not fit
the served model is not answered. A paired observation goes to ActionPublishing
(action_publishing.py) unless it is a re-sent one (answered again as before) or older than the
last answered one. A part of the policy node (protocad_ros/node/policy_node.py).

It owns the step_info subscription and the pairing state of an episode: the halves waiting for
their other half (`_unpaired`), the last answered stamp and its answer, and the observation
held for the bridge's announcement. It is handed the node (its subscriptions), the parameter
dict, the node's `count(key, why, n)`, the publisher watch's `event_callbacks`, the step_info
QoS profile, the action and context_features publishers (a re-sent observation is answered
again with the same messages), and callables: `is_active()` (the node's lifecycle),
`answer(stamp, image, info, t, first)` (ActionPublishing's), `mismatch()` and `unannounced()`
(BridgePairing's).
"""
from __future__ import annotations

import collections
import time
from typing import Any, Callable

from sensor_msgs.msg import JointState

from sim_bridge.contract import topics

#: Observations whose image and step_info have not both arrived yet (oldest dropped beyond).
MAX_UNPAIRED = 64


class ObservationPairing:
    """Image and step_info paired by stamp, answered once each; see the module docstring."""

    def __init__(self, *, node: Any, params: dict[str, Any], count: Callable[..., None], event_callbacks: Callable,
                 qos_profile: Any, publishers: tuple[Any, Any], is_active: Callable[[], bool],
                 answer: Callable[..., tuple[Any, Any]], mismatch: Callable[[], str | None],
                 unannounced: Callable[[], bool]):
        self._count, self._publishers, self._is_active = count, publishers, is_active
        self._answer, self._mismatch, self._unannounced = answer, mismatch, unannounced
        self.subscription = None if params["observations"] == "image_only" else node.create_subscription(
            JointState, topics.STEP_INFO, self._on_info, qos_profile,
            event_callbacks=event_callbacks(node.resolve_topic_name(topics.STEP_INFO)))
        self.reset()

    def reset(self) -> None:
        """A new filter run (configure, cleanup): nothing waits, nothing was answered."""
        self._unpaired: collections.OrderedDict[int, dict[str, Any]] = collections.OrderedDict()
        self._last_stamp: int | None = None
        self._last_answer: tuple[Any, Any] | None = None
        # (stamp, image + step_info, receive time) held until bridge_info arrives (_arrive)
        self._held_for_bridge_info: tuple | None = None

    def deactivate(self) -> None:
        """Halves of observations that arrived before: they will not be answered."""
        self._unpaired.clear()

    def accepting(self) -> bool:
        """Observations are answered only while active (counted, not kept, otherwise)."""
        if self._is_active():
            return True
        self._count("observations_while_inactive")
        return False

    def on_model_image(self, stamp: int, image, t: float) -> None:
        """A camera frame, already the model's image (protocad_ros/robot/camera_input.py)."""
        self._arrive(stamp, "image", image, t)

    def _on_info(self, msg) -> None:
        if not self.accepting():
            return
        t = time.monotonic()
        stamp = topics.stamp_to_ns(msg.header.stamp)
        self._count("step_info_received")
        try:
            info = topics.read_step_info(msg)
        except (ValueError, TypeError, IndexError) as e:
            return self._count("step_info_rejected", f"step_info rejected (stamp {topics.format_stamp(stamp)}): {e}")
        self._arrive(stamp, "info", info, t)

    def bridge_believed(self) -> None:
        """The bridge's announcement was believed: the observation held for it is answered if
        the bridge fits and the node is active (which it is only with a model configured)."""
        held, self._held_for_bridge_info = self._held_for_bridge_info, None
        if held is not None and self._mismatch() is None and self._is_active():
            self.answer_paired(*held)

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
        mismatch = self._mismatch()
        if mismatch is not None:
            return self._count("mismatched_observations", f"observation {topics.format_stamp(stamp)} not answered: {mismatch}")
        if self._unannounced():
            # A bridge that announces itself is there but its announcement has not arrived yet:
            # answering now could send it actions of the wrong size. Hold the newest such
            # observation and answer it when the announcement comes (it usually follows within
            # milliseconds; a lock-step bridge would otherwise wait its timeout to re-send).
            self._held_for_bridge_info = (stamp, entry, t)
            return self._count("awaiting_bridge_info", f"observation {topics.format_stamp(stamp)} held: waiting "
                               "for the bridge's announcement")
        self.answer_paired(stamp, entry, t)

    def answer_paired(self, stamp: int, entry: dict, t: float) -> None:
        """An observation with both image and step_info, from a bridge that fits: answer it."""
        if stamp == self._last_stamp and self._last_answer is not None:
            # The bridge published it again (its lock-step timeout): answer it again, same
            # action, without filtering it a second time.
            self._count("duplicate_observations")
            for pub, msg in zip(self._publishers, self._last_answer):
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
        self._last_answer = self._answer(stamp, entry["image"], entry["info"], t, self._last_stamp is None)
        self._last_stamp = stamp
        stale = [s for s in self._unpaired if s < stamp]   # pieces that can no longer pair
        for s in stale:
            del self._unpaired[s]
        if stale:
            self._count("fragments_discarded", None, len(stale))
