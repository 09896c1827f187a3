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

import collections
import threading
from typing import Any, Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState

from protocad_ros.atomic import file_signature, remove_stale_temporaries
from protocad_ros.checkpoint.files import CheckpointError, checkpoint_file
from protocad_ros.live_view import LiveView
from protocad_ros.node.action_publishing import ActEvent, ActionPublishing
from protocad_ros.node.bridge_pairing import BridgePairing
from protocad_ros.node.checkpoint_receiver import CheckpointReceiver
from protocad_ros.node.checkpoint_serving import CheckpointServing
from protocad_ros.node.diagnostics import PolicyDiagnostics
from protocad_ros.node.observation_pairing import ObservationPairing
from protocad_ros.node.policy_params import COUNTERS, PARAMS
from protocad_ros.node.refusal_log import RefusalLog
from protocad_ros.robot.camera_input import CameraInput
from protocad_ros.robot.robot_output import RobotOutput
from sim_bridge.contract import qos, topics
from sim_bridge.contract.contexts import task_actuators
from sim_bridge.nodekit.lifecycle import ManagedNode
from sim_bridge.nodekit.publisher_watch import PublisherWatch
from sim_bridge.nodekit.rosnode import (
    ConfigError,
    KeyThrottle,
    Percentiles,
    declare_all,
    flush_publishers,
    install_parameter_guards,
    run_node,
)
from sim_bridge.nodekit.type_watch import TopicTypeWatch

NODE_NAME = "policy"
#: Seconds a closing policy gives its readers to acknowledge the last actions (see close()).
ACTION_FLUSH_TIMEOUT_S = 30.0
__all__ = ["ActEvent", "COUNTERS", "PARAMS", "PolicyNode", "main"]


