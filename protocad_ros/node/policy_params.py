"""The policy node's parameter table and counters (msgs_docs/policy.md), apart from the node
so that --help, docs and tests read them without importing rclpy or torch."""
from __future__ import annotations

from protocad_ros.model.hyperparameters import DEFAULT_CLI_PRESET, PRESETS, VARIANTS
from sim_bridge.contract.contexts import TASKS
from sim_bridge.nodekit.param_table import Param, autostart_param, executor_param, remote_lifecycle_param, strict_param

PARAMS: tuple[Param, ...] = (
    Param("checkpoint", "", "Checkpoint file (protocad_ros.checkpoint). Empty: a randomly "
          "initialised agent (task, preset, variant below) with a WARNING. With "
          "checkpoint_topic: this node's own copy, where received versions are written."),
    Param("wait_for_checkpoint", False, "If the checkpoint file does not exist yet: serve a "
          "random agent and load the file once it appears (collect-train-reload loop) "
          "instead of exiting with an error."),
    Param("reload_poll_s", 2.0, "How often the checkpoint file is checked for a newer version "
          "(mtime/inode/size); a newer one is loaded in the background and served from the "
          "next is_first observation. 0 = never reload.", range=(0.0, 3600.0), units="s"),
    Param("checkpoint_topic", "", "Receive checkpoints over ROS from a checkpoint publisher "
          "(trainer/nodes/checkpoint_publisher.py) announcing on this topic, e.g. checkpoint; each "
          "verified version is written to `checkpoint` (required then) and served from the next "
          "is_first observation. Empty: off (the file alone)."),
    Param("trusted_keys", "", "Ed25519 public key file(s), comma-separated (protocad-keygen "
          "NAME writes NAME.pub): only checkpoints signed by one of them are served, received "
          "over checkpoint_topic (signed announcement) or loaded from the checkpoint file "
          "(detached signature FILE.sig), and each version's sequence number must grow. Empty: "
          "unsigned checkpoints are accepted from the file (a WARNING at start); with "
          "checkpoint_topic the node refuses to start unless allow_unsigned."),
    Param("allow_unsigned", False, "With checkpoint_topic and no trusted_keys: start anyway and "
          "serve UNSIGNED checkpoints received over ROS (anyone on the DDS domain can replace the "
          "model; a WARNING at start, diagnostics at WARN with unsigned_checkpoints_allowed=True). "
          "Default: such a node refuses to start."),
    Param("rollback_state", "", "With trusted_keys: the file that keeps the highest sequence "
          "number this node held (its rollback floor), apart from the checkpoint, so that losing "
          "FILE.sig does not lower it. Default: beside the first trusted key, "
          "KEY.served-<hash of the checkpoint path>.json."),
    Param("min_checkpoint_seq", 0, "With trusted_keys: the lowest sequence number of a signed "
          "version this node takes (over checkpoint_topic, or a changed file): an older signed "
          "version replayed while the publisher is down is refused as a rollback from the first "
          "message, also on a brand-new node whose rollback floor is still empty. The file served "
          "at start is checked against rollback_state only. 0: none. protocad-fleet sets the time "
          "it started its publisher, in ms (the publisher's current number: seq is the signer's clock).",
          range=(0, 2**62), units="seq"),
    Param("max_checkpoint_bytes", 512 << 20, "Largest checkpoint accepted over checkpoint_topic "
          "(a bigger announced version is refused before any chunk is kept) or loaded from the "
          "checkpoint file (the file, and the sizes its archive entries declare, checked before "
          "anything is expanded).",
          range=(4096, 1 << 40), units="bytes"),
    Param("checkpoint_transfer_timeout_s", 60.0, "A version announced on checkpoint_topic from "
          "which no new chunk arrived for this long (and not all of them arrived) is rejected as "
          "incomplete.", range=(0.1, 3600.0), units="s"),
    Param("task", "pendulum_swingup", "Task of the random agent (action size, K prototypes); "
          "with a checkpoint its config's task is used.", choices=tuple(sorted(TASKS))),
    Param("preset", DEFAULT_CLI_PRESET, "Model size preset of the random agent.", choices=PRESETS),
    Param("variant", "protocad", "Model variant of the random agent.", choices=VARIANTS),
    Param("device", "cpu", "Torch device of the model, e.g. cpu, cuda, cuda:0."),
    Param("mode", "deterministic", "deterministic: the actor's mode (tanh_normal: the most "
          "likely of 100 samples, as DreamerPro); sample: a sample of the actor's distribution.",
          choices=("deterministic", "sample")),
    Param("state_mean", False, "Filter with the posterior's mean instead of a sample of it "
          "(DreamerV2's eval_state_mean; false, as DreamerV2 and DreamerPro evaluate)."),
    Param("latest_only", False, "Real time: subscribe to observations with KEEP_LAST(1), so a "
          "policy that falls behind skips to the newest observation instead of answering every "
          "queued one in turn (the skipped ones are counted in observations_skipped). Off for "
          "lock-step, where every observation waits for its answer."),
    Param("exploration_noise", 0.0, "Std of Gaussian noise added to the action (then clipped "
          "to [-1, 1]).", range=(0.0, 10.0)),
    Param("seed", 0, "Seeds the random agent's weights and the action sampling/noise.",
          range=(0, 2**31 - 1)),
    Param("num_threads", 0, "torch intra-op threads (0 = torch's default).", range=(0, 1024)),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics.", range=(0.05, 3600.0),
          units="s"),
    Param("rerun_mode", "off", "Live rerun stream of image, u/w/e, assignment, action and "
          "reward on the sim_time timeline: off, spawn (local viewer), connect (to rerun_url), "
          "save (to rerun_path).", choices=("off", "spawn", "connect", "save")),
    Param("rerun_url", "", "connect mode: gRPC url of a running viewer ('' = "
          "rerun+http://127.0.0.1:9876/proxy, what a plain `rerun` listens on)."),
    Param("rerun_path", "", "save mode: the .rrd file to write (completed at shutdown)."),
    autostart_param(),
    remote_lifecycle_param(),
    strict_param(),
    executor_param(),
    # The camera (protocad_ros/robot/camera_input.py, issue 53).
    Param("image_transport", "raw", "raw: sensor_msgs/Image on image (rgb8, bgr8, rgba8, bgra8, "
          "mono8, any size); compressed: sensor_msgs/CompressedImage (JPEG or PNG) on "
          "<image>/compressed, image_transport's name for it.", choices=("raw", "compressed")),
    Param("image_crop", "center", "The part of a frame the model sees, resized to its square with "
          "area averaging: center (the largest centered square), full (the whole frame, squashed) "
          "or x,y,w,h in pixels. Another value: configuration error. A frame already at the "
          "model's size passes unchanged with center or full."),
    Param("observations", "paired", "paired: image and step_info paired by stamp (the sim "
          "bridge's contract); image_only: a camera alone, no step_info: each frame is an "
          "observation (reward 0; a new episode at the first frame after activation and after "
          "restart_episode(); episode and step counted by the node; stamps must grow).",
          choices=("paired", "image_only")),
)

