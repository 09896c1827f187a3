"""The installed ament layout: what `ros2 run` (real or our front-end) resolves.

These run against the environment the README's commands build (scripts/protocad installs
this checkout into .venv), not against the working tree.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import ROOT

PREFIX = Path(sys.prefix)
ROS2 = PREFIX / "bin" / "ros2"
EXECUTABLES = {
    "sim_bridge": {"node"},
    "protocad_ros": {"policy"},
    "trainer": {"record", "train", "evaluate", "loop", "online", "visualize", "checkpoint_publisher"},
}

pytestmark = pytest.mark.skipif(not ROS2.exists(), reason="protocad-ros is not installed in this Python (run scripts/protocad setup)")


def ros2(*args: str, env: dict | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([str(ROS2), *args], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "AMENT_PREFIX_PATH": str(PREFIX), **(env or {})})


def test_ament_python_layout_is_installed():
    for pkg, exes in EXECUTABLES.items():
        assert (PREFIX / "share/ament_index/resource_index/packages" / pkg).is_file()
        xml = (PREFIX / "share" / pkg / "package.xml").read_text()
        assert f"<name>{pkg}</name>" in xml and "ament_python" in xml
        for exe in exes:
            path = PREFIX / "lib" / pkg / exe
            assert path.is_file() and os.access(path, os.X_OK), path


@pytest.mark.process
def test_front_end_lists_packages_and_executables():
    listed = ros2("pkg", "executables").stdout.split("\n")
    for pkg, exes in EXECUTABLES.items():
        for exe in exes:
            assert f"{pkg} {exe}" in listed
    assert "sim_bridge" in ros2("pkg", "list").stdout.split()
    assert ros2("pkg", "prefix", "trainer").stdout.strip() == str(PREFIX)


@pytest.mark.process
@pytest.mark.parametrize("pkg,exe", [("sim_bridge", "node"), ("protocad_ros", "policy"), ("trainer", "record")])
def test_ros2_run_resolves_node_help(pkg, exe):
    out = ros2("run", pkg, exe, "--help")
    assert out.returncode == 0, out.stderr
    assert "usage" in out.stdout.lower()


@pytest.mark.process
def test_front_end_errors_are_clear():
    out = ros2("run", "sim_bridge", "no_such_exe")
    assert out.returncode != 0 and "No executable found" in out.stderr and "node" in out.stderr
    out = ros2("run", "no_such_pkg", "node")
    assert out.returncode != 0 and "not found" in out.stderr
    out = ros2("launch", "sim_bridge", "x.launch.py")
    assert out.returncode == 2 and "not supported" in out.stderr and "ros2 run" in out.stderr
    out = ros2("topic", "--help")   # the graph verbs resolve in the installed package too
    assert out.returncode == 0 and "echo" in out.stdout and "hz" in out.stdout


@pytest.mark.process
def test_front_end_defers_to_a_real_ros2cli(tmp_path):
    # Stand-in (named as such): ros2cli cannot be installed here, so a script playing the real
    # `ros2` later on PATH shows the front-end hands every call over to it.
    fake = tmp_path / "ros2"
    fake.write_text("#!/bin/sh\necho \"stand-in real ros2cli: $*\"\n")
    fake.chmod(0o755)
    env = {"PATH": f"{PREFIX / 'bin'}{os.pathsep}{tmp_path}{os.pathsep}{os.environ['PATH']}"}
    out = ros2("topic", "list", env=env)
    assert out.returncode == 0 and out.stdout.strip() == "stand-in real ros2cli: topic list"


def _participant_log(profile: Path) -> str:
    """What Fast DDS prints while an rclpy participant starts with `profile` as its defaults."""
    code = ("import rclpy; from rclpy.node import Node; rclpy.init(); n = Node('profile_check'); "
            "n.destroy_node(); rclpy.shutdown(); print('started')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "FASTRTPS_DEFAULT_PROFILES_FILE": str(profile)})
    assert r.returncode == 0, r.stderr
    return r.stdout + r.stderr


@pytest.mark.ros
@pytest.mark.process
def test_the_environment_sets_a_discovery_profile_fast_dds_loads(tmp_path):
    root = ROOT
    tree = root / "sim_bridge" / "fastdds_discovery.xml"
    env = {k: v for k, v in os.environ.items() if k != "FASTRTPS_DEFAULT_PROFILES_FILE"}

    def exported(extra: dict) -> str:
        r = subprocess.run(["bash", "-c", f"source {root}/scripts/env.sh; echo $FASTRTPS_DEFAULT_PROFILES_FILE"],
                           capture_output=True, text=True, env={**env, **extra}, timeout=30)
        return r.stdout.strip()

    assert Path(exported({})) == tree                                # the environment's default
    assert exported({"FASTRTPS_DEFAULT_PROFILES_FILE": "/mine.xml"}) == "/mine.xml"   # a user's own wins
    installed = PREFIX / "share" / "sim_bridge" / "fastdds_discovery.xml"
    assert installed.read_bytes() == tree.read_bytes()
    assert "XMLPARSER" not in _participant_log(tree)
    # The check can fail: a profile Fast DDS cannot parse is reported on start-up.
    bad = tmp_path / "bad.xml"
    bad.write_text(tree.read_text().replace("<sec>0</sec>", "<sec>zero</sec>", 1))
    assert "XMLPARSER" in _participant_log(bad)


def _udp_sockets(pid: int) -> list[tuple[str, int, int]]:
    """(local IPv4 address, port, bytes queued unread) of every UDP socket process `pid` holds,
    from /proc (no ss needed)."""
    import socket
    import struct

    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    out = []
    for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
        f = line.split()
        if f[9] in inodes:
            hexaddr, hexport = f[1].split(":")
            addr = socket.inet_ntoa(struct.pack("<I", int(hexaddr, 16)))
            out.append((addr, int(hexport, 16), int(f[4].split(":")[1], 16)))
    return out


@pytest.mark.ros
@pytest.mark.process
def test_dds_reads_only_loopback_sockets_in_the_default_environment():
    """With the environment's profile, every socket Fast DDS receives on is bound to 127.0.0.1;
    the others (send-only, rmw_fastrtps's LOCALHOST mode) are never read."""
    import socket
    import time

    from helpers import wait_until

    domain = int(os.environ["ROS_DOMAIN_ID"])
    code = ("import rclpy, time; from std_msgs.msg import String; rclpy.init(); "
            "n = rclpy.create_node('socket_check'); p = n.create_publisher(String, 'x', 10); "
            "print('up', flush=True); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"})
    try:
        assert proc.stdout.readline().strip() == "up"
        wait_until(lambda: len(_udp_sockets(proc.pid)) >= 3, 30, "the participant's sockets")
        socks = _udp_sockets(proc.pid)
        base = 7400 + 250 * domain      # RTPS well-known ports of this domain
        rtps = [s for s in socks if base <= s[1] < base + 250]
        assert rtps and all(a == "127.0.0.1" for a, _, _ in rtps), socks
        other = [s for s in socks if s[0] == "0.0.0.0"]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for _, port, _ in other:
                tx.sendto(b"not rtps", ("127.0.0.1", port))
        time.sleep(0.5)   # proving a negative: a reader would drain them within one poll
        after = {(a, p): q for a, p, q in _udp_sockets(proc.pid)}
        for a, p, _ in other:
            assert after[(a, p)] > 0, f"{a}:{p} was read: it is a receiving socket beyond loopback"
    finally:
        proc.kill()
        proc.wait()


