"""`ros2 run trainer record`: record ROS 2 topics into a rosbag2-compatible MCAP bag.

A minimal `ros2 bag record --storage mcap` for environments without rosbag2 (msgs_docs/
recorder.md): it subscribes with raw=True (the CDR bytes go to the bag untouched), takes
log_time = reception time (never going back within the bag) and publish_time = source time
from the rmw message info, waits for
topics that appear late (graph polling), stores the publishers' offered QoS and type hash in the
channel metadata, and closes the bag cleanly (footer, summary, metadata.yaml) on SIGINT/SIGTERM.
After a SIGKILL every chunk already written (chunk_size bytes, or flush_interval seconds) can be
read back with trainer.bag.reader.BagReader.

Usage: python -m trainer.nodes.recorder -o BAG [--topics T ...] [--namespace /protocad] ...
       ros2 run trainer record --ros-args -p output:=BAG -p compression:=lz4

Its parts, each a class named like its module and held in the node's attribute of that name:
recorder_topics.py (RecorderTopics: which topics; discovery; subscriptions and their QoS),
recorder_loss.py (RecorderLoss: sequence gaps, stalls past the DDS lease),
recorder_announcements.py (RecorderAnnouncements: bridge_info only from its bridge),
recorder_writing.py (RecorderWriting: writing, draining, closing), recorder_guard.py
(RecorderGuard, over record_budget.py: the disk budget). recorder_params.py holds the node's
parameters, recorder_cli.py the command line, generated from them. Here: the node, which holds
what its parts share (the parameters, the bag writer, the lock, the end of the recording and its
exit code, the /diagnostics publisher), builds the parts and closes them; and the entry point.
"""
from __future__ import annotations

import argparse
import math
import sys
import threading
from typing import Any, Mapping, Sequence

import rclpy.logging
from diagnostic_msgs.msg import DiagnosticArray

from sim_bridge.contract import topics as T
from sim_bridge.contract.qos import diagnostics_qos
from sim_bridge.nodekit.fastdds_profile import announced_lease, participant_lease
from sim_bridge.nodekit.param_table import ConfigError, with_defaults
from sim_bridge.nodekit.rosbase import ProtocadNode
from sim_bridge.nodekit.rosnode import KeyThrottle, declare_all, run_node
from trainer.bag.writer import BagWriteError
from trainer.nodes.record_budget import RecordBudget
from trainer.nodes.recorder_announcements import RecorderAnnouncements

# UNSUPPORTED_OPTIONS and the exit codes are imported from here (tests, msgs_docs/recorder.md).
from trainer.nodes.recorder_cli import (  # noqa: F401
    STORAGE_PRESETS,
    UNSUPPORTED_OPTIONS,
    build_parser,
    load_qos_overrides,
    parse_custom_data,
)
from trainer.nodes.recorder_guard import EXIT_BUDGET, RecorderGuard, budget_from_params  # noqa: F401
from trainer.nodes.recorder_loss import RecorderLoss
from trainer.nodes.recorder_params import PARAMS
from trainer.nodes.recorder_topics import (  # noqa: F401
    DEFAULT_QUEUE_DEPTH,
    EXIT_TYPE_MISMATCH,
    RecorderTopics,
    TopicSelection,
    history_name,
)
from trainer.nodes.recorder_writing import (  # noqa: F401
    DRAIN_LIMIT_S,
    EXIT_WRITE_FAILED,
    RecorderWriting,
    default_output,
    open_bag,
)


