"""`ros2 lifecycle nodes|get|set|list`, through the standard lifecycle services."""
from __future__ import annotations

import argparse
import sys

from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState

from trainer.ros2cli import graph

TIMEOUT_S = 5.0


def lifecycle_nodes(node, include_hidden: bool = False) -> list[str]:
    services = node.get_service_names_and_types()
    return sorted(n.full_name for n in graph.node_names(node, include_hidden)
                  if any(s == f"{n.full_name}/get_state" and "lifecycle_msgs/srv/GetState" in t
                         for s, t in services))


def _call(node, srv_type, service: str, request):
    client = node.create_client(srv_type, service)
    try:
        if not client.wait_for_service(timeout_sec=TIMEOUT_S):
            raise RuntimeError(f"service {service} not available")
        result = graph.spin_until_future(node, client.call_async(request), TIMEOUT_S)
        if result is None:
            raise RuntimeError(f"no answer from {service} within {TIMEOUT_S:g} s")
        return result
    finally:
        node.destroy_client(client)


def get_state(node, full_name: str):
    return _call(node, GetState, f"{full_name}/get_state", GetState.Request()).current_state


def transitions(node, full_name: str, *, all_: bool = False):
    service = f"{full_name}/get_transition_graph" if all_ else f"{full_name}/get_available_transitions"
    return _call(node, GetAvailableTransitions, service, GetAvailableTransitions.Request()).available_transitions


def change_state(node, full_name: str, transition) -> bool:
    return _call(node, ChangeState, f"{full_name}/change_state", ChangeState.Request(transition=transition)).success


def cmd_nodes(args) -> int | str | None:
    with graph.direct_node(args) as node:
        names = lifecycle_nodes(node, args.all)
    if args.count_nodes:
        print(len(names))
    elif names:
        print(*names, sep="\n")
    return None


def cmd_get(args) -> int | str | None:
    with graph.direct_node(args, discover=not args.node_name) as node:
        target = graph.absolute(args.node_name)
        if target and not graph.wait_for_node(node, target, args.include_hidden_nodes):
            return "Node not found"
        wanted = [target] if target else lifecycle_nodes(node, args.include_hidden_nodes)
        for name in sorted(wanted):
            try:
                state = get_state(node, name)
            except RuntimeError as exc:
                print(f"Exception while calling service of node '{name}': {exc}", file=sys.stderr)
                if target:
                    return 1
                continue
            print(("" if target else f"{name}: ") + f"{state.label} [{state.id}]")
    return None


def cmd_set(args) -> int | str | None:
    with graph.direct_node(args, discover=False) as node:
        target = graph.absolute(args.node_name)
        if not graph.wait_for_node(node, target, args.include_hidden_nodes):
            return "Node not found"
        try:
            available = transitions(node, target)
        except RuntimeError as exc:
            return f"Exception while calling service of node '{args.node_name}': {exc}"
        chosen = next((t.transition for t in available if t.transition.label == args.transition), None) or \
            next((t.transition for t in available if str(t.transition.id) == args.transition), None)
        if chosen is None:
            return "Unknown transition requested, available ones are:" + "".join(
                f"\n- {t.transition.label} [{t.transition.id}]" for t in available)
        try:
            ok = change_state(node, target, chosen)
        except RuntimeError as exc:
            print(f"Exception while calling service of node '{args.node_name}': {exc}", file=sys.stderr)
            return None
    if ok:
        print("Transitioning successful")
    else:
        print("Transitioning failed", file=sys.stderr)
    return None


def cmd_list(args) -> int | str | None:
    with graph.direct_node(args, discover=False) as node:
        target = graph.absolute(args.node_name)
        if not graph.wait_for_node(node, target, args.include_hidden_nodes):
            return "Node not found"
        try:
            listed = transitions(node, target, all_=args.all)
        except RuntimeError as exc:
            return f"Exception while calling service of node '{args.node_name}': {exc}"
    for t in listed:
        print(f"- {t.transition.label} [{t.transition.id}]\n\tStart: {t.start_state.label}\n\tGoal: {t.goal_state.label}")
    return None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("nodes", help="Output a list of nodes with lifecycle")
    graph.add_node_arguments(p)
    p.add_argument("-a", "--all", action="store_true", help="Display all nodes even hidden ones")
    p.add_argument("-c", "--count-nodes", action="store_true", help="Only display the number of nodes discovered")
    p.set_defaults(func=cmd_nodes)

    for verb, helptext, func in (("get", "Get lifecycle state for one or more nodes", cmd_get),
                                 ("set", "Trigger lifecycle state transition", cmd_set),
                                 ("list", "Output a list of available transitions", cmd_list)):
        p = sub.add_parser(verb, help=helptext)
        graph.add_node_arguments(p)
        p.add_argument("node_name", nargs="?" if verb == "get" else None,
                       help="Name of the ROS node" + (". If no name is provided, then get the state for all "
                                                      "nodes." if verb == "get" else ""))
        p.add_argument("--include-hidden-nodes", action="store_true", help="Consider hidden nodes as well")
        if verb == "set":
            p.add_argument("transition", help="The lifecycle transition")
        if verb == "list":
            p.add_argument("-a", "--all", action="store_true", help="Display all existing transitions")
        p.set_defaults(func=func)
