"""RecorderTopics, the recorder's topics (a part of RecorderNode, trainer/nodes/recorder.py):
which topics it records (TopicSelection: a list, -a, -e and the excludes, as `ros2 bag
record`), finding them in the ROS graph as their publishers appear, and subscribing to each
with a QoS adapted to what those publishers offer. A second publisher on a recorded topic is
marked in the bag's metadata.

It owns its subscriptions, the discovery timer and the PublisherWatch of the recorded topics; it
is handed the node (graph queries, create_*, its logger), the parameters, the TopicSelection
(built before the bag, so a bad regular expression leaves no bag behind), the writer (topics are
added to it, the several-publishers mark goes into its custom_data), the node's lock and `done`
event, stop(exit_code, reason) (a contract topic offered with another type ends the recording),
warn_once, on_message (RecorderWriting's, for every subscription but a contract bridge_info) and
RecorderAnnouncements' filter and heard (for that one)."""
from __future__ import annotations

import functools
import importlib
import json
import re
import threading
from typing import Any, Callable, Mapping, Sequence

from sim_bridge.contract import topics as T
from sim_bridge.nodekit.publisher_watch import PublisherWatch
from trainer.bag.rosmsg import interface_module
from trainer.bag.writer import BagWriter, qos_profile
from trainer.data.records import MULTIPLE_PUBLISHERS_KEY
from trainer.nodes.record_budget import contract_name

#: Exit status when a contract topic is offered with another type than the contract's.
EXIT_TYPE_MISMATCH = 5
#: Relative contract topics recorded by default (resolved in --namespace), plus the bridge's
#: clock there (topics.clock_topic: /clock in the default namespace).
DEFAULT_RELATIVE_TOPICS = (T.IMAGE, T.STEP_INFO, T.CONTEXT, T.ACTION, T.CONTEXT_FEATURES, T.BRIDGE_INFO)
#: Topics that have one publisher per node by design: never marked as having several.
MANY_PUBLISHERS_BY_DESIGN = frozenset({T.DIAGNOSTICS, "/rosout", "/parameter_events"})
#: 0 = KEEP_ALL subscriptions (lossless against KEEP_ALL writers); N > 0 = KEEP_LAST(N).
DEFAULT_QUEUE_DEPTH = 0
#: rclpy wants a depth even for KEEP_ALL; Fast DDS ignores it there.
KEEP_ALL_DEPTH = 1000


def default_topics(namespace: str = T.DEFAULT_NAMESPACE) -> list[str]:
    return [T.topic_name(namespace, t) for t in DEFAULT_RELATIVE_TOPICS] + [T.clock_topic(namespace)]


def qos_profile_to_dict(qos: Any) -> dict[str, Any]:
    """An rclpy QoSProfile as rosbag2 (metadata v9) serializes it."""
    def name(policy: Any) -> str:
        return policy.name.lower()   # keep_last, reliable, transient_local, automatic, unknown...

    return qos_profile(
        history=name(qos.history), depth=int(qos.depth), reliability=name(qos.reliability),
        durability=name(qos.durability), deadline_ns=qos.deadline.nanoseconds,
        lifespan_ns=qos.lifespan.nanoseconds, liveliness=name(qos.liveliness),
        liveliness_lease_duration_ns=qos.liveliness_lease_duration.nanoseconds,
        avoid_ros_namespace_conventions=bool(qos.avoid_ros_namespace_conventions))


def apply_qos_override(qos: Any, override: Mapping[str, Any] | None):
    """A --qos-profile-overrides-path entry ({reliability, durability, history, depth}) on top of
    the adapted profile (ValueError naming a bad value)."""
    if not override:
        return qos
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

    for key, enum in (("reliability", ReliabilityPolicy), ("durability", DurabilityPolicy),
                      ("history", HistoryPolicy)):
        if key in override:
            try:
                setattr(qos, key, enum[str(override[key]).upper()])
            except KeyError:
                raise ValueError(f"QoS override {key}={override[key]!r}; valid: "
                                 f"{[e.name.lower() for e in enum]}") from None
    if "depth" in override:
        qos.depth = int(override["depth"])
    return qos


