"""The sim bridge's parameter table, counters and episode-context schedule
(msgs_docs/sim_bridge.md), apart from the node so that --help, docs and tests read them
without importing rclpy."""
from __future__ import annotations

from sim_bridge.contract.contexts import TASKS
from sim_bridge.nodekit.param_table import (
    ConfigError,
    Param,
    autostart_param,
    executor_param,
    remote_lifecycle_param,
    strict_param,
)


def episode_contexts(task: str, split: str, schedule: str, fixed: str) -> list[dict[str, float]]:
    """The contexts episodes cycle through: [] = a uniform draw per reset. ConfigError for a
    malformed or out-of-table fixed context, naming the allowed values."""
    spec = TASKS[task]
    if fixed.strip():
        try:
            pairs = [item.split("=", 1) for item in fixed.replace(" ", "").split(",") if item]
            context = {k: float(v) for k, v in pairs}
        except ValueError:
            raise ConfigError(f"parameter context: {fixed!r} is not like 'm=0.2,d=1.5'") from None
        try:
            return [spec.validate(context, split)]
        except ValueError as e:
            raise ConfigError(f"parameter context: {e}") from None
    return spec.contexts(split) if schedule == "cycle" else []


MODES = ("lockstep", "realtime")
ACTION_INPUTS = ("joint_state", "float64_multi_array")

PARAMS: tuple[Param, ...] = (
    Param("task", "pendulum_swingup", "Context-randomized DMC task (sim_bridge.contract.contexts.TASKS).",
          choices=tuple(sorted(TASKS))),
    Param("split", "train", "Context split drawn at each reset: train (C_train) or test (C_test).",
          choices=("train", "test")),
    Param("context_schedule", "sample", "How each reset picks its context from the split: "
          "sample = uniform draw (training, the paper's protocol); cycle = the split's grid in "
          "order, episode i gets context i mod n (evaluation: max_episodes = E * n gives exactly "
          "E episodes per context).", choices=("sample", "cycle")),
    Param("context", "", "A fixed context for every episode, e.g. 'm=0.2,d=1.5' (values from "
          "the split's table); empty = context_schedule decides."),
    Param("seed", 0, "Seeds the context draws and dm_control's initial states: a lock-step run "
          "is reproducible given the seed.", range=(0, 2**31 - 1)),
    Param("mode", "lockstep", "lockstep: each step waits for the action answering it; "
          "realtime: steps at control_rate_hz holding the latest action.", choices=MODES),
    Param("control_rate_hz", 0.0, "Real-time mode: agent steps per wall-clock second; 0 = the "
          "task's own rate 1/control_dt (real-time factor 1). Unused in lock-step.",
          read_only=False, range=(0.0, 1000.0), units="Hz"),
    Param("render_quality", "fast", "fast: no shadows/reflections/MSAA, 64x64 framebuffer "
          "(about 4x faster); default: the suite's look.", choices=("fast", "default")),
    Param("image_size", 64, "Image height and width (the model expects 64).", range=(16, 512),
          units="px"),
    Param("action_repeat", 2, "Physics control steps per agent step (the action is repeated).",
          range=(1, 100)),
    Param("episode_length", 500, "Agent steps per episode before the time limit ends it "
          "(time_limit = episode_length * action_repeat env steps; 500 = DMC's 1000 env steps).",
          range=(1, 1_000_000), units="agent steps"),
    Param("lockstep_timeout_s", 5.0, "Lock-step: with a policy matched and no valid answer "
          "after this long, the same observation is published again (counted in "
          "lockstep_timeouts).", read_only=False, range=(0.01, 3600.0), units="s"),
    Param("lossless", True, "Lock-step: image, step_info and context keep every sample a "
          "reliable reader has not acknowledged (KEEP_ALL history): a stalled reader, e.g. a "
          "frozen recorder, costs the bridge memory (about 14 KB per 64x64 step, until it catches "
          "up or its process is gone) instead of losing steps. false = KEEP_LAST(100), as in "
          "real time, where a reader more than 100 steps behind loses the oldest (counted by the "
          "recorder). Unused in real time.", read_only=True),
    Param("first_action_publisher_only", False, "Take actions only from the first action "
          "publisher (the one that answered while it was the only one matched); actions of any "
          "other are rejected (rejected_other_publisher) until no publisher is matched. Detection, "
          "not authentication: publishers are told apart by their sample sequence numbers "
          "(rclpy gives no publisher id), which another publisher could continue by chance "
          "or on purpose. false: every publisher's actions are taken; a second publisher is "
          "still reported (multiple_publishers).", read_only=True),
    Param("max_episodes", 0, "Exit (code 0) after this many complete episodes (lock-step: once "
          "the answer to the last is_last has arrived); 0 = run until stopped. Read-only: set at "
          "start, so nobody on the domain can end a running bridge with it.", read_only=True,
          range=(0, 1_000_000_000)),
    Param("min_subscribers", 1, "Readers that must be matched on image and on step_info before "
          "the first observation is published (e.g. 2 = policy + recorder); readers already "
          "visible in the graph on image/step_info/context are awaited too (up to 2 s).",
          range=(0, 1000)),
    Param("clock_topic", "", "Where sim time goes: empty = /clock for a bridge in the default "
          "namespace (/protocad), NS/clock for one elsewhere (-r __ns:=/robot1 -> /robot1/clock), so "
          "two bridges' clocks never interleave on one topic; or a name of your choice, e.g. /clock.",
          read_only=True),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics.", range=(0.05, 3600.0),
          units="s"),
    Param("reset_service", True, "Serve the reset service (reset: end the episode, start a "
          "new one). false: the service is not created, so nobody on the domain can cut "
          "episodes short. Off in protocad-fleet.", read_only=True),
    # A real camera's frame (issue 53): the policy's camera input exercised without a robot.
    Param("camera_height", 0, "Height of the published frame; 0 = image_size (the square "
          "render, unchanged). Rendered by the same camera: the centered square of a wider "
          "frame shows what the square render shows.", range=(0, 4096), units="px"),
    Param("camera_width", 0, "Width of the published frame; 0 = image_size.", range=(0, 4096),
          units="px"),
    Param("camera_encoding", "rgb8", "Raw transport: the Image encoding published.",
          choices=("rgb8", "bgr8", "rgba8", "bgra8", "mono8")),
    Param("camera_transport", "raw", "raw: sensor_msgs/Image on image; compressed: "
          "sensor_msgs/CompressedImage on image/compressed (image_transport's name), "
          "camera_format encoded.", choices=("raw", "compressed")),
    Param("camera_format", "jpeg", "Compressed transport: jpeg or png.", choices=("jpeg", "png")),
    Param("jpeg_quality", 90, "Compressed transport, jpeg: the encoder's quality.",
          range=(1, 100)),
    # A robot's command interface (issue 53): the policy node's Float64MultiArray output.
    Param("action_input", "joint_state", "joint_state: actions on action (the contract); "
          "float64_multi_array: std_msgs/Float64MultiArray commands on command_topic in the "
          "robot's joint order and units, turned into actions through command_map (adapter "
          "mode).", choices=ACTION_INPUTS),
    Param("command_topic", "commands", "Adapter mode: where commands arrive (e.g. "
          "/forward_position_controller/commands)."),
    Param("command_map", "", "Adapter mode: the joint map YAML the policy node loads "
          "(msgs_docs/robot.md); empty = the task's actuators in order, scale 1, offset 0."),
    autostart_param(),
    remote_lifecycle_param(),
    strict_param(),
    executor_param(),
)

