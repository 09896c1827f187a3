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

Its parts: recorder_topics.py (which topics; discovery; subscriptions and their QoS),
recorder_loss.py (sequence gaps, stalls past the DDS lease), recorder_announcements.py
(bridge_info only from its bridge), recorder_writing.py (writing,
draining, closing), recorder_guard.py over record_budget.py (the disk budget), recorder_params.py
(the node's parameters), recorder_cli.py (the command line, generated from them). Here: the
node's wiring and the entry point.
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
from sim_bridge.nodekit.publisher_watch import PublisherWatch
from sim_bridge.nodekit.rosbase import ProtocadNode
from sim_bridge.nodekit.rosnode import ConfigError, KeyThrottle, declare_all, run_node, with_defaults
from trainer.bag.writer import BagWriteError
from trainer.nodes.record_budget import BudgetLimits, DiskFloor, RecordBudget, parse_topic_values
from trainer.nodes.recorder_announcements import AnnouncementFilter

# UNSUPPORTED_OPTIONS and the exit codes are imported from here (tests, msgs_docs/recorder.md).
from trainer.nodes.recorder_cli import (  # noqa: F401
    STORAGE_PRESETS,
    UNSUPPORTED_OPTIONS,
    build_parser,
    load_qos_overrides,
    parse_custom_data,
)
from trainer.nodes.recorder_guard import EXIT_BUDGET, RecorderGuard  # noqa: F401
from trainer.nodes.recorder_loss import LossAccounting
from trainer.nodes.recorder_params import PARAMS
from trainer.nodes.recorder_topics import DEFAULT_QUEUE_DEPTH, EXIT_TYPE_MISMATCH, TopicSubscriber, history_name  # noqa: F401
from trainer.nodes.recorder_writing import DRAIN_LIMIT_S, EXIT_WRITE_FAILED, BagWriting, default_output  # noqa: F401


class RecorderNode(TopicSubscriber, AnnouncementFilter, LossAccounting, BagWriting, RecorderGuard, ProtocadNode):
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

        def per_topic(key: str) -> dict[str, float]:
            return {self.resolve_topic_name(t): v for t, v in parse_topic_values(p[key], key).items()}

        self.budget = RecordBudget(BudgetLimits(
            max_topic_rate=p["max_topic_rate"], max_topic_bytes=p["max_topic_bytes"],
            max_total_bytes=p["max_total_bytes"], flood_factor=p["flood_factor"],
            rates=per_topic("rate_limits"), topic_bytes=per_topic("byte_budgets"),
            byte_rates=per_topic("byte_rate_limits"), message_bytes=per_topic("message_limits"),
            namespace=p["namespace"]))
        for off in self.budget.limits.turned_off():
            self.get_logger().warning(f"{off} turned off (0): a flood on it is not bounded (msgs_docs/recorder.md)")
        self.stop_reason: str | None = None
        self._select_topics(p, qos_overrides)   # before the bag: a bad regex leaves no bag behind
        self._start_announcement_filter()
        self._open_bag(p, custom_data)
        self.disk_floor = DiskFloor(self.writer.bag_dir, p["min_free_disk"])
        # Where a flood is reported; made now, so readers have matched it when one comes.

        self._diag_pub = self.create_publisher(DiagnosticArray, T.DIAGNOSTICS, diagnostics_qos())
        self._flood_timer = None
        self._start_loss_accounting()
        # A recorded topic with several writers mixes their samples in the bag (an impostor, a
        # second bridge): marked in the bag's metadata as soon as it is seen.
        self.publisher_watch = PublisherWatch(self._on_new_publisher)
        self._warned: set[str] = set()
        self._throttle = KeyThrottle(self.get_logger())
        self._lock = threading.Lock()
        self._discover()
        if not p["no_discovery"]:
            self._discovery_timer = self.create_timer(p["discovery_interval"], self._discover)
        if p["flush_interval"] > 0:
            self._flush_timer = self.create_timer(p["flush_interval"], self._flush_if_due)
        if p["status_interval"] > 0:
            self._status_timer = self.create_timer(p["status_interval"], self._status)
        self.get_logger().info(
            f"recording {self._selection_text()} to {self.writer.bag_dir} (compression {p['compression']}, "
            f"chunk {p['chunk_size']} B, split size {p['max_bagfile_size']} B / duration "
            f"{p['max_bagfile_duration']} s, {history_name(p['queue_depth'])})")

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)


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
        node.watch_stalls(lease)
    print(f"recorder: recording to {node.writer.bag_dir}", flush=True)
    return node


def main(argv: Sequence[str] | None = None) -> int:
    """`ros2 bag record`'s command line (argv without the program name)."""
    return run_node(start_recorder, prog="recorder", parser=build_parser(),
                    argv=[sys.argv[0], *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
