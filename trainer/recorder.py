"""`ros2 run trainer record`: record ROS 2 topics into a rosbag2-compatible MCAP bag.

A minimal `ros2 bag record --storage mcap` for environments without rosbag2 (msgs_docs/
recorder.md): it subscribes with raw=True (the CDR bytes go to the bag untouched), takes
log_time = reception time and publish_time = source time from the rmw message info, waits for
topics that appear late (graph polling), stores the publishers' offered QoS and type hash in the
channel metadata, and closes the bag cleanly (footer, summary, metadata.yaml) on SIGINT/SIGTERM.
After a SIGKILL every chunk already written (chunk_size bytes, or flush_interval seconds) can be
read back with trainer.mcap_io.BagReader.

Usage: python -m trainer.recorder -o BAG [--topics T ...] [--namespace /protocad] ...
       ros2 run trainer record --ros-args -p output:=BAG -p compression:=lz4
"""
from __future__ import annotations

import argparse
import functools
import importlib
import re
import signal
import sys
import threading
import time
from datetime import datetime
from typing import Any, Sequence

from sim_bridge.rosbase import ProtocadNode

from sim_bridge import topics as T
from trainer import mcap_io

#: Relative contract topics recorded by default (resolved in --namespace), plus /clock.
DEFAULT_RELATIVE_TOPICS = (T.IMAGE, T.STEP_INFO, T.CONTEXT, T.ACTION, T.CONTEXT_FEATURES)
DEFAULT_QUEUE_DEPTH = 1000


def default_topics(namespace: str = T.DEFAULT_NAMESPACE) -> list[str]:
    return [T.topic_name(namespace, t) for t in DEFAULT_RELATIVE_TOPICS] + [T.CLOCK]


def default_output() -> str:
    """rosbag2's default bag name: rosbag2_YYYY_MM_DD-HH_MM_SS."""
    return datetime.now().strftime("rosbag2_%Y_%m_%d-%H_%M_%S")


def qos_profile_to_dict(qos: Any) -> dict[str, Any]:
    """An rclpy QoSProfile as rosbag2 (metadata v9) serializes it."""
    def name(policy: Any) -> str:
        return policy.name.lower()   # keep_last, reliable, transient_local, automatic, unknown...

    return mcap_io.qos_profile(
        history=name(qos.history), depth=int(qos.depth), reliability=name(qos.reliability),
        durability=name(qos.durability), deadline_ns=qos.deadline.nanoseconds,
        lifespan_ns=qos.lifespan.nanoseconds, liveliness=name(qos.liveliness),
        liveliness_lease_duration_ns=qos.liveliness_lease_duration.nanoseconds,
        avoid_ros_namespace_conventions=bool(qos.avoid_ros_namespace_conventions))


