"""The Fast DDS Discovery Server for a fleet: a server address instead of multicast discovery.

Every process of a fleet is a Fast DDS discovery *client* of one server, `HOST:PORT` in
`ROS_DISCOVERY_SERVER` (a `;`-separated list for several servers, the position being the
server id): it announces itself to the server and learns from it the endpoints it shares a
topic with, so no participant needs multicast or to know the others' addresses. Processes
that must see the whole graph without sharing its topics are *super clients*
(`ROS_SUPER_CLIENT=TRUE`): the launcher's readiness checks (trainer/launch/rosgraph.py), the recorder
(it picks topics and types from the graph) and the `ros2` front-end. Bridges, policy nodes
and random actors stay plain clients: they only hear about the topics they use, which is what
keeps discovery traffic small as the fleet grows (msgs_docs/scaling.md).

    protocad-discovery-server                      # a server on 127.0.0.1:11811, foreground
    protocad-discovery-server --listen 10.0.0.5:11811  # reachable on that interface (see
                                                       # --print-profile and msgs_docs/security.md)

The server is the `fast-discovery-server` executable the ROS wheels install into the
environment's `bin/`; it needs the wheels' libraries on LD_LIBRARY_PATH, which every Python
process of this environment has (the wheels' bootstrapper sets it), so it is started from
here rather than from a shell.
"""
from __future__ import annotations

import argparse
import ipaddress
import os
import shutil
import socket
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from trainer.console import wait_until
from trainer.settings import arg, build, settings_parser

DEFAULT_PORT = 11811
LOCALHOST = "127.0.0.1"
SERVER_ENV = "ROS_DISCOVERY_SERVER"
SUPER_ENV = "ROS_SUPER_CLIENT"


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.strip().rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"expected HOST:PORT with a port in 1..65535 (e.g. 127.0.0.1:{DEFAULT_PORT}), got {text!r}")
    return host, int(port)


def parse_server_list(text: str) -> str:
    """A ROS_DISCOVERY_SERVER value, checked: `HOST:PORT` entries separated by `;` (an empty
    entry keeps a server id's position free); ValueError naming what is wrong."""
    entries = [e.strip() for e in str(text).split(";")]
    if not any(entries):
        raise ValueError(f"expected HOST:PORT, got {text!r}")
    for e in entries:
        if e:
            _host_port(e)
    return ";".join(entries)


def parse_listen(text: str) -> tuple[str, int]:
    """`PORT` or `HOST:PORT` for a server to listen on (HOST an IP address; default 127.0.0.1)."""
    text = str(text).strip()
    if text.isdigit():
        text = f"{LOCALHOST}:{text}"
    try:
        host, port = _host_port(text)
    except ValueError:
        raise ValueError(f"expected PORT or HOST:PORT with a port in 1..65535, got {text!r}") from None
    try:
        ipaddress.ip_address(host)
    except ValueError:
        raise ValueError(f"expected [HOST:]PORT with HOST an IP address, got {host!r}") from None
    return host, port


def connect_address(host: str, port: int) -> str:
    """How processes on this machine reach a server listening on host:port."""
    return f"{LOCALHOST if host in ('0.0.0.0', '::') else host}:{port}"


