"""`ros2 param list|get|set|dump|describe`, through the standard parameter services, printing
what ros2cli (Jazzy) prints."""
from __future__ import annotations

import argparse
import re
import sys
from contextlib import contextmanager
from typing import Any, Iterator

from rcl_interfaces.msg import Parameter
from rclpy.parameter import get_parameter_value, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient

from trainer.ros2cli import graph
from trainer.ros2cli.msgyaml import dump

SERVICE_TIMEOUT_S = 5.0

TYPE_NAMES = {1: "boolean", 2: "integer", 3: "double", 4: "string", 5: "byte array", 6: "boolean array",
              7: "integer array", 8: "double array", 9: "string array", 0: "not set"}


def _client(node, full_name: str):
    client = AsyncParameterClient(node, full_name)
    if not client.wait_for_services(timeout_sec=SERVICE_TIMEOUT_S):
        return None
    return client


def _require_node(node, args) -> str | None:
    """The node's absolute name, or None once `--timeout` passed without it in the graph."""
    target = graph.absolute(args.node_name)
    return target if graph.wait_for_node(node, target, args.include_hidden_nodes,
                                                 max(args.timeout, graph.SETTLE_MAX_S)) else None


@contextmanager
def _parameter_client(args) -> Iterator[tuple[Any, str, Any]]:
    """(node, absolute node name, its parameter client) for args.node_name; RuntimeError with
    ros2cli's message (exit 1) when the node or its parameter services are not there."""
    with graph.direct_node(args, discover=False) as node:   # waits for its one node instead
        target = _require_node(node, args)
        if target is None:
            raise RuntimeError("Node not found")
        client = _client(node, target)
        if client is None:
            raise RuntimeError(f"Wait for service timed out waiting for parameter services for node {target}")
        yield node, target, client


def _call(node, future):
    result = graph.spin_until_future(node, future, SERVICE_TIMEOUT_S)
    if result is None:
        raise RuntimeError(f"no answer within {SERVICE_TIMEOUT_S:g} s")
    return result


def cmd_list(args) -> int | str | None:
    target = graph.absolute(args.node_name)
    with graph.direct_node(args, discover=not target) as node:   # one node: wait for it alone
        if target:
            if not graph.wait_for_node(node, target, args.include_hidden_nodes):
                return "Node not found"
            names = [graph.parse_node_name(target)]
        else:
            names = graph.node_names(node, include_hidden=args.include_hidden_nodes)
        pattern = re.compile(args.filter[0]) if args.filter else None
        for nn in sorted(names):  # as ros2cli: NodeName tuples, i.e. by base name first
            client = _client(node, nn.full_name)
            if client is None:
                print(f"Wait for service timed out waiting for parameter services for node {nn}")
                continue
            try:
                listed = sorted(_call(node, client.list_parameters(args.param_prefixes)).result.names)
            except RuntimeError as exc:
                print(f"Exception while calling service of node '{nn.full_name}': {exc}", file=sys.stderr)
                continue
            if pattern is not None:
                listed = [n for n in listed if pattern.match(n)]
            if not args.node_name and listed:
                print(f"{nn.full_name}:")
            types = {}
            if args.param_type and listed:
                for d in _call(node, client.describe_parameters(listed)).descriptors:
                    types[d.name] = TYPE_NAMES.get(d.type, str(d.type))
            for name in listed:
                print(f"  {name} (type: {types[name]})" if args.param_type else f"  {name}")
    return None


def _label_and_value(pv) -> tuple[str, object] | str:
    t = pv.type
    table = {1: ("Boolean value is:", pv.bool_value), 2: ("Integer value is:", pv.integer_value),
             3: ("Double value is:", pv.double_value), 4: ("String value is:", pv.string_value),
             5: ("Byte values are:", pv.byte_array_value), 6: ("Boolean values are:", pv.bool_array_value),
             7: ("Integer values are:", list(pv.integer_array_value)),
             8: ("Double values are:", list(pv.double_array_value)),
             9: ("String values are:", pv.string_array_value), 0: ("Parameter not set.", None)}
    return table.get(t, f"Unknown parameter type '{t}'")