def subscription_qos(offered: Sequence[Any], depth: int):
    """The QoS the recorder requests, adapted to the publishers' offers like rosbag2
    (Rosbag2QoS::adapt_request_to_offers) but with a deep history:

    * RELIABLE when every publisher is reliable (the protocad contract: a reliable reader never
      loses a sample the writer still holds), else BEST_EFFORT (a reliable reader would not
      match a best-effort writer at all);
    * TRANSIENT_LOCAL when every publisher offers it (latched data is recorded), else VOLATILE;
    * KEEP_LAST(depth) with depth >> 1 (default 1000): the reader keeps up to `depth` samples
      while the callback is busy (writing a chunk, compressing), so lock-step at full speed and
      bursts are lossless; KEEP_ALL is not used because a stalled recorder would then grow
      without bound (and, with reliable writers, eventually stall the publishers).
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    reliable = bool(offered) and all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    latched = bool(offered) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                    for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=int(depth),
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def _import_message(msgtype: str) -> Any:
    pkg, ns, name = mcap_io.normalize_type(msgtype).split("/")
    return getattr(importlib.import_module(f"{pkg}.{ns}"), name)


class RecorderNode(ProtocadNode):
    """Records topics into a BagWriter. Every constructor argument is also a ROS parameter of
    the same name (a --ros-args -p override wins): output, topics, namespace, all_topics,
    exclude_regex, compression, chunk_size, max_bagfile_size, max_bagfile_duration,
    flush_interval, queue_depth, discovery_interval, status_interval."""

    def __init__(self, output: str | None = None, topics: Sequence[str] = (),
                 namespace: str = T.DEFAULT_NAMESPACE, all_topics: bool = False,
                 exclude_regex: str = "", compression: str = "zstd",
                 chunk_size: int = mcap_io.DEFAULT_CHUNK_SIZE, max_bagfile_size: int = 0,
                 max_bagfile_duration: float = 0.0, flush_interval: float = 1.0,
                 queue_depth: int = DEFAULT_QUEUE_DEPTH, discovery_interval: float = 0.2,
                 status_interval: float = 0.0, node_name: str = "recorder", **node_kwargs: Any):
        super().__init__(node_name, **node_kwargs)
        from rcl_interfaces.msg import ParameterDescriptor, ParameterType
        p = {}
        for key, default in (("output", output or default_output()), ("namespace", namespace),
                             ("all_topics", bool(all_topics)), ("exclude_regex", exclude_regex),
                             ("compression", compression), ("chunk_size", int(chunk_size)),
                             ("max_bagfile_size", int(max_bagfile_size)),
                             ("max_bagfile_duration", float(max_bagfile_duration)),
                             ("flush_interval", float(flush_interval)),
                             ("queue_depth", int(queue_depth)),
                             ("discovery_interval", float(discovery_interval)),
                             ("status_interval", float(status_interval))):
            p[key] = self.declare_parameter(key, default).value
        p["topics"] = list(self.declare_parameter(
            "topics", list(topics), ParameterDescriptor(
                type=ParameterType.PARAMETER_STRING_ARRAY,
                description="topics to record (empty: the contract topics in `namespace` "
                            "and /clock)")).value or [])
        self.params = p
        self.wanted: list[str] = ([] if p["all_topics"] else
                                  [self.resolve_topic_name(t) for t in p["topics"]]
                                  or default_topics(p["namespace"]))
        self._exclude = re.compile(p["exclude_regex"]) if p["exclude_regex"] else None
        self.writer = mcap_io.BagWriter(
            p["output"], compression=p["compression"], chunk_size=p["chunk_size"],
            max_bagfile_size=p["max_bagfile_size"],
            max_bagfile_duration_s=p["max_bagfile_duration"],
            flush_interval_s=p["flush_interval"])
        self.received = 0
        self.errors = 0
        self.done = threading.Event()    # set when recording cannot go on (write failure)
        self.exit_code = 0
        self._subs: dict[str, Any] = {}
        self._warned: set[str] = set()
        self._lock = threading.Lock()
        self._discover()
        self._discovery_timer = self.create_timer(p["discovery_interval"], self._discover)
        if p["flush_interval"] > 0:
            self._flush_timer = self.create_timer(p["flush_interval"], self._flush_if_due)
        if p["status_interval"] > 0:
            self._status_timer = self.create_timer(p["status_interval"], self._status)
        what = "all topics" if p["all_topics"] else ", ".join(self.wanted)
        self.get_logger().info(
            f"recording {what} to {self.writer.bag_dir} (compression {p['compression']}, "
            f"chunk {p['chunk_size']} B, split size {p['max_bagfile_size']} B / duration "
            f"{p['max_bagfile_duration']} s, KEEP_LAST({p['queue_depth']}))")

    # -- discovery -----------------------------------------------------------------------------
    def _want(self, topic: str) -> bool:
        if self._exclude is not None and self._exclude.search(topic):
            return False
        if self.params["all_topics"]:
            from rclpy.topic_or_service_is_hidden import topic_or_service_is_hidden
            return not topic_or_service_is_hidden(topic)
        return topic in self.wanted

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    def _discover(self) -> None:
        if self.writer.closed:
            return
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subs or not self._want(topic):
                continue
            if len(types) != 1:
                self._warn_once(f"types:{topic}", f"topic {topic} has several types {types}; "
                                "not recorded (as rosbag2)")
                continue
            pubs = self.get_publishers_info_by_topic(topic)
            if not pubs:
                continue  # wait for a publisher: its offered QoS decides ours
            try:
                self._subscribe(topic, types[0], pubs)
            except Exception as exc:  # unknown type, import error...
                self._warn_once(f"sub:{topic}", f"cannot record {topic} [{types[0]}]: {exc}")

    def _subscribe(self, topic: str, msgtype: str, pubs: Sequence[Any]) -> None:
        msg_class = _import_message(msgtype)
        offered = [e.qos_profile for e in pubs]
        hashes = {str(e.topic_type_hash) for e in pubs} - {"INVALID"}
        type_hash = sorted(hashes)[0] if hashes else None
        self.writer.add_topic(topic, msgtype, [qos_profile_to_dict(q) for q in offered],
                              type_hash=type_hash)
        qos = subscription_qos(offered, self.params["queue_depth"])
        self._subs[topic] = self.create_subscription(
            msg_class, topic, functools.partial(self._on_message, topic), qos, raw=True)
        self.get_logger().info(f"subscribed to {topic} [{msgtype}] "
                               f"({qos.reliability.name}, {qos.durability.name}, "
                               f"KEEP_LAST({qos.depth}))")

    # -- recording -----------------------------------------------------------------------------
    def _on_message(self, topic: str, data: bytes, info: Any) -> None:
        """raw=True + two-argument callback: CDR bytes and the rmw message info."""
        if isinstance(info, dict):
            recv, src = info.get("received_timestamp"), info.get("source_timestamp")
            seq = info.get("publication_sequence_number") or 0
        else:
            recv = getattr(info, "received_timestamp", None)
            src = getattr(info, "source_timestamp", None)
            seq = getattr(info, "publication_sequence_number", 0) or 0
        if not recv:
            recv = time.time_ns()
        with self._lock:
            if self.writer.closed:
                return
            try:
                self.writer.write(topic, data, recv, src if src else recv, sequence=seq)
                self.received += 1
            except Exception as exc:
                self.errors += 1
                self._warn_once(f"write:{type(exc).__name__}", f"write to bag failed: {exc}")
                self._check_failure()

    def _flush_if_due(self) -> None:
        with self._lock:
            try:
                self.writer.flush_if_due()
            except mcap_io.BagWriteError as exc:
                self._warn_once("flush", f"flushing the bag failed: {exc}")
                self._check_failure()

    def _check_failure(self) -> None:
        """A write error (disk full, file too large, permission lost, file removed) ends the
        recording: the bag is closed with what it holds and the recorder exits with
        EXIT_WRITE_FAILED."""
        if self.writer.failure is not None and not self.done.is_set():
            self.get_logger().error(f"recording stopped: {self.writer.failure}; closing the bag with the "
                                    f"{self.writer.message_count} messages written")
            self.exit_code = EXIT_WRITE_FAILED
            self.done.set()

    def _status(self) -> None:
        counts = ", ".join(f"{t}: {n}" for t, n in self.writer.topic_counts.items())
        self.get_logger().info(f"{self.writer.message_count} messages ({counts})")

    def drain(self, executor: Any, quiet_s: float = 0.3, limit_s: float = 3.0) -> None:
        """Take what the middleware already holds before closing (used after SIGINT/SIGTERM)."""
        deadline = time.monotonic() + limit_s
        last, quiet_since = self.received, time.monotonic()
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
            if self.received != last:
                last, quiet_since = self.received, time.monotonic()
            elif time.monotonic() - quiet_since >= quiet_s:
                break

    def close(self) -> dict[str, int]:
        """Close the bag (footer, summary, metadata.yaml); returns the per-topic counts."""
        with self._lock:
            self.writer.close()
        return self.writer.topic_counts


#: Exit status when a write error (disk full, ...) ended the recording; the bag holds what was
#: written before it, closed validly where the disk allowed (see BagWriter.close).
EXIT_WRITE_FAILED = 3


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="ros2 run trainer record",
        description="Record ROS 2 topics into a rosbag2-compatible MCAP bag directory "
                    "(NAME/NAME_0.mcap ... + metadata.yaml). Every option is also a ROS "
                    "parameter (--ros-args -p name:=value). SIGINT/SIGTERM close the bag cleanly.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("-o", "--output", default=None,
                    help="bag directory to create (default: rosbag2_YYYY_MM_DD-HH_MM_SS)")
    ap.add_argument("topics", nargs="*", default=[],
                    help="topics to record (default: the contract topics image, step_info, "
                         "context, action, context_features in --namespace, and /clock)")
    ap.add_argument("--topics", dest="topics_opt", nargs="+", default=[], metavar="TOPIC",
                    help="same as the positional topics")
    ap.add_argument("-a", "--all", dest="all_topics", action="store_true",
                    help="record every (non-hidden) topic")
    ap.add_argument("-e", "--exclude-regex", default="", help="do not record matching topics")
    ap.add_argument("--namespace", default=T.DEFAULT_NAMESPACE,
                    help="namespace of the default contract topics")
    ap.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                    help="MCAP chunk compression")
    ap.add_argument("--chunk-size", type=int, default=mcap_io.DEFAULT_CHUNK_SIZE,
                    help="uncompressed chunk size in bytes (smaller: less lost on SIGKILL)")
    ap.add_argument("-b", "--max-bag-size", dest="max_bagfile_size", type=int, default=0,
                    help="split the bag at this file size in bytes (0: no split; >= 1024)")
    ap.add_argument("-d", "--max-bag-duration", dest="max_bagfile_duration", type=float,
                    default=0.0, help="split the bag after this many seconds (0: no split)")
    ap.add_argument("--flush-interval", type=float, default=1.0,
                    help="write the open chunk at least every this many seconds (0: only by "
                         "size); bounds what a SIGKILL loses")
    ap.add_argument("--queue-depth", type=int, default=DEFAULT_QUEUE_DEPTH,
                    help="KEEP_LAST depth of the recorder's subscriptions")
    ap.add_argument("--discovery-interval", type=float, default=0.2,
                    help="seconds between graph polls for topics that appear late")
    ap.add_argument("--status-interval", type=float, default=0.0,
                    help="log message counts every this many seconds (0: off)")
    ap.add_argument("--node-name", default="recorder", help="ROS node name")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else [sys.argv[0], *argv])
    from rclpy.utilities import remove_ros_args
    args = build_parser().parse_args(remove_ros_args(argv)[1:])
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        stop.set()

    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        node = RecorderNode(
            output=args.output, topics=[*args.topics, *args.topics_opt],
            namespace=args.namespace, all_topics=args.all_topics,
            exclude_regex=args.exclude_regex, compression=args.compression,
            chunk_size=args.chunk_size, max_bagfile_size=args.max_bagfile_size,
            max_bagfile_duration=args.max_bagfile_duration, flush_interval=args.flush_interval,
            queue_depth=args.queue_depth, discovery_interval=args.discovery_interval,
            status_interval=args.status_interval, node_name=args.node_name)
    except (mcap_io.BagWriteError, ValueError) as exc:
        print(f"recorder: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    print(f"recorder: recording to {node.writer.bag_dir}", flush=True)
    try:
        while not stop.is_set() and not node.done.is_set():
            executor.spin_once(timeout_sec=0.1)
        if not node.done.is_set():
            node.drain(executor)
    finally:
        counts = node.close()
        w = node.writer
        total = sum(counts.values())
        lines = [f"recorder: recorded {total} messages to {w.bag_dir} ({len(w.files)} file(s))"]
        lines += [f"  {t}: {n}" for t, n in counts.items()]
        if node.errors:
            lines.append(f"  write errors: {node.errors}")
        if w.failure is not None:
            lines.append(f"  RECORDING STOPPED EARLY: {w.failure}")
            lines.append(f"  messages lost (received, not in the bag: the open chunk and everything after): "
                         f"{w.lost_after_failure}")
            lines += [f"  {note}" for note in w.salvage_notes]
            lines.append(f"  metadata.yaml: {'written' if (w.bag_dir / 'metadata.yaml').exists() else 'NOT written'}")
        print("\n".join(lines), flush=True)
        executor.remove_node(node)
        node.destroy_node()
        rclpy.try_shutdown()
    return node.exit_code


if __name__ == "__main__":
    sys.exit(main())
