"""`PolicyDiagnostics`: what the policy node reports on /diagnostics (msgs_docs/policy.md): the
agent and checkpoint it serves (and the one pending for the next episode, the version being
received, the trust settings and rollback floor), latency and model-time percentiles, its
counters, and one level and message saying what needs a look first. A part of the policy node
(protocad_ros/node/policy_node.py), called by its timer, at each hand-over of a loaded
checkpoint (launchers wait for pending_checkpoint_updates), when it starts serving it, and
once more at close.

It owns nothing but its publisher's use; it is handed the node (lifecycle state, error counts,
clock, name), the parameter dict, the diagnostics publisher, `counters()` (a copy of the node's
counters, taken under its lock), and the parts and watches whose state it reports, read through
their public methods and properties.
"""
from __future__ import annotations

from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray

from sim_bridge.nodekit.rosnode import make_status


class PolicyDiagnostics:
    """One DiagnosticStatus per call of publish(); see the module docstring."""

    def __init__(self, *, node: Any, params: dict[str, Any], publisher: Any, counters: Callable[[], dict[str, int]],
                 checkpoint_serving: Any, camera_input: Any, action_publishing: Any, bridge_pairing: Any,
                 robot_output: Any, publisher_watch: Any, type_watch: Any):
        self._node, self._params, self._publisher, self._counters = node, params, publisher, counters
        self._serving, self._camera, self._actions = checkpoint_serving, camera_input, action_publishing
        self._bridge, self._robot = bridge_pairing, robot_output
        self._publisher_watch, self._type_watch = publisher_watch, type_watch
        self._name = node.get_fully_qualified_name()   # -r __node:=... renames it too

    def publish(self) -> None:
        node, serving, actions = self._node, self._serving, self._actions
        state = node.lifecycle_state
        c = self._counters()
        task = serving.facts.task
        values: dict[str, Any] = {
            **serving.diagnostics(),
            "task": task, "device": self._params["device"], "mode": self._params["mode"],
            "camera": self._camera.describe(),
            "latency_ms_p50": actions.latency.percentile(50) * 1e3,
            "latency_ms_p99": actions.latency.percentile(99) * 1e3,
            "act_ms_p50": actions.act_time.percentile(50) * 1e3,
            "act_ms_p99": actions.act_time.percentile(99) * 1e3,
            "episode": actions.episode, "step": actions.step, "callback_errors": node.callback_errors,
            "lifecycle_state": state, "transition_errors": node.transition_errors,
            **c,
        }
        bad = (c["images_rejected"] or c["step_info_rejected"] or c["checkpoint_load_errors"]
               or c["checkpoint_transfers_rejected"]
               or c["stale_observations"] or c["unpaired_dropped"] or c["observations_lost"]
               or node.callback_errors)
        unknown = node.unknown_parameters
        bridge, mismatch = self._bridge.bridge, self._bridge.mismatch
        values["bridge"] = (f"{bridge.task} {bridge.action_names}" if bridge else "")
        several = self._publisher_watch.summary()
        values["multiple_publishers"] = several
        values["multiple_publishers_detected"] = self._publisher_watch.detected
        values.update(self._type_watch.diagnostics())
        claimed = values["type_mismatches"]
        unsigned, random = serving.unsigned_topic, serving.agent_kind == "random"
        level = ("ERROR" if mismatch or claimed else
                 "WARN" if bad or unknown or several or unsigned or random else "OK")
        message = (f"not answering: {mismatch}" if mismatch else
                   f"offered with another type than the contract's: {claimed}" if claimed else
                   f"several publishers on {several} (a second bridge? an impostor?)" if several else
                   f"unknown parameters ignored: {unknown}" if unknown else
                   f"{state}: not answering" if state != "active" else
                   "accepting UNSIGNED checkpoints over checkpoint_topic (allow_unsigned)" if unsigned else
                   "random agent" if random else
                   "rejected inputs or checkpoint errors" if bad else "serving")
        level, message = self._robot.report(values, level, message)   # watchdog, enable switch
        arr = DiagnosticArray()
        arr.header.stamp = node.get_clock().now().to_msg()
        arr.status = [make_status(self._name, task, values, level, message)]
        try:
            self._publisher.publish(arr)
        except Exception:  # noqa: BLE001 - context shutting down
            pass
