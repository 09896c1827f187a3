"""The ProtoCAD policy node (msgs_docs/policy.md).

    ros2 run protocad_ros policy --ros-args -p checkpoint:=runs/x   # a run directory or a file
    ros2 run protocad_ros policy --ros-args -p task:=walker_walk        # random agent + WARNING

Subscribes to image and step_info only (never the true context), pairs them by header stamp
(they may arrive in any order), filters the RSSM state over the episode (reset on is_first),
and answers EVERY observation with exactly one action stamped like it, plus the inferred
context features u, w, e on context_features (same stamp). A newer checkpoint at the same path
(or, with checkpoint_topic, a version received over ROS: protocad_ros/node/checkpoint_receiver.py)
is loaded in a background thread and swapped in at the next is_first observation, so no step
waits for a load and an episode is never served by two models.

Extension point: `add_act_callback(fn)` calls fn(ActEvent) after each answered observation
(e.g. protocad_ros.live_view for a rerun live stream); exceptions in callbacks are logged and
counted, never propagated.
"""
from __future__ import annotations

import threading
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState

from protocad_ros.node.action_publishing import ActEvent, ActionPublishing
from protocad_ros.node.bridge_pairing import BridgePairing
from protocad_ros.node.checkpoint_serving import CheckpointServing
from protocad_ros.node.observation_pairing import ObservationPairing
from protocad_ros.node.policy_diagnostics import PolicyDiagnostics
from protocad_ros.node.policy_params import COUNTERS, PARAMS
from protocad_ros.robot.camera_input import CameraInput
from protocad_ros.robot.robot_output import RobotOutput
from sim_bridge.contract import qos, topics
from sim_bridge.nodekit.lifecycle import ManagedNode
from sim_bridge.nodekit.param_table import ConfigError
from sim_bridge.nodekit.publisher_watch import PublisherWatch
from sim_bridge.nodekit.rosnode import KeyThrottle, declare_all, flush_publishers, install_parameter_guards, run_node
from sim_bridge.nodekit.type_watch import TopicTypeWatch

NODE_NAME = "policy"
#: Seconds a closing policy gives its readers to acknowledge the last actions (see close()).
ACTION_FLUSH_TIMEOUT_S = 30.0
__all__ = ["ActEvent", "COUNTERS", "PARAMS", "PolicyNode", "main"]


def _set_up_torch(p: dict[str, Any]) -> None:
    """num_threads, and the device checked (a ConfigError for one this process cannot use)."""
    import torch

    if p["num_threads"]:
        torch.set_num_threads(p["num_threads"])
    try:
        dev = torch.device(p["device"])
    except (RuntimeError, ValueError) as e:
        raise ConfigError(f"device {p['device']!r}: {e}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {p['device']!r} requested but CUDA is not available "
                          "(torch.cuda.is_available() is False); use device:=cpu")


