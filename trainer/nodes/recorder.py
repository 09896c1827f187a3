"""`ros2 run trainer record`: record ROS 2 topics into a rosbag2-compatible MCAP bag.

A minimal `ros2 bag record --storage mcap` for environments without rosbag2 (msgs_docs/
recorder.md): it subscribes with raw=True (the CDR bytes go to the bag untouched), takes
log_time = reception time (never going back within the bag) and publish_time = source time
from the rmw message info, waits for
topics that appear late (graph polling), stores the publishers' offered QoS and type hash in the
channel metadata, and closes the bag cleanly (footer, summary, metadata.yaml) on SIGINT/SIGTERM.
After a SIGKILL every chunk already written (chunk_size bytes, or flush_interval seconds) can be
read back with trainer.bag.mcap_io.BagReader.

Usage: python -m trainer.nodes.recorder -o BAG [--topics T ...] [--namespace /protocad] ...
       ros2 run trainer record --ros-args -p output:=BAG -p compression:=lz4
"""
from __future__ import annotations

import argparse
import math
import sys
import threading
from typing import Any, Mapping, Sequence

from sim_bridge.nodekit.fastdds_profile import announced_lease, participant_lease
from sim_bridge.nodekit.publisher_watch import PublisherWatch
from sim_bridge.nodekit.rosbase import ProtocadNode
from sim_bridge.nodekit.rosnode import ConfigError, KeyThrottle, run_node

from sim_bridge.contract import topics as T
from trainer.bag import mcap_io
from trainer.nodes.record_budget import (DEFAULT_FLOOD_FACTOR, DEFAULT_MIN_FREE_DISK, BudgetLimits, DiskFloor,
                                         RecordBudget, parse_topic_values)
from trainer.nodes.recorder_guard import EXIT_BUDGET, RecorderGuard, add_budget_options  # noqa: F401 - EXIT_BUDGET: beside EXIT_WRITE_FAILED
from trainer.nodes.recorder_loss import DEFAULT_LEASE_S, LossAccounting
from trainer.nodes.recorder_topics import DEFAULT_QUEUE_DEPTH, TopicSubscriber, history_name
from trainer.nodes.recorder_writing import DRAIN_LIMIT_S, EXIT_WRITE_FAILED, BagWriting, default_output  # noqa: F401 - EXIT_WRITE_FAILED: imported from here