def subscription_qos(offered: Sequence[Any], depth: int):
    """The QoS the recorder requests, adapted to the publishers' offers like rosbag2
    (Rosbag2QoS::adapt_request_to_offers), with the history the contract needs:

    * RELIABLE when every publisher is reliable (the protocad contract: a reliable reader never
      loses a sample the writer still holds), else BEST_EFFORT (a reliable reader would not
      match a best-effort writer at all);
    * TRANSIENT_LOCAL when every publisher offers it (latched data is recorded), else VOLATILE;
    * KEEP_ALL when depth <= 0 (the default): the reader never drops a sample it accepted and
      refuses (does not acknowledge) what it has no room for, so a KEEP_ALL writer (the lock-step
      bridge, every action publisher) keeps it and sends it again: a backlog of any size, e.g.
      after a stall, costs the writer time and memory, never a sample. A KEEP_LAST writer (a
      real-time bridge) is not held back: it overwrites, and the gap is counted. depth > 0:
      KEEP_LAST(depth), which drops the oldest samples of a backlog deeper than that.
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    reliable = bool(offered) and all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    latched = bool(offered) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                    for q in offered)
    keep_all = int(depth) <= 0
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL if keep_all else HistoryPolicy.KEEP_LAST,
        depth=KEEP_ALL_DEPTH if keep_all else int(depth),
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def history_name(depth: int) -> str:
    """The history a `queue_depth` asks for, for logs: KEEP_ALL or KEEP_LAST(N)."""
    return "KEEP_ALL" if int(depth) <= 0 else f"KEEP_LAST({int(depth)})"


def _import_message(msgtype: str) -> Any:
    """The rclpy class of a type a remote participant advertises: checked before anything is
    imported (trainer.bag.rosmsg.interface_module: identifiers, an interface kind, an ament package)."""
    module, name = interface_module(msgtype)
    return getattr(importlib.import_module(module), name)


class TopicSelection:
    """Which topics to record, from the parameters (ValueError for a bad regular expression):
    built before the bag, so a bad one leaves no bag behind. `resolve` is the node's
    resolve_topic_name."""

    def __init__(self, p: Mapping[str, Any], resolve: Callable[[str], str],
                 qos_overrides: Mapping[str, Mapping[str, Any]] | None):
        self._all, self._regex = p["all_topics"], p["regex"]
        self._hidden = p["include_hidden_topics"]
        # As ros2 bag record: -a overrides -e; topics and -e add up; excludes apply on top.
        explicit = [resolve(t) for t in p["topics"]]
        self.wanted: list[str] = ([] if p["all_topics"] else explicit
                                  or ([] if p["regex"] else default_topics(p["namespace"])))
        try:
            self._include = re.compile(p["regex"]) if p["regex"] and not p["all_topics"] else None
            self._exclude = re.compile(p["exclude_regex"]) if p["exclude_regex"] else None
        except re.error as exc:
            raise ValueError(f"bad regular expression: {exc}") from None
        self._excluded = {resolve(t) for t in p["exclude_topics"]}
        self._qos_overrides = {resolve(t): dict(v) for t, v in (qos_overrides or {}).items()}

    def text(self) -> str:
        """The selection, for the start-up line."""
        return ("all topics" if self._all else ", ".join(
            self.wanted + ([f"topics matching {self._regex!r}"] if self._include else [])))

    def want(self, topic: str) -> bool:
        if topic in self._excluded or (self._exclude is not None and self._exclude.search(topic)):
            return False
        if topic in self.wanted:
            return True
        if self._all or (self._include is not None and self._include.search(topic)):
            from rclpy.topic_or_service_is_hidden import topic_or_service_is_hidden
            return self._hidden or not topic_or_service_is_hidden(topic)
        return False

    def qos_override(self, topic: str) -> Mapping[str, Any] | None:
        """The --qos-profile-overrides-path entry for `topic`, if any."""
        return self._qos_overrides.get(topic)


class RecorderTopics:
    """Finds the selected topics in the graph and subscribes to each (see the module docstring)."""

    def __init__(self, *, node: Any, params: Mapping[str, Any], selection: TopicSelection,
                 writer: BagWriter, lock: threading.Lock, done: threading.Event,
                 stop: Callable[[int, str | None], None], warn_once: Callable[[str, str], None],
                 on_message: Callable[[str, bytes, Any], None],
                 filter_announcements: Callable[[str, Any, Any], None],
                 on_announcement_heard: Callable[[str, bytes, Any], None]):
        self._node, self._params, self.selection, self._writer = node, params, selection, writer
        self._lock, self._done, self._stop, self._warn_once = lock, done, stop, warn_once
        self._on_message = on_message
        self._filter_announcements, self._on_announcement_heard = filter_announcements, on_announcement_heard
        self._subs: dict[str, Any] = {}
        # A recorded topic with several writers mixes their samples in the bag (an impostor, a
        # second bridge): marked in the bag's metadata as soon as it is seen.
        self.publisher_watch = PublisherWatch(self._on_new_publisher)
        self._discovery_timer = None

    def start(self) -> None:
        """Subscribe to what the graph has now, then look again every discovery_interval (unless
        no_discovery)."""
        self._discover()
        if not self._params["no_discovery"]:
            self._discovery_timer = self._node.create_timer(self._params["discovery_interval"], self._discover)

    def _discover(self) -> None:
        if self._writer.closed or self._done.is_set():
            return
        for topic, types in self._node.get_topic_names_and_types():
            if topic in self._subs or not self.selection.want(topic):
                continue
            expected = T.contract_topic_type(topic, self._params["namespace"], nested=True)
            if expected is not None and set(types) != {expected}:
                return self._claimed_with_another_type(topic, types, expected)
            if len(types) != 1:
                self._warn_once(f"types:{topic}", f"topic {topic} has several types {types}; "
                                "not recorded (as rosbag2)")
                continue
            pubs = self._node.get_publishers_info_by_topic(topic)
            if not pubs:
                continue  # wait for a publisher: its offered QoS decides ours
            try:
                self._subscribe(topic, types[0], pubs)
            except Exception as exc:  # noqa: BLE001 - unknown type, import error...
                self._warn_once(f"sub:{topic}", f"cannot record {topic} [{types[0]}]: {exc}")

    def _claimed_with_another_type(self, topic: str, types: Sequence[str], expected: str) -> None:
        """A contract topic offered with a type that is not the contract's (a stranger who
        claimed the name first): its writers and the bridge's can never match, so a bridge
        waiting for its readers would wait forever. One ERROR line; the recording ends (a
        closed bag, EXIT_TYPE_MISMATCH), which ends a launcher's run."""
        reason = (f"{topic} is offered as {', '.join(sorted(types))}, but its contract type is "
                  f"{expected} (another participant claimed the topic with another type)")
        self._node.get_logger().error(f"recording stopped: {reason}")
        self._stop(EXIT_TYPE_MISMATCH, reason)

    def _subscribe(self, topic: str, msgtype: str, pubs: Sequence[Any]) -> None:
        msg_class = _import_message(msgtype)
        offered = [e.qos_profile for e in pubs]
        hashes = {str(e.topic_type_hash) for e in pubs} - {"INVALID"}
        type_hash = sorted(hashes)[0] if hashes else None
        self._writer.add_topic(topic, msgtype, [qos_profile_to_dict(q) for q in offered],
                               type_hash=type_hash)
        qos = apply_qos_override(subscription_qos(offered, self._params["queue_depth"]),
                                 self.selection.qos_override(topic))
        on_message = self._on_message
        if contract_name(topic, self._params["namespace"]) == T.BRIDGE_INFO:   # only its bridge's
            self._filter_announcements(topic, msg_class, qos)
            on_message = self._on_announcement_heard
        self._subs[topic] = self._node.create_subscription(
            msg_class, topic, functools.partial(on_message, topic), qos, raw=True,
            event_callbacks=None if topic in MANY_PUBLISHERS_BY_DESIGN else self.publisher_watch.callbacks(topic))
        from sim_bridge.contract.qos import describe

        self._node.get_logger().info(f"subscribed to {topic} [{msgtype}] ({describe(qos)})")

    def _on_new_publisher(self, topic: str, publishers: int, first_time: bool) -> None:
        with self._lock:
            self._writer.custom_data = {**(self._writer.custom_data or {}), **self.publishers_summary()}
        if first_time:
            self._node.get_logger().warning(
                f"{topic}: {publishers} publishers: their messages interleave in the bag (a second "
                f"bridge, an impostor?); marked in its metadata ({MULTIPLE_PUBLISHERS_KEY}), and "
                "protocad-train refuses it unless given --accept-multiple-publishers")

    def publishers_summary(self) -> dict[str, str]:
        """The topics that had several publishers, as metadata.yaml custom_data."""
        ever = self.publisher_watch.ever
        return {MULTIPLE_PUBLISHERS_KEY: json.dumps(ever, sort_keys=True)} if ever else {}

    def summary_lines(self) -> list[str]:
        """The topics that had several publishers, for the exit summary."""
        several = self.publisher_watch.ever
        if not several:
            return []
        return ["  SEVERAL PUBLISHERS (marked in the metadata): " + ", ".join(
            f"{t}: {n}" for t, n in sorted(several.items()))]