class RecorderNode(ProtocadNode):
    """Records topics into a BagWriter. Its ROS parameters are the table recorder_params.PARAMS,
    declared with `values` (the command line's) as their defaults: a --ros-args -p override
    wins; the per-topic lists (rate_limits, byte_budgets, byte_rate_limits, message_limits:
    TOPIC=NUMBER) are over the contract topics' defaults (record_budget.contract_bounds).
    `qos_overrides` ({topic: policies}) and `custom_data` are constructor-only (the command
    line's YAML file and KEY=VALUE list)."""

    #: run_node's bound on the close: the drain of a backlog, then closing the bag.
    shutdown_budget_s = DRAIN_LIMIT_S + 10.0

    def __init__(self, values: Mapping[str, Any] | None = None, *,
                 qos_overrides: Mapping[str, Mapping[str, Any]] | None = None,
                 custom_data: Mapping[str, str] | None = None, node_name: str = "recorder", **node_kwargs: Any):
        super().__init__(node_name, **node_kwargs)
        values = {k: v for k, v in (values or {}).items() if v is not None}
        values["output"] = values.get("output") or default_output()
        p = self.params = declare_all(self, with_defaults(PARAMS, values))
        budget = budget_from_params(p, self.resolve_topic_name)
        for off in budget.limits.turned_off():
            self.get_logger().warning(f"{off} turned off (0): a flood on it is not bounded (msgs_docs/recorder.md)")
        #: Why the recording ended by itself (the budget, a topic of another type), or None.
        self.stop_reason: str | None = None
        self.done = threading.Event()    # set when recording cannot go on (run_node then closes)
        self.exit_code = 0
        selection = TopicSelection(p, self.resolve_topic_name, qos_overrides)   # before the bag: a bad regex leaves no bag behind
        self.writer = open_bag(p, custom_data)
        # Where a flood is reported; made now, so readers have matched it when one comes.
        self._diag_pub = self.create_publisher(DiagnosticArray, T.DIAGNOSTICS, diagnostics_qos())
        self._warned: set[str] = set()
        self._throttle = KeyThrottle(self.get_logger())
        self._lock = threading.Lock()
        self._build_parts(budget, selection)
        self.recorder_topics.start()
        self.recorder_writing.start()
        self.get_logger().info(
            f"recording {selection.text()} to {self.writer.bag_dir} (compression {p['compression']}, "
            f"chunk {p['chunk_size']} B, split size {p['max_bagfile_size']} B / duration "
            f"{p['max_bagfile_duration']} s, {history_name(p['queue_depth'])})")

    def _build_parts(self, budget: RecordBudget, selection: TopicSelection) -> None:
        """The parts, each handed what it needs (the recorder's parts are described in the module docstring)."""
        shared = dict(node=self, writer=self.writer, lock=self._lock)
        self.recorder_guard = RecorderGuard(
            node=self, budget=budget, writer=self.writer, min_free_disk=self.params["min_free_disk"],
            diag_pub=self._diag_pub, done=self.done, stop=self.stop, warn_once=self._warn_once,
            warn_throttled=self._throttle.warning)
        self.recorder_loss = RecorderLoss(node=self, lock=self._lock, warn_once=self._warn_once,
                                          warn_throttled=self._throttle.warning)
        self.recorder_writing = RecorderWriting(
            **shared, params=self.params, done=self.done, stop=self.stop, warn_once=self._warn_once,
            account=self.recorder_loss.account, within_budget=self.recorder_guard.within_budget)
        self.recorder_announcements = RecorderAnnouncements(
            **shared, on_message=self.recorder_writing.on_message, warn_once=self._warn_once)
        self.recorder_topics = RecorderTopics(
            **shared, params=self.params, selection=selection, done=self.done, stop=self.stop,
            warn_once=self._warn_once, on_message=self.recorder_writing.on_message,
            filter_announcements=self.recorder_announcements.filter,
            on_announcement_heard=self.recorder_announcements.heard)

    def stop(self, exit_code: int, reason: str | None = None) -> None:
        """End the recording (run_node then closes the bag) with `exit_code`; `reason`, when
        given, goes into the bag's metadata and the summary."""
        if reason is not None:
            self.stop_reason = reason
        self.exit_code = exit_code
        self.done.set()

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    def close(self) -> dict[str, int]:
        """Take what the middleware still holds (when stopped by a signal, not by the recording's
        own end), close the bag (footer, summary, metadata.yaml with the loss and the marks),
        print the summary; returns the per-topic counts."""
        self.recorder_writing.drain_held()
        self.recorder_announcements.stop()   # held announcements: the bridge's written, others left out
        self.recorder_loss.stop()
        self.recorder_writing.close(self._marks)
        print(self.summary(), flush=True)
        return self.writer.topic_counts

    def _marks(self) -> dict[str, str]:
        """What the bag's metadata says beside the counts (custom_data)."""
        marks = {**self.recorder_loss.metadata(), **self.recorder_topics.publishers_summary(),
                 **self.recorder_guard.metadata()}
        if self.stop_reason:
            marks["protocad_recording_stopped"] = self.stop_reason
        return marks

    def summary(self) -> str:
        """What was recorded and what was lost, for the exit message."""
        lines = self.recorder_writing.recorded_lines() + self.recorder_loss.summary_lines() \
            + self.recorder_guard.summary_lines()
        if self.stop_reason:
            lines.append(f"  RECORDING STOPPED: {self.stop_reason}")
        lines += self.recorder_announcements.summary_lines() + self.recorder_topics.summary_lines() \
            + self.recorder_writing.failure_lines()
        return "\n".join(lines)


def start_recorder(args: argparse.Namespace) -> RecorderNode:
    """The RecorderNode the parsed command line asks for (ConfigError: bad options, exit 2)."""
    rclpy.logging.set_logger_level(args.node_name, getattr(rclpy.logging.LoggingSeverity, args.log_level.upper()))
    try:
        compression = args.compression or STORAGE_PRESETS.get(args.storage_preset_profile or "none", "zstd")
        qos_overrides = load_qos_overrides(args.qos_profile_overrides_path) \
            if args.qos_profile_overrides_path else None
        values = {p.name: getattr(args, p.name) for p in PARAMS if hasattr(args, p.name)}
        values.update(topics=[*args.topics, *args.topics_opt], compression=compression,
                      discovery_interval=args.polling_interval / 1000.0)
        with participant_lease(args.lease_duration) as lease_profile:
            node = RecorderNode(values, qos_overrides=qos_overrides, custom_data=parse_custom_data(args.custom_data),
                                node_name=args.node_name)
    except (BagWriteError, ValueError) as exc:
        raise ConfigError(str(exc)) from None
    if lease_profile is not None:   # not with another rmw, nor with 0 (the profile's own)
        node.get_logger().info(f"DDS lease {args.lease_duration:g} s: a stall shorter than that loses nothing")
    lease = announced_lease(args.lease_duration)
    if lease is not None and math.isfinite(lease):
        node.recorder_loss.watch_stalls(lease)
    print(f"recorder: recording to {node.writer.bag_dir}", flush=True)
    return node


def main(argv: Sequence[str] | None = None) -> int:
    """`ros2 bag record`'s command line (argv without the program name)."""
    return run_node(start_recorder, prog="recorder", parser=build_parser(),
                    argv=[sys.argv[0], *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