class RecorderNode(TopicSubscriber, LossAccounting, BagWriting, RecorderGuard, ProtocadNode):
    """Records topics into a BagWriter. Every constructor argument is also a ROS parameter of
    the same name (a --ros-args -p override wins): output, topics, namespace, all_topics,
    regex (include), exclude_regex, exclude_topics, include_hidden_topics, no_discovery,
    compression, chunk_size, max_bagfile_size, max_bagfile_duration, flush_interval,
    queue_depth, discovery_interval, status_interval, and the disk budget's (trainer/nodes/
    record_budget.py) max_topic_rate, max_topic_bytes, max_total_bytes, min_free_disk,
    flood_factor, rate_limits and byte_budgets (TOPIC=NUMBER lists). `qos_overrides` ({topic: policies}) and
    `custom_data` are constructor-only (the command line's YAML file and KEY=VALUE list)."""

    #: run_node's bound on the close: the drain of a backlog, then closing the bag.
    shutdown_budget_s = DRAIN_LIMIT_S + 10.0

    def __init__(self, output: str | None = None, topics: Sequence[str] = (),
                 namespace: str = T.DEFAULT_NAMESPACE, all_topics: bool = False,
                 exclude_regex: str = "", compression: str = "zstd", regex: str = "",
                 exclude_topics: Sequence[str] = (), include_hidden_topics: bool = False,
                 no_discovery: bool = False, qos_overrides: Mapping[str, Mapping[str, Any]] | None = None,
                 custom_data: Mapping[str, str] | None = None,
                 chunk_size: int = mcap_io.DEFAULT_CHUNK_SIZE, max_bagfile_size: int = 0,
                 max_bagfile_duration: float = 0.0, flush_interval: float = 1.0,
                 queue_depth: int = DEFAULT_QUEUE_DEPTH, discovery_interval: float = 0.2,
                 status_interval: float = 0.0, max_topic_rate: float = 0.0, max_topic_bytes: int = 0,
                 max_total_bytes: int = 0, min_free_disk: int = DEFAULT_MIN_FREE_DISK,
                 flood_factor: float = DEFAULT_FLOOD_FACTOR, rate_limits: Sequence[str] = (),
                 byte_budgets: Sequence[str] = (), node_name: str = "recorder", **node_kwargs: Any):
        super().__init__(node_name, **node_kwargs)
        from rcl_interfaces.msg import ParameterDescriptor, ParameterType
        p = {}
        for key, default in (("output", output or default_output()), ("namespace", namespace),
                             ("all_topics", bool(all_topics)), ("exclude_regex", exclude_regex),
                             ("regex", regex), ("include_hidden_topics", bool(include_hidden_topics)),
                             ("no_discovery", bool(no_discovery)),
                             ("compression", compression), ("chunk_size", int(chunk_size)),
                             ("max_bagfile_size", int(max_bagfile_size)),
                             ("max_bagfile_duration", float(max_bagfile_duration)),
                             ("flush_interval", float(flush_interval)),
                             ("queue_depth", int(queue_depth)),
                             ("discovery_interval", float(discovery_interval)),
                             ("status_interval", float(status_interval)),
                             ("max_topic_rate", float(max_topic_rate)), ("max_topic_bytes", int(max_topic_bytes)),
                             ("max_total_bytes", int(max_total_bytes)), ("min_free_disk", int(min_free_disk)),
                             ("flood_factor", float(flood_factor))):
            p[key] = self.declare_parameter(key, default).value
        p["topics"] = list(self.declare_parameter(
            "topics", list(topics), ParameterDescriptor(
                type=ParameterType.PARAMETER_STRING_ARRAY,
                description="topics to record (empty: the contract topics in `namespace` "
                            "and /clock)")).value or [])
        p["exclude_topics"] = list(self.declare_parameter(
            "exclude_topics", list(exclude_topics), ParameterDescriptor(
                type=ParameterType.PARAMETER_STRING_ARRAY,
                description="topics not to record")).value or [])
        for key, items, what in (("rate_limits", rate_limits, "TOPIC=HZ: a rate limit of its own"),
                                 ("byte_budgets", byte_budgets, "TOPIC=BYTES: a byte budget of its own")):
            p[key] = list(self.declare_parameter(key, list(items), ParameterDescriptor(
                type=ParameterType.PARAMETER_STRING_ARRAY, description=what)).value or [])
        self.params = p
        self.budget = RecordBudget(BudgetLimits(
            max_topic_rate=p["max_topic_rate"], max_topic_bytes=p["max_topic_bytes"],
            max_total_bytes=p["max_total_bytes"], flood_factor=p["flood_factor"],
            rates={self.resolve_topic_name(t): v for t, v in parse_topic_values(p["rate_limits"], "rate_limits").items()},
            topic_bytes={self.resolve_topic_name(t): v
                         for t, v in parse_topic_values(p["byte_budgets"], "byte_budgets").items()}))
        self.stop_reason: str | None = None
        self._select_topics(p, qos_overrides)   # before the bag: a bad regex leaves no bag behind
        self._open_bag(p, custom_data)
        self.disk_floor = DiskFloor(self.writer.bag_dir, p["min_free_disk"])
        # Where a flood is reported; made now, so readers have matched it when one comes.
        from diagnostic_msgs.msg import DiagnosticArray

        from sim_bridge.contract.qos import diagnostics_qos
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


#: `ros2 bag record` (Jazzy) options this recorder does not have, and why (each is refused
#: with that reason rather than silently ignored).
UNSUPPORTED_OPTIONS: dict[str, str] = {
    "--services": "service recording (service event topics) is not supported",
    "--all-services": "service recording (service event topics) is not supported",
    "--exclude-services": "service recording (service event topics) is not supported",
    "--topic-types": "selecting topics by type is not supported: name them, or use --regex",
    "--exclude-topic-types": "excluding topics by type is not supported: use --exclude-regex",
    "--include-unpublished-topics": "a topic is recorded once a publisher offers its QoS (as the "
                                    "default ros2 bag record does)",
    "--ignore-leaf-topics": "not supported",
    "--use-sim-time": "messages are stamped with receive and source times, never /clock",
    "--snapshot-mode": "snapshot mode is not supported",
    "--start-paused": "pausing is not supported",
    "--max-cache-size": "there is no write cache: each message is handed to the MCAP writer "
                        "as it arrives (chunking is --chunk-size)",
    "--compression-mode": "rosbag2's file/message compression is not supported: MCAP chunks are "
                          "compressed instead (--compression zstd|lz4|none, "
                          "or --storage-preset-profile)",
    "--compression-format": "see --compression-mode",
    "--compression-queue-size": "see --compression-mode",
    "--compression-threads": "see --compression-mode",
    "--storage-config-file": "MCAP writer options are --chunk-size and --compression",
    "--static-topics-path": "not supported",
}
#: MCAP storage presets of rosbag2 (`--storage-preset-profile`) as our chunk compression.
STORAGE_PRESETS = {"none": "zstd", "fastwrite": "none", "zstd_fast": "zstd", "zstd_small": "zstd"}


