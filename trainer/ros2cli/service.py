"""`ros2 service list|type|call`, as ros2cli (Jazzy) prints them."""
from __future__ import annotations

import argparse
import sys
import time

import rclpy
import yaml

from trainer.ros2cli import graph
from trainer.ros2cli.msgyaml import interface_class, set_message_fields


def service_names_and_types(node, include_hidden: bool = False) -> list[tuple[str, list[str]]]:
    return [(n, t) for n, t in node.get_service_names_and_types() if include_hidden or not graph.is_hidden(n)]


def cmd_list(args) -> int | str | None:
    with graph.direct_node(args) as node:
        services = service_names_and_types(node, args.include_hidden_services)
    if args.count_services:
        print(len(services))
    else:
        for name, types in services:
            print(f"{name} [{', '.join(types)}]" if args.show_types else name)
    return None


def cmd_type(args) -> int | str | None:
    with graph.direct_node(args, discover=False) as node:   # wait for this one service instead
        graph.wait_for(lambda: args.service_name in dict(service_names_and_types(node, True)), node)
        types = dict(service_names_and_types(node, include_hidden=True)).get(args.service_name)
    if types is None:
        return "Unknown service name"
    print(*types, sep="\n")
    return None


def cmd_call(args) -> int | str | None:
    try:
        srv = interface_class(args.service_type, kind="srv")
        srv.Request, srv.Response  # noqa: B018  (a message type has neither)
    except ValueError:
        return "The passed service type is invalid"
    except AttributeError:
        return "The passed type is not a service"
    if args.rate is not None and args.rate <= 0:
        return "rate must be greater than zero"
    try:
        values = yaml.safe_load(sys.stdin.read() if args.stdin else args.values)
    except yaml.YAMLError as exc:
        return f"Failed to populate field: the values are not YAML: {exc}"
    request = srv.Request()
    try:
        set_message_fields(request, values)
    except Exception as exc:  # noqa: BLE001  any bad YAML shape is the user's to fix
        return f"Failed to populate field: {exc}"
    pkg, name = args.service_type.split("/")[0], args.service_type.split("/")[-1]
    with graph.direct_node(args, name=f"{graph.NODE_NAME_PREFIX}_requester_{pkg}_{name}", discover=False) as node:
        client = node.create_client(srv, args.service_name)
        if not client.service_is_ready():
            print("waiting for service to become available...")
            while rclpy.ok() and not client.wait_for_service(timeout_sec=1.0):
                pass
        period = 1.0 / args.rate if args.rate else None
        while True:
            print(f"requester: making request: {request!r}\n")
            started = time.time()
            future = client.call_async(request)
            rclpy.spin_until_future_complete(node, future)
            if future.result() is None:
                return f"Exception while calling service: {future.exception()!r}"
            print(f"response:\n{future.result()!r}\n")
            if period is None or not rclpy.ok():
                break
            time.sleep(max(0.0, started + period - time.time()))
    return None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("list", help="Output a list of available services")
    graph.add_node_arguments(p)
    p.add_argument("-t", "--show-types", action="store_true", help="Additionally show the service type")
    p.add_argument("-c", "--count-services", action="store_true", help="Only display the number of services discovered")
    p.add_argument("--include-hidden-services", action="store_true", help="Consider hidden services as well")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("type", help="Output a service's type")
    graph.add_node_arguments(p)
    p.add_argument("service_name", help="Name of the ROS service to get type (e.g. '/talker/list_parameters')")
    p.set_defaults(func=cmd_type)

    p = sub.add_parser("call", help="Call a service")
    p.add_argument("service_name", help="Name of the ROS service to call to (e.g. '/add_two_ints')")
    p.add_argument("service_type", help="Type of the ROS service (e.g. 'std_srvs/srv/Empty')")
    g = p.add_mutually_exclusive_group()
    g.add_argument("values", nargs="?", default="{}",
                   help="Values to fill the service request with in YAML format (e.g. '{a: 1, b: 2}'), otherwise "
                        "the service request will be published with default values")
    g.add_argument("--stdin", action="store_true", help="Read values from standard input")
    p.add_argument("-r", "--rate", metavar="N", type=float, help="Repeat the call at a specific rate in Hz")
    p.set_defaults(func=cmd_call)
