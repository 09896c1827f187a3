"""What reaches the sim bridge on its executor thread: actions (checked, attributed to their
publisher, matched to the observation that awaits them, clipped) and the reset service.

ActionIntake (the node's `action_intake`) creates and owns the action subscription (or, in
adapter mode, the command subscription and its CommandAdapter, loaded at configure), the
publisher watch and first-publisher lock on it, and the reset service; it owns which stamps were
answered and the action latency (observation published -> answer received). It is handed
BridgeShared (sim_bridge/bridge/handover.py: the node, to create those and for its logger and
lifecycle state; the parameters; the Handover through which accepted actions and reset requests
reach the stepping thread; the counters, the log throttle, the mode) and the node's `done` event
(a reset request stops waiting once the node is done)."""
from __future__ import annotations

import collections
import threading
import time
from typing import Any

import numpy as np
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from sim_bridge.bridge.command_adapter import CommandAdapter, CommandRejected
from sim_bridge.bridge.handover import BridgeShared
from sim_bridge.bridge.params import ACTION_HIGH, ACTION_LOW
from sim_bridge.contract import qos, topics
from sim_bridge.contract.contexts import task_actuators
from sim_bridge.nodekit.publisher_watch import FirstPublisherLock, PublisherWatch
from sim_bridge.nodekit.rosnode import Percentiles