class PolicyNode(ManagedNode):
    """See the module docstring; parameters in PARAMS, counters in COUNTERS. A managed node
    (sim_bridge/nodekit/lifecycle.py): configure loads the checkpoint (or builds the random agent) and
    starts its file watcher, activate serves, deactivate stops answering, cleanup drops the
    model. This class keeps the node-wide state (parameters, counters and their lock, the
    publishers, the publisher and type watches), builds its parts and forwards the lifecycle
    to them; each part is an object in a file of its own, held in the attribute named like its
    module: checkpoint_serving (CheckpointServing: loading, verifying, watching and swapping
    checkpoints), observation_pairing (ObservationPairing: image and step_info paired by
    stamp), bridge_pairing (BridgePairing: bridge_info believed only from the writer of those
    observations, checked against the model), action_publishing (ActionPublishing: the model
    step, action and context_features out, act callbacks), camera_input and robot_output
    (protocad_ros/robot/) and policy_diagnostics (PolicyDiagnostics: /diagnostics)."""

    def __init__(self, *, namespace: str = topics.DEFAULT_NAMESPACE, **kw: Any):
        super().__init__(NODE_NAME, namespace=namespace, **kw)
        self.done = threading.Event()
        self.exit_code = 0
        p = self.params = declare_all(self, PARAMS)
        self.executor_kind = p["executor"]
        _set_up_torch(p)
        self._lock = threading.Lock()            # guards the counters
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.counters["unknown_parameters"] = len(self.unknown_parameters)
        if not self.params["remote_lifecycle"]:
            self.refuse_remote_transitions()
        self._throttle = KeyThrottle(self.get_logger())

        obs_qos, out_qos = qos.observation_qos(), qos.action_qos()
        if p["latest_only"]:
            obs_qos.depth = 1
        # Profiles of their own: rclpy's QoS overriding changes the profile object it is given.
        # Lifecycle publishers: no action goes out unless active.
        self.pub_action = self.create_lifecycle_publisher(JointState, topics.ACTION, qos.action_qos(),
                                                          qos_overriding_options=qos.overridable())
        self.pub_features = self.create_lifecycle_publisher(JointState, topics.CONTEXT_FEATURES, out_qos)
        self.pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                              qos.diagnostics_qos())
        answers = (self.pub_action, self.pub_features)
        image_qos = qos.observation_qos()
        image_qos.depth = obs_qos.depth
        # One bridge per namespace: a second publisher of what the policy reads (a second
        # bridge announcing itself, an impostor) is warned about once and counted.
        self.publisher_watch = PublisherWatch(self._on_new_publisher)
        watch = self.publisher_watch.callbacks
        self.checkpoint_serving = CheckpointServing(node=self, params=p, count=self.count,
                                                    publish_diagnostics=self.publish_diagnostics)
        serving = self.checkpoint_serving
        # A robot's command interface and the fail-safe (protocad_ros/robot/).
        self.robot_output = RobotOutput(self, p, self.count)
        self.action_publishing = ActionPublishing(
            node=self, params=p, count=self.count, publishers=answers, policy=lambda: serving.policy,
            swap_if_pending=serving.swap_if_pending, checkpoint_updates=lambda: serving.checkpoint_updates,
            command=self.robot_output.answer)
        # Pairing and the bridge's announcement need each other: the pairing asks through lambdas.
        self.observation_pairing = ObservationPairing(
            node=self, params=p, count=self.count, event_callbacks=watch, qos_profile=obs_qos,
            publishers=answers, is_active=lambda: self.is_active, answer=self.action_publishing.answer,
            mismatch=lambda: self.bridge_pairing.mismatch, unannounced=lambda: self.bridge_pairing.unannounced())
        # The camera (protocad_ros/robot/camera_input.py): raw or compressed, any size, paired with
        # step_info or alone; a bad image_crop is a configuration error here.
        self.camera_input = CameraInput(self, p, qos_profile=image_qos, event_callbacks=watch,
                                        active=self.observation_pairing.accepting,
                                        size=lambda: serving.facts.image_hw[0], count=self.count,
                                        image=self.observation_pairing.on_model_image,
                                        observation=self.observation_pairing.answer_paired)
        self.bridge_pairing = BridgePairing(
            node=self, count=self.count, event_callbacks=watch, image_topic=self.camera_input.topic,
            facts=lambda: serving.facts, loaded=lambda: serving.policy is not None,
            believed=self.observation_pairing.bridge_believed)
        # A contract topic claimed by a stranger with another type never matches: said, not a hang.
        self.type_watch = TopicTypeWatch(self)
        self.policy_diagnostics = PolicyDiagnostics(
            node=self, params=p, publisher=self.pub_diag, counters=self._counters_now,
            checkpoint_serving=serving, camera_input=self.camera_input, action_publishing=self.action_publishing,
            bridge_pairing=self.bridge_pairing, robot_output=self.robot_output,
            publisher_watch=self.publisher_watch, type_watch=self.type_watch)
        self.diag_timer = self.create_timer(p["diagnostics_period_s"], self.publish_diagnostics)
        install_parameter_guards(self, PARAMS, lambda name, value: None,
                                 lambda reason: self.count("parameters_rejected",
                                                           f"parameter change rejected: {reason}"))
        if p["autostart"]:
            self.autostart()
        else:
            self.get_logger().info("autostart:=false: unconfigured, waiting for lifecycle "
                                   f"transitions on {self.get_fully_qualified_name()}/change_state")

    def add_act_callback(self, fn: Callable[[ActEvent], None]) -> None:
        """Call fn(ActEvent) after each answered observation (in the executor thread: keep it
        quick, e.g. hand over to a queue)."""
        self.action_publishing.add_act_callback(fn)

    # ------------------------------------------------------------------ lifecycle
    def configure_node(self) -> None:
        """Load the checkpoint (or build the random agent), start the file watcher; a missing
        or unloadable checkpoint is a ConfigError."""
        self.checkpoint_serving.configure()
        facts = self.checkpoint_serving.facts
        self.robot_output.configure(facts.action_names)
        self.observation_pairing.reset()
        self.action_publishing.configure(facts.action_dim, facts.action_names)
        self.bridge_pairing.configured()   # announced before we could check it
        self.checkpoint_serving.start()

    def activate_node(self) -> None:
        p, serving = self.params, self.checkpoint_serving
        facts = serving.facts
        self.get_logger().info(
            f"serving {serving.describe_agent()} on {p['device']} ({p['mode']}, exploration "
            f"noise {p['exploration_noise']}); {facts.action_dim}-d actions {facts.action_names}; "
            f"sees {facts.image_hw[0]}x{facts.image_hw[1]} of {self.camera_input.describe()}")
        self.camera_input.activated()
        # The config's precision is a request: resolved here, on this node's device.
        self.get_logger().info(serving.policy.agent.precision.describe())
        self.robot_output.activate()

    def restart_episode(self) -> None:
        """With observations:=image_only, the next frame starts a new episode (a blank filter):
        for a part that knows the robot's input was interrupted (watchdog, enable switch)."""
        self.camera_input.restart_episode()

    def deactivate_node(self) -> None:
        self.observation_pairing.deactivate()
        self.robot_output.deactivate()

    def cleanup_node(self) -> None:
        self.checkpoint_serving.stop()
        self.action_publishing.cleanup()
        self.robot_output.cleanup()
        self.checkpoint_serving.release()
        self.bridge_pairing.release()
        self.observation_pairing.reset()

    # ------------------------------------------------------------------ node-wide
    def count(self, key: str, why: str | None = None, n: int = 1) -> None:
        """Counts `n` under `key` (diagnostics); `why`: a warning, throttled per key."""
        with self._lock:
            self.counters[key] += n
            total = self.counters[key]
        if why:
            self._throttle.warning(key, f"{why} ({key}: {total} so far)")

    def _counters_now(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counters)

    def publish_diagnostics(self) -> None:
        self.policy_diagnostics.publish()

    def _on_new_publisher(self, topic: str, publishers: int, first_time: bool) -> None:
        if first_time:
            self.get_logger().warning(
                f"{publishers} publishers on {topic}: a second sim bridge in {self.get_namespace()}, or "
                "another node publishing there (an impostor?); their observations interleave "
                "(multiple_publishers on /diagnostics)")

    def close(self) -> None:
        """Last diagnostics (what was served), then the shutdown transition (the watcher
        ends, the live view's recording is completed), then up to ACTION_FLUSH_TIMEOUT_S for
        reliable readers to acknowledge every action and context_features sample: a recorder
        that was stalled still has a backlog, which exiting at once would lose."""
        try:
            self.publish_diagnostics()
        except Exception:  # noqa: BLE001 - exiting: the last diagnostics are best effort
            pass
        self.shutdown_lifecycle()
        self.bridge_pairing.stop()
        try:
            for topic in flush_publishers((self.pub_action, self.pub_features), ACTION_FLUSH_TIMEOUT_S):
                self.get_logger().warning(f"{topic}: exiting with samples a reader has not acknowledged "
                                          f"after {ACTION_FLUSH_TIMEOUT_S:g} s (a reader stalled or gone)")
        except Exception as exc:  # noqa: BLE001  closing must go on; say why nothing was flushed
            self.get_logger().warning(f"could not wait for the last actions to be acknowledged: {exc}")
        c, latency = self.counters, self.action_publishing.latency
        self.get_logger().info("stopped: " + ", ".join(f"{k}={c[k]}" for k in COUNTERS if c[k])
                               + f"; latency p50 {latency.percentile(50) * 1e3:.2f} ms, "
                               f"p99 {latency.percentile(99) * 1e3:.2f} ms")


def main(argv: list[str] | None = None) -> None:
    raise SystemExit(run_node(
        PolicyNode, prog="policy", params=PARAMS, argv=argv,
        description="ProtoCAD policy node: answers every observation (image + step_info, "
                    "paired by stamp) with an action stamped like it, and publishes the "
                    "inferred context features u, w, e. Contract: msgs_docs/policy.md.",
        example="ros2 run protocad_ros policy --ros-args -p checkpoint:=runs/x "
                "-p reload_poll_s:=5.0 -p mode:=deterministic"))


if __name__ == "__main__":
    main()