LAUNCH_FILE = ROOT / "trainer" / "ros_launch" / "protocad.launch.py"


@pytest.mark.process
def test_the_launch_file_is_installed_and_names_real_parameters():
    import ast

    installed = PREFIX / "share" / "trainer" / "launch" / "protocad.launch.py"
    assert installed.read_bytes() == LAUNCH_FILE.read_bytes()      # where `ros2 launch trainer` looks
    tree = ast.parse(LAUNCH_FILE.read_text())                         # valid Python without launch
    params = {k.value for node in ast.walk(tree) if isinstance(node, ast.Dict)
              for k in node.keys if isinstance(k, ast.Constant) and isinstance(k.value, str)}
    from protocad_ros.node.policy_params import PARAMS as POLICY
    from sim_bridge.bridge.params import PARAMS as BRIDGE
    known = {p.name for p in BRIDGE} | {p.name for p in POLICY}
    node_params = params - {"task", "split", "checkpoint", "output", "record", "max_episodes", "namespace"}
    assert {"checkpoint", "task", "split", "max_episodes", "min_subscribers"} <= known
    assert node_params <= known, node_params - known


@pytest.mark.process
def test_the_launch_file_parses_with_launch_ros():
    pytest.importorskip("launch", reason="ros2 launch is not installable from PyPI (needs a full ROS 2 install)")
    pytest.importorskip("launch_ros", reason="launch_ros is not installable from PyPI (needs a full ROS 2 install)")
    from launch.launch_description_sources import PythonLaunchDescriptionSource
    from launch_ros.actions import Node

    description = PythonLaunchDescriptionSource(str(LAUNCH_FILE)).get_launch_description(None)
    nodes = [e for e in description.entities if isinstance(e, Node)]
    assert len(nodes) == 3