class _Unsupported(argparse.Action):
    def __init__(self, option_strings, dest, **kw):
        kw.setdefault("nargs", "*")
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string}: {UNSUPPORTED_OPTIONS[option_string]} (this recorder follows "
                     "`ros2 bag record` of Jazzy for the options it has)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="ros2 run trainer record",
        description="Record ROS 2 topics into a rosbag2-compatible MCAP bag directory "
                    "(NAME/NAME_0.mcap ... + metadata.yaml). Options follow `ros2 bag record` of "
                    "Jazzy (same names, same meanings: -e/--regex includes, --exclude-regex "
                    "excludes); its options this recorder lacks are refused with the reason. Every "
                    "option is also a ROS parameter (--ros-args -p name:=value), except "
                    "--lease-duration (needed before the node exists). SIGINT/SIGTERM close "
                    "the bag cleanly; a write error (disk full) closes it and exits 3.",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", default=None,
                    help="bag directory to create (default: rosbag2_YYYY_MM_DD-HH_MM_SS)")
    ap.add_argument("-s", "--storage", default="mcap", choices=("mcap",),
                    help="storage identifier (only mcap; default mcap)")
    ap.add_argument("topics", nargs="*", default=[],
                    help="topics to record (default, with no topic, -a or -e: the contract topics "
                         "image, step_info, context, action, context_features in --namespace, and /clock)")
    ap.add_argument("--topics", dest="topics_opt", nargs="+", default=[], metavar="TOPIC",
                    help="space-delimited list of topics to record (as the positional ones)")
    ap.add_argument("-a", "--all", dest="all_topics", action="store_true",
                    help="record every topic (hidden ones excluded)")
    ap.add_argument("--all-topics", dest="all_topics", action="store_true", help="same as -a")
    ap.add_argument("-e", "--regex", default="",
                    help="record only topics matching this regular expression (re.search); "
                         "-a overrides it")
    ap.add_argument("--exclude-regex", default="",
                    help="do not record topics matching this regular expression; works on top of "
                         "-a, --topics and -e")
    ap.add_argument("--exclude-topics", nargs="+", default=[], metavar="TOPIC",
                    help="topics not to record; works on top of -a, --topics and -e")
    ap.add_argument("--include-hidden-topics", action="store_true",
                    help="with -a or -e: hidden topics too")
    ap.add_argument("--no-discovery", action="store_true",
                    help="record only topics present at start-up")
    ap.add_argument("-p", "--polling-interval", type=int, default=200, metavar="MS",
                    help="milliseconds between graph polls for topics that appear late (default 200)")
    ap.add_argument("--qos-profile-overrides-path", type=argparse.FileType("r"), default=None,
                    metavar="YAML", help="QoS for specific topics, as ros2 bag record: "
                    "{/topic: {reliability: reliable|best_effort, durability: volatile|transient_local, "
                    "history: keep_last|keep_all, depth: N}}")
    ap.add_argument("-f", "--serialization-format", default="cdr", choices=("cdr",),
                    help="serialization format (only cdr, what every rmw here uses)")
    ap.add_argument("-b", "--max-bag-size", dest="max_bagfile_size", type=int, default=0,
                    help="split the bag at this file size in bytes (0: no split; >= 1024)")
    ap.add_argument("-d", "--max-bag-duration", dest="max_bagfile_duration", type=float,
                    default=0.0, help="split the bag after this many seconds (0: no split)")
    ap.add_argument("--storage-preset-profile", choices=sorted(STORAGE_PRESETS), default=None,
                    help="rosbag2's MCAP presets, as chunk compression: fastwrite = none, "
                         "zstd_fast / zstd_small / none = zstd")
    ap.add_argument("--custom-data", nargs="*", default=[], metavar="KEY=VALUE",
                    help="stored under custom_data in metadata.yaml (as ros2 bag record)")
    ap.add_argument("--node-name", default="recorder", help="ROS node name (default recorder)")
    ap.add_argument("--log-level", choices=("debug", "info", "warn", "error", "fatal"), default="info")
    ap.add_argument("--disable-keyboard-controls", action="store_true",
                    help="accepted for compatibility: this recorder has no keyboard controls")
    g = ap.add_argument_group("this recorder's own options")
    g.add_argument("--namespace", default=T.DEFAULT_NAMESPACE,
                   help="namespace of the default contract topics (default /protocad)")
    g.add_argument("--compression", choices=("zstd", "lz4", "none"), default=None,
                   help="MCAP chunk compression (default zstd)")
    g.add_argument("--chunk-size", type=int, default=mcap_io.DEFAULT_CHUNK_SIZE,
                   help=f"uncompressed chunk size in bytes (smaller: less lost on SIGKILL; default "
                        f"{mcap_io.DEFAULT_CHUNK_SIZE})")
    g.add_argument("--flush-interval", type=float, default=1.0,
                   help="write the open chunk at least every this many seconds (0: only by "
                        "size); bounds what a SIGKILL loses (default 1.0)")
    g.add_argument("--queue-depth", type=int, default=DEFAULT_QUEUE_DEPTH,
                   help="history of the subscriptions: 0 = KEEP_ALL (default: a backlog of any size "
                        "holds KEEP_ALL writers back instead of being dropped), N > 0 = KEEP_LAST(N) "
                        "(never holds a writer back; drops the oldest of a deeper backlog, counted)")
    g.add_argument("--status-interval", type=float, default=0.0,
                   help="log message counts every this many seconds (0: off)")
    g.add_argument("--lease-duration", type=float, default=DEFAULT_LEASE_S, metavar="S",
                   help="the DDS participant lease the recorder announces: a stall (SIGSTOP, a "
                        "debugger, an overloaded machine) shorter than this loses nothing, since "
                        "reliable KEEP_ALL writers (a lock-step bridge) keep what it has not "
                        "acknowledged (and pause after 5,000 samples); a longer one makes the "
                        "writers drop it and its backlog, which the recorder counts as LOST when "
                        "the next sample comes; the stall itself is reported (STALLED, metadata "
                        "protocad_stalls_past_lease). A recorder killed outright stays in the graph "
                        "this long. 0: Fast DDS's own (20 s, or the profile's). Command line "
                        f"only: it must be known before the node exists (default {DEFAULT_LEASE_S:g})")
    add_budget_options(ap)
    g = ap.add_argument_group("`ros2 bag record` options this recorder does not have (refused, "
                              "with the reason)")
    for opt in UNSUPPORTED_OPTIONS:
        g.add_argument(opt, action=_Unsupported, help=argparse.SUPPRESS)
    return ap