def _argtype(parse: Callable[[str], object]):
    def conv(text: str):
        try:
            return parse(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    conv.__name__ = parse.__name__
    return conv


server_list_arg = _argtype(parse_server_list)
listen_arg = _argtype(parse_listen)
DEFAULT_LISTEN = (LOCALHOST, DEFAULT_PORT)


@dataclass
class DiscoverySettings:
    """--discovery-server / --start-discovery-server, the same on every launcher that starts
    nodes (a base of its settings)."""

    discovery_server: str | None = arg(None, type=server_list_arg, metavar="HOST:PORT", exclusive="discovery")
    """discover through this running Fast DDS Discovery Server instead of multicast (sets
    ROS_DISCOVERY_SERVER for every node; default: $ROS_DISCOVERY_SERVER if set)"""
    start_discovery_server: tuple | None = arg(None, type=listen_arg, nargs="?", const=DEFAULT_LISTEN,
                                               metavar="[HOST:]PORT", exclusive="discovery")
    """start a Discovery Server (fast-discovery-server, default 127.0.0.1:11811) before the
    nodes, stop it after them, and discover through it; listen on this machine's fleet-facing
    address to let actor groups on other machines join (0.0.0.0 works but exposes it everywhere)"""


def from_args(a: Any) -> tuple[str | None, tuple[str, int] | None]:
    """(server address to use, (host, port) to start one on) from DiscoverySettings' fields (or
    settings with those fields; a saved [host, port] list becomes a tuple again)."""
    start = getattr(a, "start_discovery_server", None)
    return getattr(a, "discovery_server", None), tuple(start) if start is not None else None


def apply_env(env: dict[str, str], server: str | None, *, super_client: bool) -> dict[str, str]:
    """Make `env` a discovery client of `server` (a super client if asked), or, without a
    server, drop the discovery-server variables so that it discovers the usual way."""
    env.pop(SUPER_ENV, None)
    if server:
        env[SERVER_ENV] = server
        if super_client:
            env[SUPER_ENV] = "TRUE"
    else:
        env.pop(SERVER_ENV, None)
    return env


def server_executable() -> str:
    exe = Path(sys.prefix) / "bin" / "fast-discovery-server"
    if exe.exists():
        return str(exe)
    found = shutil.which("fast-discovery-server")
    if not found:
        raise FileNotFoundError("fast-discovery-server not found (it ships with the ros-jazzy Fast DDS wheels "
                                f"in {exe.parent}/)")
    return found


def exposure_warning(host: str) -> str | None:
    """What to tell a user who makes a server listen on every interface, or None."""
    if host not in ("0.0.0.0", "::"):
        return None
    return (f"WARNING: listening on {host}: every network this machine is on reaches the server "
            "and, through it, the ROS domain, where any participant can publish actions, "
            "resets or checkpoints (msgs_docs/security.md). Listen on the fleet's own interface "
            "address, on a private network or behind a firewall, and give the fleet's processes "
            "a Fast DDS profile that allows that interface.")


def fleet_profile(addresses: list[str]) -> str:
    """The environment's Fast DDS profile (sim_bridge/fastdds_discovery.xml) with these
    interface addresses allowed beside 127.0.0.1: what every process of a fleet across
    machines needs, each machine with its own fleet-facing address."""
    for a in addresses:
        ipaddress.IPv4Address(a)   # ValueError for anything but one IPv4 address
    name = "fastdds_discovery.xml"
    installed = Path(sys.prefix) / "share" / "sim_bridge" / name
    tree = Path(__file__).resolve().parents[2] / "sim_bridge" / name
    text = (installed if installed.exists() else tree).read_text()
    loopback = "<address>127.0.0.1</address>"
    return text.replace(loopback, loopback + "".join(f"<address>{a}</address>" for a in addresses), 1)


def server_command(host: str, port: int, server_id: int = 0) -> list[str]:
    return [server_executable(), "-i", str(server_id), "-l", host, "-p", str(port)]


def free_port(host: str = LOCALHOST) -> int:
    """A UDP port nobody on this machine holds right now (for tests and benchmarks)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _socket_inodes(pid: int) -> set[str]:
    out = set()
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return out
    for fd in fds:
        try:
            link = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            out.add(link[8:-1])
    return out


def udp_listening(pid: int, port: int) -> bool:
    """Whether process `pid` itself holds a UDP socket bound to `port` (read from /proc, so a
    socket of another process on that port does not count)."""
    inodes = _socket_inodes(pid)
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if len(f) > 9 and int(f[1].rsplit(":", 1)[1], 16) == port and f[9] in inodes:
                return True
    return False


def wait_listening(pid: int, port: int, alive: Callable[[], str | None], timeout: float = 20.0) -> None:
    """Block until the server process listens on its port; RuntimeError if it exits first,
    TimeoutError if it does not within `timeout`."""
    wait_until(lambda: udp_listening(pid, port), what=f"discovery server listening on UDP port {port}",
               timeout=timeout, alive=alive)


@dataclass
class DiscoveryServerSettings:
    """protocad-discovery-server's options."""

    listen: tuple = arg(DEFAULT_LISTEN, type=listen_arg, metavar="[HOST:]PORT")
    """address to listen on (default 127.0.0.1:11811: this machine only; this machine's
    fleet-facing address for other machines; 0.0.0.0 is warned about)"""
    server_id: int = 0
    """the server's position in ROS_DISCOVERY_SERVER lists of several servers"""
    print_profile: list[str] | None = arg(None, metavar="ADDRESS")
    """print the environment's Fast DDS profile with these interface addresses allowed beside
    127.0.0.1 (for FASTRTPS_DEFAULT_PROFILES_FILE on a fleet's machines) and exit"""


def build_parser() -> argparse.ArgumentParser:
    return settings_parser("protocad-discovery-server", __doc__.split("\n\n")[0], [(None, DiscoveryServerSettings)],
                           epilog=f"Then, in every shell of the fleet: export {SERVER_ENV}=HOST:PORT (and "
                                  f"{SUPER_ENV}=TRUE for ros2 topic/node introspection), or give the launchers "
                                  "--discovery-server HOST:PORT.")


def main(argv: Sequence[str] | None = None) -> int:
    a = build(DiscoveryServerSettings, vars(build_parser().parse_args(argv)))
    if a.print_profile:
        try:
            print(fleet_profile(a.print_profile), end="")
        except ValueError as exc:
            print(f"protocad-discovery-server: error: --print-profile: {exc}", file=sys.stderr)
            return 2
        return 0
    host, port = a.listen
    try:
        cmd = server_command(host, port, a.server_id)
    except FileNotFoundError as exc:
        print(f"protocad-discovery-server: error: {exc}", file=sys.stderr)
        return 2
    print(f"[discovery] {' '.join(cmd)}\n[discovery] clients: export {SERVER_ENV}={connect_address(host, port)}",
          flush=True)
    warning = exposure_warning(host)
    if warning:
        print(f"[discovery] {warning}", file=sys.stderr, flush=True)
    os.execv(cmd[0], cmd)


if __name__ == "__main__":
    sys.exit(main())
