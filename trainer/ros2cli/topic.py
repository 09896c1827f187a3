"""`ros2 topic list|info|echo|hz`, printing what ros2cli (Jazzy) prints for the options here."""
from __future__ import annotations

import argparse
import math
import threading
from typing import Any

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import (
    QoSDurabilityPolicy,
    QoSHistoryPolicy,
    QoSPresetProfiles,
    QoSReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.task import Future

from trainer.cli_values import non_negative_int, positive_float, positive_int
from trainer.ros2cli import graph
from trainer.ros2cli.msgyaml import interface_class, message_to_csv, message_to_yaml

DEFAULT_TRUNCATE_LENGTH = 128
DEFAULT_WINDOW_SIZE = 10000


def topic_names_and_types(node, include_hidden: bool = False) -> list[tuple[str, list[str]]]:
    return [(n, t) for n, t in node.get_topic_names_and_types() if include_hidden or not graph.is_hidden(n)]


def topic_type(node, topic: str) -> str | None:
    for name, types in topic_names_and_types(node, include_hidden=True):
        if name == topic:
            return types[0]
    return None


# ------------------------------------------------------------------ list / info
def cmd_list(args) -> int | str | None:
    with graph.direct_node(args) as node:
        info = []
        for name, types in topic_names_and_types(node, args.include_hidden_topics):
            pubs, subs = (node.count_publishers(name), node.count_subscribers(name)) if args.verbose else (0, 0)
            info.append((name, types, pubs, subs))
    if args.count_topics:
        print(len(info))
    elif info and args.verbose:
        for is_pub in (True, False):
            lines = ["Published topics:" if is_pub else "Subscribed topics:"]
            for name, types, pubs, subs in info:
                count = pubs if is_pub else subs
                if count:
                    what = "publisher" if is_pub else "subscriber"
                    lines.append(f" * {name} [{', '.join(types)}] {count} {what}{'s' if count > 1 else ''}")
            print("\n".join(lines) + "\n")
    else:
        for name, types, _, _ in info:
            print(f"{name} [{', '.join(types)}]" if args.show_types else name)
    return None


def cmd_info(args) -> int | str | None:
    with graph.direct_node(args) as node:
        graph.wait_for(lambda: topic_type(node, args.topic_name) is not None, node)
        types = dict(topic_names_and_types(node, include_hidden=True)).get(args.topic_name)
        if types is None:
            return f"Unknown topic '{args.topic_name}'"
        end = "\n\n" if args.verbose else "\n"
        print(f"Type: {types[0] if len(types) == 1 else types}", end=end)
        print(f"Publisher count: {node.count_publishers(args.topic_name)}", end=end)
        if args.verbose:
            for info in node.get_publishers_info_by_topic(args.topic_name):
                print(info, end=end)
        print(f"Subscription count: {node.count_subscribers(args.topic_name)}", end=end)
        if args.verbose:
            for info in node.get_subscriptions_info_by_topic(args.topic_name):
                print(info, end=end)
    return None


def message_filter(expr: str | None):
    """ros2cli's --filter: a Python expression of `m`, the message; None without one. A syntax
    error is a clear RuntimeError at once; one raised while filtering names the expression."""
    if not expr:
        return None
    try:
        fn = eval(f"lambda m: ({expr})")  # noqa: S307  (what --filter is, as in ros2cli)
    except SyntaxError as exc:
        raise RuntimeError(f"--filter {expr!r} is not a Python expression: {exc.msg}") from None

    def keep(m) -> bool:
        try:
            return bool(fn(m))
        except Exception as exc:  # noqa: BLE001  the user's expression
            raise RuntimeError(f"--filter {expr!r} failed on a message: {type(exc).__name__}: {exc}") from None

    return keep


def message_class(type_name: str):
    try:
        return interface_class(type_name)
    except ValueError as exc:   # e.g. a foreign message type not installed here
        raise RuntimeError(f"cannot decode {type_name}: {exc}") from None


# ------------------------------------------------------------------ echo
QOS_PROFILES = ("system_default", "sensor_data", "services_default", "parameters", "parameter_events",
                "action_status_default", "best_available")


def add_qos_arguments(parser: argparse.ArgumentParser, default_profile: str) -> None:
    parser.add_argument("--qos-profile", choices=QOS_PROFILES, default=default_profile,
                        help=f"Quality of service preset profile to subscribe with (default: {default_profile})")
    parser.add_argument("--qos-depth", metavar="N", type=int, default=None,
                        help="Queue size setting to subscribe with (overrides depth value of --qos-profile option)")
    parser.add_argument("--qos-history", choices=("system_default", "keep_last", "keep_all"), default=None,
                        help="History of samples setting to subscribe with (overrides --qos-profile)")
    parser.add_argument("--qos-reliability", choices=("system_default", "reliable", "best_effort"), default=None,
                        help="Quality of service reliability setting to subscribe with (overrides --qos-profile)")
    parser.add_argument("--qos-durability", choices=("system_default", "transient_local", "volatile"),
                        default=None,
                        help="Quality of service durability setting to subscribe with (overrides --qos-profile)")


def choose_qos(node, args) -> Any:
    """ros2cli's rule: the preset, adapted to what every publisher offers, unless set explicitly."""
    profile = QoSPresetProfiles.get_from_short_key(args.qos_profile)
    explicit = any(v is not None for v in (args.qos_depth, args.qos_history, args.qos_reliability,
                                           args.qos_durability))
    if explicit:
        if args.qos_history is not None:
            profile.history = QoSHistoryPolicy.get_from_short_key(args.qos_history)
        if args.qos_reliability is not None:
            profile.reliability = QoSReliabilityPolicy.get_from_short_key(args.qos_reliability)
        if args.qos_durability is not None:
            profile.durability = QoSDurabilityPolicy.get_from_short_key(args.qos_durability)
        if args.qos_depth is not None:
            profile.depth = args.qos_depth
        return profile
    pubs = node.get_publishers_info_by_topic(args.topic_name)
    if not pubs:
        return profile
    reliable = sum(p.qos_profile.reliability == QoSReliabilityPolicy.RELIABLE for p in pubs)
    latched = sum(p.qos_profile.durability == QoSDurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
    if reliable == len(pubs):
        profile.reliability = QoSReliabilityPolicy.RELIABLE
    else:
        if reliable:
            print("Some, but not all, publishers are offering QoSReliabilityPolicy.RELIABLE. Falling back "
                  "to QoSReliabilityPolicy.BEST_EFFORT as it will connect to all publishers")
        profile.reliability = QoSReliabilityPolicy.BEST_EFFORT
    if latched == len(pubs):
        profile.durability = QoSDurabilityPolicy.TRANSIENT_LOCAL
    else:
        if latched:
            print("Some, but not all, publishers are offering QoSDurabilityPolicy.TRANSIENT_LOCAL. Falling "
                  "back to QoSDurabilityPolicy.VOLATILE as it will connect to all publishers")
        profile.durability = QoSDurabilityPolicy.VOLATILE
    return profile


def _message_class(node, args) -> Any:
    if args.message_type is not None:
        try:
            return interface_class(args.message_type)
        except ValueError:
            raise RuntimeError("The passed message type is invalid") from None
    graph.wait_for(lambda: topic_type(node, args.topic_name) is not None, node)
    name = topic_type(node, args.topic_name)
    if name is None:
        raise RuntimeError("Could not determine the type for the passed topic")
    return message_class(name)


def cmd_echo(args) -> int | str | None:
    field = None
    if args.field is not None:
        field = [f for f in args.field.split(".") if f]
        if not field:
            return f"Invalid field value '{args.field}'"
    truncate = None if args.full_length else args.truncate_length
    keep = message_filter(args.filter_expr)
    done = Future()  # set by --once, --timeout or a bad --field; else Ctrl-C ends the echo
    failure: list[str] = []

    def on_message(msg, info) -> None:
        sub = msg
        for f in field or ():
            try:
                sub = getattr(sub, f)
            except AttributeError as exc:
                failure.append(f"Invalid field '{'.'.join(field)}': {exc}")
                done.done() or done.set_result(True)
                return
        try:
            if keep is not None and not keep(sub):
                return
        except RuntimeError as exc:
            failure.append(str(exc))
            done.done() or done.set_result(True)
            return
        if args.once:
            if done.done():
                return
            done.set_result(True)
        if not hasattr(sub, "__slots__"):
            print(sub, end="\n---\n")
        elif args.csv:
            print(message_to_csv(sub, truncate_length=truncate, no_arr=args.no_arr, no_str=args.no_str))
        else:
            print(message_to_yaml(sub, truncate_length=truncate, no_arr=args.no_arr, no_str=args.no_str,
                                  flow_style=args.flow_style), end="---\n")

    def on_lost(status) -> None:
        print(f"A message was lost!!!\n\ttotal count change:{status.total_count_change}"
              f"\n\ttotal count: {status.total_count}", end="---\n")

    with graph.direct_node(args, discover=False) as node:
        msg_type = _message_class(node, args)
        # The QoS adapts to the publishers (a latched topic needs TRANSIENT_LOCAL): wait for one.
        graph.wait_for(lambda: node.count_publishers(args.topic_name) > 0, node)
        events = None if args.no_lost_messages else SubscriptionEventCallbacks(message_lost=on_lost)
        try:
            node.create_subscription(msg_type, args.topic_name, on_message, choose_qos(node, args),
                                     event_callbacks=events)
        except Exception:  # noqa: BLE001  a middleware without the message-lost event
            node.create_subscription(msg_type, args.topic_name, on_message, choose_qos(node, args))
        if args.timeout:
            node.create_timer(args.timeout, lambda: done.done() or done.set_result(True))
        rclpy.spin_until_future_complete(node, done)
    return failure[0] if failure else None


# ------------------------------------------------------------------ hz
class RateMeter:
    """Inter-arrival times of the last `window` messages, reported at most once a second."""

    def __init__(self, window: int, clock):
        self.window, self.clock = window, clock
        self.lock = threading.Lock()
        self.times: list[int] = []
        self.t0, self.tn, self.last_printed = -1, 0, 0

    def tick(self, now_ns: int) -> None:
        with self.lock:
            if now_ns == 0:  # sim time not started yet (or reset)
                if self.times:
                    print("time has reset, resetting counters")
                    self.times = []
                return
            if self.t0 < 0 or self.t0 > now_ns:
                self.t0 = self.tn = now_ns
                self.times = []
            else:
                self.times.append(now_ns - self.tn)
                self.tn = now_ns
            if len(self.times) > self.window:
                self.times.pop(0)

    def report(self) -> tuple[float, float, float, float, int] | None:
        with self.lock:
            if not self.times:
                return None
            if self.last_printed == 0:
                self.last_printed = self.tn
                return None
            if self.tn < self.last_printed + 1e9:
                return None
            n = len(self.times)
            mean = sum(self.times) / n
            std = math.sqrt(sum((x - mean) ** 2 for x in self.times) / n)
            self.last_printed = self.tn
            return (1.0 / mean if mean > 0 else 0.0), min(self.times), max(self.times), std, n


def format_hz(rate_per_ns: float, min_ns: float, max_ns: float, std_ns: float, window: int) -> str:
    return ("average rate: %.3f\n\tmin: %.3fs max: %.3fs std dev: %.5fs window: %s"
            % (rate_per_ns * 1e9, min_ns * 1e-9, max_ns * 1e-9, std_ns * 1e-9, window))


def cmd_hz(args) -> int | str | None:
    keep = message_filter(args.filter_expr)
    failure: list[str] = []
    with graph.direct_node(args, discover=False) as node:
        name = None
        while rclpy.ok() and name is None:  # ros2cli waits for the topic to appear
            name = topic_type(node, args.topic_name)
            if name is None:
                rclpy.spin_once(node, timeout_sec=0.1)
        clock = Clock(clock_type=ClockType.SYSTEM_TIME) if args.use_wtime else node.get_clock()
        meter = RateMeter(args.window_size, clock)

        def on_message(msg) -> None:
            try:
                if keep is None or keep(msg):
                    meter.tick(clock.now().nanoseconds)
            except RuntimeError as exc:
                failure.append(str(exc))

        node.create_subscription(message_class(name), args.topic_name, on_message, qos_profile_sensor_data)
        while rclpy.ok() and not failure:
            rclpy.spin_once(node, timeout_sec=0.1)
            stats = meter.report()
            if stats is not None:
                print(format_hz(*stats))
    return failure[0] if failure else None


# ------------------------------------------------------------------ parsers
def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("list", help="Output a list of available topics")
    graph.add_node_arguments(p)
    p.add_argument("-t", "--show-types", action="store_true", help="Additionally show the topic type")
    p.add_argument("-c", "--count-topics", action="store_true", help="Only display the number of topics discovered")
    p.add_argument("--include-hidden-topics", action="store_true", help="Consider hidden topics as well")
    p.add_argument("-v", "--verbose", action="store_true", help="List full details about each topic")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("info", help="Print information about a topic")
    graph.add_node_arguments(p)
    p.add_argument("topic_name", help="Name of the ROS topic to get info (e.g. '/chatter')")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="Prints detailed information like the node name, node namespace, topic type, topic type "
                        "hash, GUID, and QoS Profile of the publishers and subscribers to this topic")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("echo", help="Output messages from a topic")
    graph.add_node_arguments(p)
    p.add_argument("topic_name", help="Name of the ROS topic to listen to (e.g. '/chatter')")
    p.add_argument("message_type", nargs="?", help="Type of the ROS message (e.g. 'std_msgs/msg/String')")
    add_qos_arguments(p, "sensor_data")
    p.add_argument("--csv", action="store_true", help="Output all recursive fields separated by commas")
    p.add_argument("--field", default=None, help="Echo a selected field of a message; '.' selects sub-fields")
    p.add_argument("--full-length", "-f", action="store_true",
                   help="Output all elements for arrays, bytes, and string with a length > '--truncate-length'")
    p.add_argument("--truncate-length", "-l", type=non_negative_int, default=DEFAULT_TRUNCATE_LENGTH,
                   help=f"The length to truncate arrays, bytes, and string to (default: {DEFAULT_TRUNCATE_LENGTH})")
    p.add_argument("--no-arr", action="store_true", help="Don't print array fields of messages")
    p.add_argument("--no-str", action="store_true", help="Don't print string fields of messages")
    p.add_argument("--flow-style", action="store_true", help="Print collections in the flow style")
    p.add_argument("--no-lost-messages", action="store_true", help="Don't report when a message is lost")
    p.add_argument("--filter", dest="filter_expr", help="Python expression (of m, the message) selecting "
                                                         "the messages that are printed")
    p.add_argument("--once", action="store_true", help="Print the first message received and then exit.")
    p.add_argument("--timeout", metavar="N", type=positive_float, default=None,
                   help="Set a timeout in seconds for waiting")
    p.set_defaults(func=cmd_echo)

    p = sub.add_parser("hz", help="Print the average publishing rate to screen")
    graph.add_node_arguments(p)
    p.add_argument("topic_name", help="Name of the ROS topic to listen to (e.g. '/chatter')")
    p.add_argument("--window", "-w", dest="window_size", type=positive_int, default=DEFAULT_WINDOW_SIZE,
                   metavar="WINDOW",
                   help=f"window size, in # of messages, for calculating rate (default: {DEFAULT_WINDOW_SIZE})")
    p.add_argument("--filter", dest="filter_expr", default=None, metavar="EXPR",
                   help="only measure messages matching the specified Python expression")
    p.add_argument("--wall-time", dest="use_wtime", action="store_true",
                   help="calculates rate using wall time which can be helpful when clock is not published "
                        "during simulation")
    p.set_defaults(func=cmd_hz)