def parse_custom_data(items: Sequence[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--custom-data expects KEY=VALUE, got {item!r}")
        out[key] = value
    return out


def load_qos_overrides(stream: Any) -> dict[str, dict[str, Any]]:
    """The YAML of --qos-profile-overrides-path: {topic: {policy: value}} (ValueError if malformed)."""
    import yaml

    data = yaml.safe_load(stream) or {}
    if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
        raise ValueError("--qos-profile-overrides-path: expected a mapping of topic -> QoS policies")
    allowed = {"reliability", "durability", "history", "depth"}
    for topic, policies in data.items():
        bad = set(policies) - allowed
        if bad:
            raise ValueError(f"--qos-profile-overrides-path: {topic}: unknown policies {sorted(bad)}; "
                             f"supported: {sorted(allowed)}")
    return {str(k): dict(v) for k, v in data.items()}


def start_recorder(args: argparse.Namespace) -> RecorderNode:
    """The RecorderNode the parsed command line asks for (ConfigError: bad options, exit 2)."""
    import rclpy.logging

    rclpy.logging.set_logger_level(args.node_name, getattr(rclpy.logging.LoggingSeverity, args.log_level.upper()))
    try:
        compression = args.compression or STORAGE_PRESETS.get(args.storage_preset_profile or "none", "zstd")
        qos_overrides = load_qos_overrides(args.qos_profile_overrides_path) \
            if args.qos_profile_overrides_path else None
        with participant_lease(args.lease_duration) as lease_profile:
            node = RecorderNode(
                output=args.output, topics=[*args.topics, *args.topics_opt],
                namespace=args.namespace, all_topics=args.all_topics, regex=args.regex,
                exclude_regex=args.exclude_regex, exclude_topics=args.exclude_topics,
                include_hidden_topics=args.include_hidden_topics, no_discovery=args.no_discovery,
                qos_overrides=qos_overrides, custom_data=parse_custom_data(args.custom_data),
                compression=compression,
                chunk_size=args.chunk_size, max_bagfile_size=args.max_bagfile_size,
                max_bagfile_duration=args.max_bagfile_duration, flush_interval=args.flush_interval,
                queue_depth=args.queue_depth, discovery_interval=args.polling_interval / 1000.0,
                status_interval=args.status_interval, max_topic_rate=args.max_topic_rate,
                max_topic_bytes=args.max_topic_bytes, max_total_bytes=args.max_total_bytes,
                min_free_disk=args.min_free_disk, flood_factor=args.flood_factor,
                rate_limits=args.rate_limits, byte_budgets=args.byte_budgets, node_name=args.node_name)
    except (mcap_io.BagWriteError, ValueError) as exc:
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