# A robot's command interface and the fail-safe (protocad_ros/robot/, msgs_docs/policy.md).
COMMAND_PARAMS: tuple[Param, ...] = (
    Param("command_output", "", "Also send each answer as a robot's command on command_topic: "
          "float64_multi_array (std_msgs/Float64MultiArray, a ros2_control forward command "
          "controller) or joint_trajectory (trajectory_msgs/JointTrajectory, one point), in the "
          "joint order and units of command_map. Empty: none (the action topic alone).",
          choices=("", "float64_multi_array", "joint_trajectory")),
    Param("command_topic", "commands", "Where the commands go (remap or set it to the controller's, "
          "e.g. /forward_position_controller/commands)."),
    Param("command_map", "", "YAML joint map (sim_bridge/contract/joint_map.py): the robot's joints "
          "in its order, each driven by one action through offset + scale * action, with an optional "
          "max_rate; checked at configure (a bad map: configuration error). Empty: one joint per "
          "action, named after it, unscaled."),
    Param("trajectory_time_from_start_s", 0.1, "joint_trajectory: the point's time_from_start "
          "(header.stamp is the observation's).", range=(0.0, 3600.0), units="s"),
    Param("input_timeout_s", 0.5, "Real-time use (command_output set, or latest_only): when no fresh "
          "observation was answered for this long, the safe action goes out on command_topic (again "
          "every input_timeout_s) and /diagnostics is ERROR until the next one.",
          range=(0.01, 3600.0), units="s"),
    Param("safe_action", "zero", "What goes out while disabled or while the watchdog is tripped: zero "
          "(action 0 through the map: each joint at its offset) or hold (the last command sent), "
          "rate limited like every command.", choices=("zero", "hold")),
    Param("enabled_at_start", "auto", "Whether the model's commands go out from the start: auto = "
          "false with command_output (enable with ~/enable or the enable topic), true otherwise.",
          choices=("auto", "true", "false")),
)
PARAMS += COMMAND_PARAMS

COUNTERS = ("observations_answered", "episodes", "images_received", "images_rejected",
            "rejected_image_encoding", "rejected_image_size", "rejected_image_data",
            "step_info_rejected", "duplicate_observations", "stale_observations", "sim_time_restarts",
            "unpaired_dropped", "checkpoint_reloads", "checkpoint_load_errors",
            "act_callback_errors", "unknown_parameters", "parameters_rejected",
            "observations_lost", "observations_skipped", "fragments_discarded", "step_info_received",
            "mismatched_observations", "awaiting_bridge_info", "bridge_info_rejected", "bridge_info_ignored",
            "observations_while_inactive", "checkpoint_transfers", "checkpoint_transfers_rejected",
            "checkpoint_signatures_rejected", "checkpoint_rollbacks_rejected",
            "checkpoint_limits_rejected", "checkpoint_mismatches", "checkpoint_chunks_dropped",
            "remote_transitions_refused", "episode_restarts")
# The robot's command interface and the fail-safe.
COUNTERS += ("commands_sent", "safe_commands_sent", "commands_rate_limited", "watchdog_trips",
             "watchdog_clears", "enable_switches")