def cmd_get(args) -> int | str | None:
    with _parameter_client(args) as (node, target, client):
        values = _call(node, client.get_parameters([args.parameter_name])).values
    if not values:
        return "Parameter not set"
    got = _label_and_value(values[0])
    if isinstance(got, str):
        return got
    label, value = got
    if args.hide_type:
        print(value)
    else:
        print(label, value) if value is not None else print(label)
    return None


def cmd_set(args) -> int | str | None:
    with _parameter_client(args) as (node, target, client):
        param = Parameter(name=args.parameter_name, value=get_parameter_value(string_value=args.value))
        result = _call(node, client.set_parameters([param])).results[0]
    if result.successful:
        print("Set parameter successful" + (f": {result.reason}" if result.reason else ""))
    else:
        print("Setting parameter failed" + (f": {result.reason}" if result.reason else ""), file=sys.stderr)
    return None


def _insert(d: dict, dotted: str, value) -> None:
    head, _, rest = dotted.partition(".")
    if rest:
        _insert(d.setdefault(head, {}), rest, value)
    else:
        d[dotted] = value


def cmd_dump(args) -> int | str | None:
    with _parameter_client(args) as (node, target, client):
        names = sorted(_call(node, client.list_parameters()).result.names)
        values = _call(node, client.get_parameters(names)).values
    params: dict = {}
    for name, pv in zip(names, values):
        _insert(params, name, parameter_value_to_python(pv))
    print(dump({target: {"ros__parameters": params}}))
    return None


def cmd_describe(args) -> int | str | None:
    with _parameter_client(args) as (node, target, client):
        descriptors = _call(node, client.describe_parameters(args.parameter_names)).descriptors
    for d in descriptors:
        print(f"Parameter name: {d.name}")
        print(f"  Type: {TYPE_NAMES.get(d.type, d.type)}")
        if d.description:
            print(f"  Description: {d.description}")
        if d.additional_constraints or d.read_only or d.floating_point_range or d.integer_range:
            print("  Constraints:")
            if d.read_only:
                print("    Read only: true")
            if d.dynamic_typing:
                print("    Dynamic typing: true")
            if d.additional_constraints:
                print(f"    Additional constraints: {d.additional_constraints}")
            for r in d.integer_range:
                print(f"    Min value: {r.from_value}\n    Max value: {r.to_value}")
                if r.step:
                    print(f"    Step: {r.step}")
            for r in d.floating_point_range:
                print(f"    Min value: {r.from_value}\n    Max value: {r.to_value}")
                if r.step:
                    print(f"    Step: {r.step}")
    return None


def _node_args(p: argparse.ArgumentParser, *, optional: bool = False, timeout: bool = True) -> None:
    graph.add_node_arguments(p)
    p.add_argument("node_name", nargs="?" if optional else None, help="Name of the ROS node")
    p.add_argument("--include-hidden-nodes", action="store_true", help="Consider hidden nodes as well")
    if timeout:
        p.add_argument("--timeout", metavar="N", type=int, default=1,
                       help="Wait at least N seconds until node becomes available (default %(default)s sec; "
                            "the front-end waits up to 4 s whatever N)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("list", help="Output a list of available parameters")
    _node_args(p, optional=True, timeout=False)
    p.add_argument("--filter", nargs=1, help="Only parameters matching the regex expression will be showed.")
    p.add_argument("--param-prefixes", nargs="+", default=[], help="Only list parameters with the provided prefixes")
    p.add_argument("--param-type", action="store_true", help="Print parameter types with parameter names")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("get", help="Get parameter")
    _node_args(p)
    p.add_argument("parameter_name", help="Name of the parameter")
    p.add_argument("--hide-type", action="store_true", help="Hide the type information")
    p.set_defaults(func=cmd_get)

    p = sub.add_parser("set", help="Set parameter")
    _node_args(p)
    p.add_argument("parameter_name", help="Name of the parameter")
    p.add_argument("value", help="Value of the parameter")
    p.set_defaults(func=cmd_set)

    p = sub.add_parser("dump", help="Show all of the parameters of a node in a YAML file format")
    _node_args(p)
    p.set_defaults(func=cmd_dump)

    p = sub.add_parser("describe", help="Show descriptive information about declared parameters")
    _node_args(p)
    p.add_argument("parameter_names", nargs="+", help="Names of the parameters")
    p.set_defaults(func=cmd_describe)