ACTION_LOW, ACTION_HIGH = -1.0, 1.0
#: Longest wait, once min_subscribers are matched, for readers already in the graph to match.
READY_GRACE_S = 2.0
#: Longest wait at shutdown for reliable readers to acknowledge the last observations. Above
#: Fast DDS's heartbeat period (3 s): a sample a lagging reader missed is repaired only after the
#: writer's next heartbeat, and a reader still catching up (a recorder after a stall) loses what
#: the writer takes away by exiting, a loss no sequence gap after it can reveal.
FLUSH_TIMEOUT_S = 5.0
#: The same wait in lossless lock-step: long enough for a recorder that was stalled to catch up.
LOSSLESS_FLUSH_TIMEOUT_S = 30.0
#: Counters reported on /diagnostics (all cumulative since start).
COUNTERS = ("steps", "episodes", "observations_published", "observations_republished",
            "actions_received", "actions_accepted", "actions_rejected", "rejected_malformed",
            "rejected_wrong_length", "rejected_nonfinite", "rejected_stale_stamp",
            "rejected_duplicate", "actions_clipped", "late_actions", "lockstep_timeouts",
            "realtime_overruns", "resets_requested", "unknown_parameters",
            "parameters_rejected", "actions_while_inactive", "rejected_other_publisher",
            "multiple_publishers_detected", "publish_waits", "remote_transitions_refused",
            "commands_unsolicited")