class ActionIntake:
    """Actions and the reset service; see the module docstring."""

    def __init__(self, shared: BridgeShared, *, done: threading.Event):
        node, params = self.node, self.params = shared.node, shared.params
        self.handover, self.counters, self.throttle = shared.handover, shared.counters, shared.throttle
        self.lockstep = shared.lockstep
        self.done = done
        self.latency = Percentiles()   # observation published -> answer received
        self.command_adapter: CommandAdapter | None = None   # adapter mode, from configure
        self.new_run(0, [])
        # A second action publisher (an impostor, a stray `ros2 topic pub`) is reported; with
        # first_action_publisher_only its actions are refused too.
        self.publisher_watch = PublisherWatch(self._on_new_publisher)
        self._action_lock = FirstPublisherLock() if params["first_action_publisher_only"] else None
        self.sub_action = self._subscribe_actions(params)
        self.srv_reset = (node.create_service(Trigger, topics.RESET_SERVICE, self._on_reset)
                          if params["reset_service"] else None)

    def _subscribe_actions(self, p: dict[str, Any]):
        """Actions on `action`, or in adapter mode a robot's commands instead (never both)."""
        adapter = p["action_input"] == "float64_multi_array"
        action_type, action_topic, on_action = ((Float64MultiArray, p["command_topic"], self._on_command)
                                                if adapter else (JointState, topics.ACTION, self._on_action))
        return self.node.create_subscription(
            action_type, action_topic,
            # first_action_publisher_only: rclpy passes the message info (its sequence number)
            # to a two-argument callback.
            on_action if self._action_lock is None else (lambda msg, info: on_action(msg, info)),
            qos.action_qos(), qos_overriding_options=qos.overridable(),
            event_callbacks=self.publisher_watch.callbacks(self.node.resolve_topic_name(action_topic),
                                                           also=self._on_action_matched))

    # ------------------------------------------------------------------ the node's calls
    def configure(self) -> None:
        """Adapter mode: load the command map (a bad map is a ConfigError before anything starts)."""
        p = self.params
        if p["action_input"] == "float64_multi_array":
            self.command_adapter = CommandAdapter.load(p["command_map"], task_actuators(p["task"]))

    def new_run(self, action_dim: int, action_names: list[str]) -> None:
        """A configured run's action shape; nothing answered yet. Called under the handover's cond."""
        self.action_dim, self.action_names = action_dim, action_names
        self._answered_stamps: collections.deque[int] = collections.deque(maxlen=64)

    def describe(self) -> str:
        """The configure log's note on adapter mode ('' otherwise)."""
        if self.command_adapter is None:
            return ""
        return (f"; commands on {self.sub_action.topic_name} for joints "
                f"{list(self.command_adapter.map.joint_names)}")

    def action_publishers(self) -> int:
        return self.sub_action.get_publisher_count()

    def policy_present(self) -> bool:
        return self.action_publishers() > 0

    # ------------------------------------------------------------------ callbacks
    def _on_action_matched(self, info) -> None:
        with self.handover.cond:   # wake the stepping thread (it re-checks policy_present)
            if self._action_lock is not None and info.current_count == 0:
                self._action_lock.release()   # nobody left: the next publisher alone takes it
            self.handover.cond.notify_all()

    def _on_new_publisher(self, topic: str, publishers: int, first_time: bool) -> None:
        with self.handover.cond:
            self.counters["multiple_publishers_detected"] += 1
        if first_time:
            what = ("only the first one's actions are taken" if self._action_lock is not None
                    else "every one's actions are taken (first_action_publisher_only:=true takes "
                         "the first one's only)")
            self.node.get_logger().warning(
                f"{publishers} publishers on {topic}: another node publishes actions to this bridge "
                f"(an impostor, a second policy, a stray `ros2 topic pub`?); {what}")

    def _other_publisher(self, info: Any) -> str | None:
        """Why the action comes from another publisher than the first (first_action_publisher_only),
        or None. Called under cond."""
        if self._action_lock is None:
            return None
        seq = info.get("publication_sequence_number", 0) if isinstance(info, dict) else \
            getattr(info, "publication_sequence_number", 0)
        return self._action_lock.admit(int(seq or 0), self.sub_action.get_publisher_count())

    def _reject(self, counter: str, why: str) -> None:
        self.counters["actions_rejected"] += 1
        self.counters[counter] += 1
        self.throttle.warning(
            counter, f"action rejected ({counter}, {self.counters[counter]} so far): {why}")

    def _on_action(self, msg, info=None) -> None:
        now = time.monotonic()
        stamp = topics.stamp_to_ns(msg.header.stamp)
        h = self.handover
        with h.cond:
            # Attribution first: the locked publisher's every sample advances its numbers.
            other = self._other_publisher(info)
            if not h.go:   # not active: no observation awaits an answer (dropped, counted)
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
                if stamp != h.pending_stamp:
                    if stamp in self._answered_stamps:
                        return self._reject("rejected_duplicate",
                                            f"stamp {topics.format_stamp(stamp)} was already answered")
                    return self._reject("rejected_stale_stamp",
                                        f"stamp {topics.format_stamp(stamp)} is not the observation awaiting an "
                                        f"answer ({topics.format_stamp(h.pending_stamp)})" if h.pending_stamp is not None
                                        else f"stamp {topics.format_stamp(stamp)} arrived while no observation awaits an answer")
            else:
                if stamp not in h.published:
                    return self._reject("rejected_stale_stamp",
                                        f"stamp {topics.format_stamp(stamp)} answers no recent observation")
                if stamp in self._answered_stamps:
                    return self._reject("rejected_duplicate",
                                        f"stamp {topics.format_stamp(stamp)} was already answered")
            clipped = self._accept(a, stamp, now)
            if self.lockstep:
                h.hand_answer(clipped)
            else:
                if stamp != h.newest_stamp:
                    self.counters["late_actions"] += 1
                    self.throttle.warning(
                        "late_actions", f"late action for stamp {topics.format_stamp(stamp)} (newest observation "
                        f"{topics.format_stamp(h.newest_stamp)}; {self.counters['late_actions']} late so far)")
                if stamp > h.held_stamp:
                    h.held, h.held_stamp = clipped, stamp

    def _accept(self, a: np.ndarray, stamp: int, now: float) -> np.ndarray:
        """A valid answer to `stamp`, clipped and counted. Called under cond."""
        clipped = np.clip(a, ACTION_LOW, ACTION_HIGH)
        if np.any(clipped != a):
            self.counters["actions_clipped"] += 1
            self.throttle.warning(
                "actions_clipped", f"action {a.tolist()} clipped to [{ACTION_LOW}, "
                f"{ACTION_HIGH}] ({self.counters['actions_clipped']} so far)")
        self.counters["actions_accepted"] += 1
        first = stamp not in self._answered_stamps
        self._answered_stamps.append(stamp)
        sent = self.handover.published.get(stamp)
        if sent is not None and first:
            self.latency.add(now - sent)
        return clipped

    def _on_command(self, msg, info=None) -> None:
        """Adapter mode: a Float64MultiArray carries no stamp, so in lock-step the first command
        after an observation answers it (one arriving with none awaiting an answer is counted
        in commands_unsolicited and dropped); in real time the latest command is applied."""
        now = time.monotonic()
        h = self.handover
        with h.cond:
            other = self._other_publisher(info)
            if not h.go:
                self.counters["actions_while_inactive"] += 1
                return
            self.counters["actions_received"] += 1
            if other is not None:
                return self._reject("rejected_other_publisher", other)
            try:
                a = self.command_adapter.action(msg.data)
            except CommandRejected as e:
                return self._reject(e.counter, str(e))
            stamp = h.pending_stamp if self.lockstep else h.newest_stamp
            if stamp is None:
                self.counters["commands_unsolicited"] += 1
                self.throttle.warning(
                    "commands_unsolicited", f"a command arrived while no observation awaits an answer: "
                    f"dropped ({self.counters['commands_unsolicited']} so far)")
                return
            clipped = self._accept(a, stamp, now)
            if self.lockstep:
                h.hand_answer(clipped)
            else:
                h.held, h.held_stamp = clipped, stamp

    def _on_reset(self, request, response):
        h = self.handover
        with h.cond:
            self.counters["resets_requested"] += 1
            if not h.go:
                response.success = False
                response.message = f"not active (lifecycle state {self.node.lifecycle_state})"
                return response
            if not h.started:
                response.success = False
                response.message = "no episode running yet (waiting for subscribers)"
                return response
            served = h.reset_served
            h.reset_requested = True
            h.cond.notify_all()
            ok = h.cond.wait_for(lambda: (h.reset_served > served or h.stop.is_set()
                                          or self.done.is_set()), timeout=10.0)
            response.success = bool(ok and h.reset_served > served)
            response.message = h.reset_note if response.success else "reset not served"
        return response