class PolicyNode(ObservationPairing, BridgePairing, ActionPublishing, CheckpointServing, PolicyDiagnostics,
                 ManagedNode):
    """See the module docstring; parameters in PARAMS, counters in COUNTERS. A managed node
    (sim_bridge/nodekit/lifecycle.py): configure loads the checkpoint (or builds the random agent) and
    starts its file watcher, activate serves, deactivate stops answering, cleanup drops the
    model. This class wires the node's ROS interfaces, state and lifecycle; its parts, one file
    each: ObservationPairing (image, step_info and bridge_info in, paired by stamp), BridgePairing
    (bridge_info believed only from the writer of those observations),
    ActionPublishing (the model step, action and context_features out, act callbacks),
    CheckpointServing (loading, watching and swapping checkpoints) and PolicyDiagnostics
    (/diagnostics)."""

    def __init__(self, *, namespace: str = topics.DEFAULT_NAMESPACE, **kw: Any):
        super().__init__(NODE_NAME, namespace=namespace, **kw)
        self.done = threading.Event()
        self.exit_code = 0
        p = self.params = declare_all(self, PARAMS)
        self.executor_kind = p["executor"]
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
        self._lock = threading.Lock()            # guards _pending_policy and counters
        self._stop = threading.Event()           # set: the checkpoint watcher ends (cleanup)
        self._wake = threading.Event()           # set: the watcher looks now (a received version)
        self.receiver: CheckpointReceiver | None = None
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.counters["unknown_parameters"] = len(self.unknown_parameters)
        if not self.params["remote_lifecycle"]:
            self.refuse_remote_transitions()
        self._throttle = KeyThrottle(self.get_logger())
        self.refusals = RefusalLog(self.get_logger().error)   # refused checkpoints' lines
        self.latency = Percentiles()             # completing message -> action published
        self.act_time = Percentiles()            # model time (Policy.act)
        self._act_callbacks: list[Callable[[ActEvent], None]] = []
        self._release_model()

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
        image_qos = qos.observation_qos()
        image_qos.depth = obs_qos.depth
        # One bridge per namespace: a second publisher of what the policy reads (a second
        # bridge announcing itself, an impostor) is warned about once and counted.
        self.publisher_watch = PublisherWatch(self._on_new_publisher)
        watch = self.publisher_watch.callbacks
        # The camera (protocad_ros/robot/camera_input.py): raw or compressed, any size, paired with
        # step_info or alone; a bad image_crop is a configuration error here.
        self.camera = CameraInput(self, p, qos_profile=image_qos, event_callbacks=watch,
                                  active=lambda: not self._inactive(), size=lambda: self.image_hw[0],
                                  count=self._count, image=self._on_model_image, observation=self._answer_paired)
        self.sub_info = None if p["observations"] == "image_only" else self.create_subscription(
            JointState, topics.STEP_INFO, self._on_info, obs_qos,
            event_callbacks=watch(self.resolve_topic_name(topics.STEP_INFO)))
        self.bridge: topics.BridgeInfo | None = None
        self._announcer_checked_at, self._announcer_present = -1e9, False
        self.sub_bridge_info = self.create_subscription(JointState, topics.BRIDGE_INFO, self._on_bridge_info_heard,
                                                        qos.announcement_qos(),
                                                        event_callbacks=watch(self.resolve_topic_name(topics.BRIDGE_INFO)))
        self._start_bridge_pairing()
        # A contract topic claimed by a stranger with another type never matches: said, not a hang.
        self.type_watch = TopicTypeWatch(self)
        self.diag_timer = self.create_timer(p["diagnostics_period_s"], self._publish_diagnostics)
        install_parameter_guards(self, PARAMS, lambda name, value: None,
                                 lambda reason: self._count("parameters_rejected",
                                                            f"parameter change rejected: {reason}"))
        self._diag_name = self.get_fully_qualified_name()
        # A robot's command interface and the fail-safe (protocad_ros/robot/).
        self.robot = RobotOutput(self, p, self._count)
        if p["autostart"]:
            self.autostart()
        else:
            self.get_logger().info("autostart:=false: unconfigured, waiting for lifecycle "
                                   f"transitions on {self._diag_name}/change_state")

    def _release_model(self) -> None:
        """No model, no per-episode state (unconfigured)."""
        self.policy = None
        self.ckpt_counters: dict[str, Any] = {}
        self.agent_kind = "none"
        self.task = self.params["task"]
        self.action_dim, self.image_hw, self.action_names = 0, (0, 0), []
        self.live_view: LiveView | None = None
        self._watcher: threading.Thread | None = None
        self._loaded_sig: tuple | None = None     # watch keys (checkpoint_serving._watch_key)
        self._failed_sig: tuple | None = None
        self._unsigned_since: tuple = (None, 0.0)   # (watch key, since): a file awaiting FILE.sig
        self.ckpt_sha: str | None = None          # sha256 of the served checkpoint file
        self.ckpt_seq = -1                        # its signed sequence number (-1: unsigned)
        self.trusted = None                       # key id -> public key; None: unsigned accepted
        self.rollback = None                      # RollbackFloor with trusted keys
        with self._lock:
            self._pending_policy: tuple | None = None   # (policy, counters, key, sha, seq) to swap in
        self.mismatch: str | None = None
        self._reset_filter()

    def _reset_filter(self) -> None:
        # Per-episode filter state (the RSSM state itself lives in self.policy).
        self._prev_action = np.zeros(self.action_dim, np.float32)
        self._unpaired: collections.OrderedDict[int, dict[str, Any]] = collections.OrderedDict()
        self._last_stamp: int | None = None
        self._last_answer: tuple[Any, Any] | None = None
        self._episode = -1
        self._episode_return: float | None = None
        # (stamp, image + step_info, receive time) held until bridge_info arrives (_arrive)
        self._held_for_bridge_info: tuple | None = None
        self._step = -1

    # ------------------------------------------------------------------ lifecycle
    def configure_node(self) -> None:
        """Load the checkpoint (or build the random agent), start the file watcher; a missing
        or unloadable checkpoint is a ConfigError."""
        p = self.params
        if p["checkpoint"]:   # a file or a run directory, as everywhere else
            p["checkpoint"] = str(checkpoint_file(p["checkpoint"]))
        path, topic = p["checkpoint"], p["checkpoint_topic"]
        if topic and not path:
            raise ConfigError(f"checkpoint_topic:={topic} needs checkpoint:=FILE: where received "
                              "versions are written (and served from after a restart)")
        self._load_trust()
        sig = file_signature(path) if path else None
        if sig is not None:
            try:
                data, self.ckpt_sha = self._read_once(path)   # verified and loaded, read once
            except (OSError, CheckpointError) as e:   # CheckpointError: over max_checkpoint_bytes
                raise ConfigError(f"cannot read checkpoint {path}: {e}") from None
            self._configure_seq(path, self.ckpt_sha, len(data))
            try:
                self.policy, self.ckpt_counters = self._load(path, data=data)
            except Exception as e:  # noqa: BLE001 - CheckpointError and friends: a clear message, exit 2
                raise ConfigError(f"cannot load checkpoint {path}: {e}") from None
            self._loaded_sig = self._watch_key(path)
            self.agent_kind = "checkpoint"
        elif path and not (p["wait_for_checkpoint"] or topic):
            raise ConfigError(f"checkpoint {path} does not exist (set wait_for_checkpoint:=true "
                              "to serve a random agent until it appears)")
        elif path and p["reload_poll_s"] <= 0 and not topic:
            raise ConfigError(f"checkpoint {path} does not exist and reload_poll_s is 0: it "
                              "would never be loaded")
        else:
            self.policy, self.ckpt_counters = self._random_policy(), {}
            self.agent_kind = "random"
            self.get_logger().warning(
                ("checkpoint %s does not exist yet: " % path if path else "no checkpoint given: ")
                + f"serving a RANDOMLY INITIALISED {p['variant']} agent ({p['preset']} preset, "
                f"task {p['task']}); its actions are meaningless")
        cfg = self.policy.agent.cfg
        self.task = getattr(cfg, "task", p["task"])
        self.action_dim = int(self.policy.agent.action_dim)
        self.image_hw = (int(cfg.train.image_size),) * 2
        try:
            names = task_actuators(self.task)
        except Exception:  # noqa: BLE001 - no actuator names for this task: generic ones below
            names = []
        self.action_names = names if len(names) == self.action_dim else [
            f"a{i}" for i in range(self.action_dim)]
        self.robot.configure(self.action_names)
        self.policy.reset()
        self._reset_filter()
        try:
            self.live_view = LiveView.from_params(p["rerun_mode"], p["rerun_url"],
                                                  p["rerun_path"], action_names=self.action_names)
        except ValueError as e:
            raise ConfigError(f"rerun: {e}") from None
        if self.bridge is not None:   # announced before we could check it
            self._check_bridge()
        self._stop.clear()
        if topic:
            remove_stale_temporaries(path)   # what an install interrupted by a kill left
            self.receiver = CheckpointReceiver(
                self, topic, timeout_s=p["checkpoint_transfer_timeout_s"], wake=self._wake.set,
                next_sha=self._next_sha, serving=self._describe_agent, count=self._count,
                max_bytes=p["max_checkpoint_bytes"], trusted=self.trusted,
                newest_seq=self._newest_seq, fits=self._announced_fits, refusals=self.refusals)
        if path and (p["reload_poll_s"] > 0 or topic):
            self._watcher = threading.Thread(target=self._watch, name="checkpoint_watcher",
                                             daemon=True)
            self._watcher.start()

    def activate_node(self) -> None:
        p = self.params
        self.get_logger().info(
            f"serving {self._describe_agent()} on {p['device']} ({p['mode']}, exploration "
            f"noise {p['exploration_noise']}); {self.action_dim}-d actions {self.action_names}; "
            f"sees {self.image_hw[0]}x{self.image_hw[1]} of {self.camera.describe()}")
        self.camera.activated()
        # The config's precision is a request: resolved here, on this node's device.
        self.get_logger().info(self.policy.agent.precision.describe())
        self.robot.activate()

    def restart_episode(self) -> None:
        """With observations:=image_only, the next frame starts a new episode (a blank filter):
        for a part that knows the robot's input was interrupted (watchdog, enable switch)."""
        self.camera.restart_episode()

    def deactivate_node(self) -> None:
        # Halves of observations that arrived before: they will not be answered.
        self._unpaired.clear()
        self.robot.deactivate()

    def cleanup_node(self) -> None:
        self._stop.set()
        self._wake.set()
        if self.receiver is not None:
            self.receiver.destroy()
            self.receiver = None
        if self._watcher is not None:
            self._watcher.join(timeout=10.0)
            if self._watcher.is_alive():
                raise RuntimeError("the checkpoint watcher did not end within 10 s")
        if self.live_view is not None:
            self.live_view.close()
        self.robot.cleanup()
        self._release_model()

    # ------------------------------------------------------------------ callbacks
    def _count(self, key: str, why: str | None = None) -> None:
        with self._lock:
            self.counters[key] += 1
            n = self.counters[key]
        if why:
            self._throttle.warning(key, f"{why} ({key}: {n} so far)")

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
            self._publish_diagnostics()
        except Exception:  # noqa: BLE001 - exiting: the last diagnostics are best effort
            pass
        self.shutdown_lifecycle()
        self._stop_bridge_pairing()
        try:
            for topic in flush_publishers((self.pub_action, self.pub_features), ACTION_FLUSH_TIMEOUT_S):
                self.get_logger().warning(f"{topic}: exiting with samples a reader has not acknowledged "
                                          f"after {ACTION_FLUSH_TIMEOUT_S:g} s (a reader stalled or gone)")
        except Exception as exc:  # noqa: BLE001  closing must go on; say why nothing was flushed
            self.get_logger().warning(f"could not wait for the last actions to be acknowledged: {exc}")
        c = self.counters
        self.get_logger().info("stopped: " + ", ".join(f"{k}={c[k]}" for k in COUNTERS if c[k])
                               + f"; latency p50 {self.latency.percentile(50) * 1e3:.2f} ms, "
                               f"p99 {self.latency.percentile(99) * 1e3:.2f} ms")


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
