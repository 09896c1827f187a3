"""What the policy node reports on /diagnostics (msgs_docs/policy.md): the agent and checkpoint
it serves (and the one pending for the next episode, the version being received, the trust
settings and rollback floor), latency and model-time percentiles, its counters, and one level
and message saying what needs a look first. A part of PolicyNode, reading its counters and
pending checkpoint under the node's lock; called by its timer, at each hand-over of a loaded
checkpoint (launchers wait for pending_checkpoint_updates), when it starts serving it, and
once more at close."""
from __future__ import annotations

from typing import Any

from diagnostic_msgs.msg import DiagnosticArray

from sim_bridge.nodekit.rosnode import make_status


class PolicyDiagnostics:
    def _publish_diagnostics(self) -> None:
        state = self.lifecycle_state
        with self._lock:
            c = dict(self.counters)
            pending = self._pending_policy
        values: dict[str, Any] = {
            "agent": self.agent_kind, "checkpoint": self.params["checkpoint"],
            "checkpoint_updates": self.checkpoint_updates,
            "pending_checkpoint_updates": (pending[1].get("updates", -1) if pending else -1),
            "checkpoint_sha256": self.ckpt_sha or "",
            "checkpoint_announced": self.receiver.last_announced if self.receiver is not None else "",
            "checkpoint_transfer": self.receiver.progress() if self.receiver is not None else "",
            "checkpoint_buffered_bytes": self.receiver.buffered_bytes() if self.receiver is not None else 0,
            "checkpoint_seq": self.ckpt_seq,
            "checkpoint_trusted_keys": ",".join(sorted(self.trusted)) if self.trusted else "",
            "checkpoint_rollback_floor": self.rollback.seq if self.rollback is not None else -1,
            "unsigned_checkpoints_allowed": self.unsigned_topic,
            # The trainer's scalar counters only (env steps, episodes, ...): its sampler state
            # and bag list would be kilobytes on every diagnostics message.
            **{f"checkpoint/{k}": v for k, v in self.ckpt_counters.items()
               if k != "updates" and isinstance(v, (int, float)) and not isinstance(v, bool)},
            "task": self.task, "device": self.params["device"], "mode": self.params["mode"],
            "camera": self.camera.describe(),
            "latency_ms_p50": self.latency.percentile(50) * 1e3,
            "latency_ms_p99": self.latency.percentile(99) * 1e3,
            "act_ms_p50": self.act_time.percentile(50) * 1e3,
            "act_ms_p99": self.act_time.percentile(99) * 1e3,
            "episode": self._episode, "step": self._step, "callback_errors": self.callback_errors,
            "lifecycle_state": state, "transition_errors": self.transition_errors,
            **c,
        }
        bad = (c["images_rejected"] or c["step_info_rejected"] or c["checkpoint_load_errors"]
               or c["checkpoint_transfers_rejected"]
               or c["stale_observations"] or c["unpaired_dropped"] or c["observations_lost"]
               or self.callback_errors)
        unknown = self.unknown_parameters
        values["bridge"] = (f"{self.bridge.task} {self.bridge.action_names}" if self.bridge else "")
        several = self.publisher_watch.summary()
        values["multiple_publishers"] = several
        values["multiple_publishers_detected"] = self.publisher_watch.detected
        values.update(self.type_watch.diagnostics())
        claimed = values["type_mismatches"]
        unsigned = self.unsigned_topic
        level = ("ERROR" if self.mismatch or claimed else
                 "WARN" if bad or unknown or several or unsigned or self.agent_kind == "random" else "OK")
        message = (f"not answering: {self.mismatch}" if self.mismatch else
                   f"offered with another type than the contract's: {claimed}" if claimed else
                   f"several publishers on {several} (a second bridge? an impostor?)" if several else
                   f"unknown parameters ignored: {unknown}" if unknown else
                   f"{state}: not answering" if state != "active" else
                   "accepting UNSIGNED checkpoints over checkpoint_topic (allow_unsigned)" if unsigned else
                   "random agent" if self.agent_kind == "random" else
                   "rejected inputs or checkpoint errors" if bad else "serving")
        level, message = self.robot.report(values, level, message)   # watchdog, enable switch
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [make_status(self._diag_name, self.task, values, level, message)]
        try:
            self.pub_diag.publish(arr)
        except Exception:  # noqa: BLE001 - context shutting down
            pass
