"""What reaches the sim bridge on its executor thread: actions (checked, attributed to their
publisher, matched to the observation that awaits them, clipped) and the reset service. A part of
SimBridgeNode, as BridgeDiagnostics is: it works on the node's state under the node's condition
variable, which hands accepted actions to the stepping thread (sim_bridge/bridge/stepping.py)."""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from sim_bridge.bridge.commands import CommandRejected
from sim_bridge.bridge.params import ACTION_HIGH, ACTION_LOW
from sim_bridge.contract import topics


class ActionIntake:
    def _on_action_matched(self, info) -> None:
        with self._cond:   # wake the stepping thread (it re-checks _policy_present)
            if self._action_lock is not None and info.current_count == 0:
                self._action_lock.release()   # nobody left: the next publisher alone takes it
            self._cond.notify_all()

    def _on_new_publisher(self, topic: str, publishers: int, first_time: bool) -> None:
        with self._cond:
            self.counters["multiple_publishers_detected"] += 1
        if first_time:
            what = ("only the first one's actions are taken" if self._action_lock is not None
                    else "every one's actions are taken (first_action_publisher_only:=true takes "
                         "the first one's only)")
            self.get_logger().warning(
                f"{publishers} publishers on {topic}: another node publishes actions to this bridge "
                f"(an impostor, a second policy, a stray `ros2 topic pub`?); {what}")

    def _policy_present(self) -> bool:
        return self.sub_action.get_publisher_count() > 0

    def _other_publisher(self, info: Any) -> str | None:
        """Why the action comes from another publisher than the first (first_action_publisher_only),
        or None. Called under _cond."""
        if self._action_lock is None:
            return None
        seq = info.get("publication_sequence_number", 0) if isinstance(info, dict) else \
            getattr(info, "publication_sequence_number", 0)
        return self._action_lock.admit(int(seq or 0), self.sub_action.get_publisher_count())

    def _reject(self, counter: str, why: str) -> None:
        self.counters["actions_rejected"] += 1
        self.counters[counter] += 1
        self._throttle.warning(
            counter, f"action rejected ({counter}, {self.counters[counter]} so far): {why}")

    def _on_action(self, msg, info=None) -> None:
        now = time.monotonic()
        stamp = topics.stamp_to_ns(msg.header.stamp)
        with self._cond:
            # Attribution first: the locked publisher's every sample advances its numbers.
            other = self._other_publisher(info)
            if not self._go:   # not active: no observation awaits an answer (dropped, counted)
                self.counters["actions_while_inactive"] += 1
                return
            self.counters["actions_received"] += 1
            if other is not None:
                return self._reject("rejected_other_publisher", f"stamp {topics.format_stamp(stamp)}: {other}")
            try:
                a = topics.read_action(msg)
            except (ValueError, TypeError) as e:
                return self._reject("rejected_malformed", f"{e} (stamp {topics.format_stamp(stamp)})")
            if a.shape != (self.action_dim,):
                return self._reject("rejected_wrong_length",
                                    f"{a.size} values, expected {self.action_dim} "
                                    f"{self.action_names} (stamp {topics.format_stamp(stamp)})")
            if not np.all(np.isfinite(a)):
                return self._reject("rejected_nonfinite", f"{a.tolist()} (stamp {topics.format_stamp(stamp)})")
            if self.lockstep:
                if stamp != self._pending_stamp:
                    if stamp in self._answered_stamps:
                        return self._reject("rejected_duplicate",
                                            f"stamp {topics.format_stamp(stamp)} was already answered")
                    return self._reject("rejected_stale_stamp",
                                        f"stamp {topics.format_stamp(stamp)} is not the observation awaiting an "
                                        f"answer ({topics.format_stamp(self._pending_stamp)})" if self._pending_stamp is not None
                                        else f"stamp {topics.format_stamp(stamp)} arrived while no observation awaits an answer")
            else:
                if stamp not in self._published:
                    return self._reject("rejected_stale_stamp",
                                        f"stamp {topics.format_stamp(stamp)} answers no recent observation")
                if stamp in self._answered_stamps:
                    return self._reject("rejected_duplicate",
                                        f"stamp {topics.format_stamp(stamp)} was already answered")
            clipped = self._accept(a, stamp, now)
            if self.lockstep:
                self._hand_to_stepping(clipped)
            else:
                if stamp != self._newest_stamp:
                    self.counters["late_actions"] += 1
                    self._throttle.warning(
                        "late_actions", f"late action for stamp {topics.format_stamp(stamp)} (newest observation "
                        f"{topics.format_stamp(self._newest_stamp)}; {self.counters['late_actions']} late so far)")
                if stamp > self._held_stamp:
                    self._held, self._held_stamp = clipped, stamp

    def _accept(self, a: np.ndarray, stamp: int, now: float) -> np.ndarray:
        """A valid answer to `stamp`, clipped and counted. Called under _cond."""
        clipped = np.clip(a, ACTION_LOW, ACTION_HIGH)
        if np.any(clipped != a):
            self.counters["actions_clipped"] += 1
            self._throttle.warning(
                "actions_clipped", f"action {a.tolist()} clipped to [{ACTION_LOW}, "
                f"{ACTION_HIGH}] ({self.counters['actions_clipped']} so far)")
        self.counters["actions_accepted"] += 1
        first = stamp not in self._answered_stamps
        self._answered_stamps.append(stamp)
        sent = self._published.get(stamp)
        if sent is not None and first:
            self.latency.add(now - sent)
        return clipped

    def _on_command(self, msg, info=None) -> None:
        """Adapter mode: a Float64MultiArray carries no stamp, so in lock-step the first command
        after an observation answers it (one arriving with none awaiting an answer is counted
        in commands_unsolicited and dropped); in real time the latest command is applied."""
        now = time.monotonic()
        with self._cond:
            other = self._other_publisher(info)
            if not self._go:
                self.counters["actions_while_inactive"] += 1
                return
            self.counters["actions_received"] += 1
            if other is not None:
                return self._reject("rejected_other_publisher", other)
            try:
                a = self.commands.action(msg.data)
            except CommandRejected as e:
                return self._reject(e.counter, str(e))
            stamp = self._pending_stamp if self.lockstep else self._newest_stamp
            if stamp is None:
                self.counters["commands_unsolicited"] += 1
                self._throttle.warning(
                    "commands_unsolicited", f"a command arrived while no observation awaits an answer: "
                    f"dropped ({self.counters['commands_unsolicited']} so far)")
                return
            clipped = self._accept(a, stamp, now)
            if self.lockstep:
                self._hand_to_stepping(clipped)
            else:
                self._held, self._held_stamp = clipped, stamp

    def _hand_to_stepping(self, action) -> None:
        """Lock-step: the action answers the pending observation; the stepping thread goes on."""
        self._answer = action
        self._pending_stamp = None
        self._cond.notify_all()

    def _on_reset(self, request, response):
        with self._cond:
            self.counters["resets_requested"] += 1
            if not self._go:
                response.success = False
                response.message = f"not active (lifecycle state {self.lifecycle_state})"
                return response
            if not self._started:
                response.success = False
                response.message = "no episode running yet (waiting for subscribers)"
                return response
            served = self._reset_served
            self._reset_requested = True
            self._cond.notify_all()
            ok = self._cond.wait_for(lambda: (self._reset_served > served or self._stop.is_set()
                                              or self.done.is_set()), timeout=10.0)
            response.success = bool(ok and self._reset_served > served)
            response.message = self._reset_note if response.success else "reset not served"
        return response
