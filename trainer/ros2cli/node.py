"""`ros2 node list|info`, as ros2cli (Jazzy) prints them."""
from __future__ import annotations

import argparse
import sys

import rclpy.action

from trainer.ros2cli import graph


def cmd_list(args) -> int | str | None:
    with graph.direct_node(args) as node:
        names = sorted(n.full_name for n in graph.node_names(node, include_hidden=args.all))
    if args.count_nodes:
        print(len(names))
    elif names:
        if len(set(names)) < len(names):
            print("WARNING: Be aware that there are nodes in the graph that share an exact name, which can "
                  "have unintended side effects.", file=sys.stderr)
        print(*names, sep="\n")
    return None


def _section(title: str, names_and_types, include_hidden: bool) -> None:
    print(f"  {title}:")
    print(*[f"    {n}: {', '.join(t)}" for n, t in names_and_types if include_hidden or not graph.is_hidden(n)],
          sep="\n")


def cmd_info(args) -> int | str | None:
    target = graph.absolute(args.node_name)
    with graph.direct_node(args) as node:
        graph.wait_for_node(node, target, include_hidden=True)
        count = [n.full_name for n in graph.node_names(node, include_hidden=True)].count(target)
        if count == 0:
            return f"Unable to find node '{args.node_name}'"
        if count > 1:
            print(f"There are {count} nodes in the graph with the exact name \"{target}\". You are seeing "
                  "information about only one of them.", file=sys.stderr)
        nn = graph.parse_node_name(target)
        print(target)
        hidden = args.include_hidden
        _section("Subscribers", node.get_subscriber_names_and_types_by_node(nn.name, nn.namespace), hidden)
        _section("Publishers", node.get_publisher_names_and_types_by_node(nn.name, nn.namespace), hidden)
        _section("Service Servers", node.get_service_names_and_types_by_node(nn.name, nn.namespace), hidden)
        _section("Service Clients", node.get_client_names_and_types_by_node(nn.name, nn.namespace), hidden)
        _section("Action Servers",
                 rclpy.action.get_action_server_names_and_types_by_node(node, nn.name, nn.namespace), hidden)
        _section("Action Clients",
                 rclpy.action.get_action_client_names_and_types_by_node(node, nn.name, nn.namespace), hidden)
    return None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("list", help="Output a list of available nodes")
    graph.add_node_arguments(p)
    p.add_argument("-a", "--all", action="store_true", help="Display all nodes even hidden ones")
    p.add_argument("-c", "--count-nodes", action="store_true", help="Only display the number of nodes discovered")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("info", help="Output information about a node")
    graph.add_node_arguments(p)
    p.add_argument("node_name", help="Fully qualified node name to request information with Type")
    p.add_argument("--include-hidden", action="store_true", help="Display hidden topics, services, and actions as well")
    p.set_defaults(func=cmd_info)
