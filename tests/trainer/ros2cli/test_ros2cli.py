"""The `ros2` front-end's graph and bag verbs against a running sim bridge (a separate process,
over DDS), compared with the output ros2cli and rosbag2 (Jazzy) print for the same calls:
topic echo YAML, topic info, the hz summary, param get/set/dump, node info's sections, service
call's request/response lines and the `ros2 bag info` table. Formats and behaviour only; no
timing asserts (the rate hz prints is checked for consistency with its own min/max, not a value).
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys

import pytest
import yaml
from helpers import ROOT, Proc, wait_until
from helpers.ros import Probe, Responder

pytestmark = pytest.mark.process

TASK = "pendulum_swingup"
BRIDGE = "/protocad/sim_bridge"
START = 90.0


def ros2(*args: str, timeout: float = 60, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "trainer.ros2cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env={**os.environ, **(env or {})})


def ros2_graph(*args: str) -> subprocess.CompletedProcess:
    """A graph verb given ros2cli's --spin-time: without a daemon it answers from what discovery
    found so far: a participant is discovered at once or at the next announcement of the
    running ones (every 0.5 s with the suite's sim_bridge/fastdds_discovery.xml, 3 s without),
    and a CI machine under load adds to that."""
    return ros2(*args, "--spin-time", "3")


@pytest.fixture(scope="module")
def bridge(tmp_path_factory):
    """A real-time bridge that steps while something reads it (the probe's subscription)."""
    log = tmp_path_factory.mktemp("ros2cli") / "bridge.log"
    proc = Proc([sys.executable, "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}",
                 "-p", "mode:=realtime", "-p", "control_rate_hz:=50.0", "-p", "seed:=3",
                 "-p", "diagnostics_period_s:=0.2"], log)
    probe = Probe("ros2cli_test_probe")
    reader = Responder(probe, None, names=["torque"])   # reads image + step_info, answers nothing
    wait_until(lambda: len(reader.steps) >= 3, START, "the bridge to step")
    yield probe, proc
    probe.close()
    assert proc.stop() == 0
    assert "Traceback" not in proc.output()


@pytest.mark.ros
def test_node_list_and_info(bridge):
    out = ros2_graph("node", "list")
    assert out.returncode == 0, out.stderr
    names = out.stdout.split()
    assert BRIDGE in names and "/protocad/ros2cli_test_probe" in names
    assert not any(n.rsplit("/", 1)[-1].startswith("_") for n in names)   # hidden nodes (ours) not listed
    assert ros2_graph("node", "list", "-c").stdout.strip() == str(len(names))

    info = ros2_graph("node", "info", BRIDGE)
    assert info.returncode == 0, info.stderr
    lines = info.stdout.splitlines()
    assert lines[0] == BRIDGE
    sections = [ln.strip(" :") for ln in lines if re.fullmatch(r"  [A-Z][A-Za-z ]+:", ln)]
    assert sections == ["Subscribers", "Publishers", "Service Servers", "Service Clients", "Action Servers",
                        "Action Clients"]
    body = info.stdout
    assert "    /protocad/action: sensor_msgs/msg/JointState" in body
    assert "    /protocad/image: sensor_msgs/msg/Image" in body
    assert "    /protocad/reset: std_srvs/srv/Trigger" in body
    assert f"    {BRIDGE}/set_parameters: rcl_interfaces/srv/SetParameters" in body
    missing = ros2("node", "info", "/protocad/nobody")
    assert missing.returncode == 1 and "Unable to find node '/protocad/nobody'" in missing.stderr


@pytest.mark.ros
def test_topic_list_and_info(bridge):
    out = ros2_graph("topic", "list", "-t")
    assert out.returncode == 0, out.stderr
    assert "/protocad/image [sensor_msgs/msg/Image]" in out.stdout.splitlines()
    assert "/clock [rosgraph_msgs/msg/Clock]" in out.stdout.splitlines()
    plain = ros2_graph("topic", "list").stdout.splitlines()
    assert plain == sorted(plain) and "/protocad/step_info" in plain

    info = ros2_graph("topic", "info", "/protocad/image")
    assert info.returncode == 0, info.stderr
    lines = info.stdout.splitlines()
    assert lines[0] == "Type: sensor_msgs/msg/Image" and lines[1] == "Publisher count: 1"
    assert re.fullmatch(r"Subscription count: [1-9]\d*", lines[2]) and len(lines) == 3
    verbose = ros2_graph("topic", "info", "-v", "/protocad/image").stdout
    for needle in ("Node name: sim_bridge", "Node namespace: /protocad", "Topic type: sensor_msgs/msg/Image",
                   "Endpoint type: PUBLISHER", "Reliability: RELIABLE", "Durability: VOLATILE"):
        assert needle in verbose, (needle, verbose)
    unknown = ros2("topic", "info", "/protocad/nope")
    assert unknown.returncode == 1 and unknown.stderr.strip() == "Unknown topic '/protocad/nope'"


@pytest.mark.ros
def test_topic_echo_prints_ros2cli_yaml(bridge):
    # The latched bridge_info is deterministic: the whole text is ros2cli's block YAML.
    out = ros2("topic", "echo", "/protocad/bridge_info", "--once")
    assert out.returncode == 0, out.stderr
    assert out.stdout == (
        "header:\n  stamp:\n    sec: 0\n    nanosec: 0\n  frame_id: pendulum_swingup\n"
        "name:\n- torque\n- '@control_dt'\n- '@image_size'\n"
        "position:\n- 0.0\n- 0.04\n- 64.0\nvelocity: []\neffort: []\n---\n")

    img = ros2("topic", "echo", "/protocad/image", "--once")
    doc = yaml.safe_load(img.stdout.split("\n---\n")[0])
    assert list(doc) == ["header", "height", "width", "encoding", "is_bigendian", "step", "data"]
    assert (doc["height"], doc["width"], doc["encoding"], doc["step"]) == (64, 64, "rgb8", 192)
    assert len(doc["data"]) == 129 and doc["data"][-1] == "..."    # truncated at 128 like ros2cli
    assert all(isinstance(v, int) and 0 <= v < 256 for v in doc["data"][:128])
    no_arr = yaml.safe_load(ros2("topic", "echo", "/protocad/image", "--once", "--no-arr").stdout.split("---")[0])
    assert no_arr["data"] == "<sequence type: uint8, length: 12288>"
    stamp = yaml.safe_load(ros2("topic", "echo", "/protocad/step_info", "--once", "--field",
                                "header.stamp").stdout.split("---")[0])
    assert set(stamp) == {"sec", "nanosec"} and stamp["nanosec"] % 20_000_000 == 0   # control_dt = 20 ms steps
    csv = ros2("topic", "echo", "/protocad/step_info", "--once", "--csv").stdout.strip().split(",")
    assert csv[3:5] == ["reward", "discount"]    # sec, nanosec, frame_id, then the names
    bad = ros2("topic", "echo", "/protocad/step_info", "--once", "--field", "nope")
    assert bad.returncode == 1 and "Invalid field 'nope'" in bad.stderr
    picked = yaml.safe_load(ros2("topic", "echo", "/protocad/step_info", "--once", "--filter",
                                 "m.header.stamp.sec >= 0").stdout.split("---")[0])
    assert picked["name"][:2] == ["reward", "discount"]
    failing = ros2("topic", "echo", "/protocad/step_info", "--once", "--filter", "m.nope > 0")
    assert failing.returncode == 1 and "--filter 'm.nope > 0' failed on a message: AttributeError" in failing.stderr
    assert "Traceback" not in failing.stderr


@pytest.mark.ros
def test_topic_hz_prints_the_ros2cli_summary(bridge, tmp_path):
    log = tmp_path / "hz.log"
    with open(log, "w") as fh:
        p = subprocess.Popen([sys.executable, "-m", "trainer.ros2cli", "topic", "hz", "/protocad/step_info"],
                             stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)
        pattern = re.compile(r"average rate: (\d+\.\d{3})\n\tmin: (\d+\.\d{3})s max: (\d+\.\d{3})s "
                             r"std dev: (\d+\.\d{5})s window: (\d+)\n")
        try:
            wait_until(lambda: len(pattern.findall(log.read_text())) >= 2, 60, "two hz reports")
        finally:
            os.killpg(p.pid, signal.SIGINT)
            assert p.wait(20) == 0                     # Ctrl-C ends hz cleanly
    reports = pattern.findall(log.read_text())
    windows = [int(r[4]) for r in reports]
    assert windows == sorted(windows) and windows[0] >= 2
    for rate, lo, hi, std, _ in reports:
        assert float(lo) <= float(hi) and float(std) >= 0
        assert float(lo) - 1e-3 <= 1.0 / float(rate) <= float(hi) + 1e-3   # mean interval within [min, max]
    assert "Traceback" not in log.read_text()


@pytest.mark.ros
def test_param_list_get_set_dump(bridge):
    probe, _ = bridge
    listed = ros2("param", "list", BRIDGE)
    assert listed.returncode == 0, listed.stderr
    names = listed.stdout.splitlines()
    assert "  task" in names and "  control_rate_hz" in names and names == sorted(names)
    assert "  task (type: string)" in ros2("param", "list", BRIDGE, "--param-type").stdout.splitlines()
    every = ros2_graph("param", "list").stdout.splitlines()
    assert f"{BRIDGE}:" in every and "  use_sim_time" in every

    assert ros2("param", "get", BRIDGE, "task").stdout == f"String value is: {TASK}\n"
    assert ros2("param", "get", BRIDGE, "seed").stdout == "Integer value is: 3\n"
    assert ros2("param", "get", BRIDGE, "task", "--hide-type").stdout == f"{TASK}\n"
    undeclared = ros2("param", "get", BRIDGE, "nope")
    assert undeclared.returncode == 1 and undeclared.stderr == "Parameter not set\n"

    ok = ros2("param", "set", BRIDGE, "control_rate_hz", "40.0")
    assert ok.returncode == 0 and ok.stdout == "Set parameter successful\n", ok.stderr
    assert ros2("param", "get", BRIDGE, "control_rate_hz").stdout == "Double value is: 40.0\n"
    wait_until(lambda: probe.node_diag("sim_bridge").get("control_rate_hz") in ("40", "40.0"), 20,
               "the bridge to run at the new rate")
    refused = ros2("param", "set", BRIDGE, "control_rate_hz", "5000.0")
    assert refused.returncode == 0 and refused.stdout == ""           # ros2cli: exit 0, reason on stderr
    assert refused.stderr.startswith("Setting parameter failed: ") and "1000" in refused.stderr
    assert ros2("param", "get", BRIDGE, "control_rate_hz").stdout == "Double value is: 40.0\n"
    read_only = ros2("param", "set", BRIDGE, "task", "walker_walk")
    assert read_only.stderr.startswith("Setting parameter failed: ")
    assert ros2("param", "get", "/protocad/nobody", "task").stderr.strip() == "Node not found"

    dumped = yaml.safe_load(ros2("param", "dump", BRIDGE).stdout)
    params = dumped[BRIDGE]["ros__parameters"]
    assert params["task"] == TASK and params["seed"] == 3 and params["control_rate_hz"] == 40.0
    assert params["qos_overrides"]["/protocad/image"]["publisher"]["reliability"] == "reliable"

    described = ros2("param", "describe", BRIDGE, "control_rate_hz").stdout
    assert described.startswith("Parameter name: control_rate_hz\n  Type: double\n")
    assert "    Min value: 0.0\n    Max value: 1000.0" in described


@pytest.mark.ros
def test_service_list_and_call(bridge):
    listed = ros2_graph("service", "list", "-t").stdout.splitlines()
    assert "/protocad/reset [std_srvs/srv/Trigger]" in listed
    assert ros2("service", "type", "/protocad/reset").stdout == "std_srvs/srv/Trigger\n"
    out = ros2("service", "call", "/protocad/reset", "std_srvs/srv/Trigger")
    assert out.returncode == 0, out.stderr
    m = re.fullmatch(r"(waiting for service to become available\.\.\.\n)?"
                     r"requester: making request: std_srvs\.srv\.Trigger_Request\(\)\n\n"
                     r"response:\nstd_srvs\.srv\.Trigger_Response\(success=True, message='(.+)'\)\n\n", out.stdout)
    assert m, out.stdout
    assert "started" in m.group(2)
    bad = ros2("service", "call", "/protocad/reset", "std_srvs/srv/Nope")
    assert bad.returncode == 1 and bad.stderr.strip() == "The passed service type is invalid"
    bad_field = ros2("service", "call", "/protocad/reset", "std_srvs/srv/Trigger", "{nope: 1}")
    assert bad_field.returncode == 1 and bad_field.stderr.startswith("Failed to populate field:")


@pytest.mark.ros
def test_lifecycle_nodes_get_list_set(bridge):
    probe, _ = bridge
    assert BRIDGE in ros2_graph("lifecycle", "nodes").stdout.splitlines()
    assert ros2("lifecycle", "get", BRIDGE).stdout == "active [3]\n"
    listed = ros2("lifecycle", "list", BRIDGE).stdout
    assert "- deactivate [4]\n\tStart: active\n\tGoal: deactivating\n" in listed
    wrong = ros2("lifecycle", "set", BRIDGE, "configure")
    assert wrong.returncode == 1 and wrong.stderr.startswith(
        "Unknown transition requested, available ones are:\n- deactivate [4]\n")
    try:
        out = ros2("lifecycle", "set", BRIDGE, "deactivate")
        assert out.returncode == 0 and out.stdout == "Transitioning successful\n", out.stderr
        assert ros2("lifecycle", "get", BRIDGE).stdout == "inactive [2]\n"
        wait_until(lambda: probe.node_diag("sim_bridge").get("lifecycle_state") == "inactive", 20,
                   "the bridge to report itself inactive")
    finally:
        assert ros2("lifecycle", "set", BRIDGE, "activate").stdout == "Transitioning successful\n"
    assert ros2("lifecycle", "get", BRIDGE).stdout == "active [3]\n"
    assert ros2("lifecycle", "get", "/protocad/nobody").stderr.strip() == "Node not found"


def test_bag_info_prints_the_rosbag2_table(tmp_path):
    from sensor_msgs.msg import JointState

    from trainer.bag.rosmsg import encode
    from trainer.bag.writer import BagWriter

    bag = tmp_path / "session"
    t0 = 1_700_000_000_123_456_789
    with BagWriter(bag, ros_distro="jazzy") as w:
        w.add_topic("/protocad/step_info", "sensor_msgs/msg/JointState")
        w.add_topic("/protocad/action", "sensor_msgs/msg/JointState")
        for i in range(5):
            w.write("/protocad/step_info", encode("sensor_msgs/msg/JointState", JointState()), t0 + i * 20_000_000)
        for i in range(3):
            w.write("/protocad/action", encode("sensor_msgs/msg/JointState", JointState()), t0 + i * 20_000_000 + 1)
    size = sum(f.stat().st_size for f in bag.glob("*.mcap"))
    size_text = f"{size / 1024:.1f} KiB" if size >= 1024 else f"{size} B"
    out = ros2("bag", "info", str(bag), env={"TZ": "UTC"})
    assert out.returncode == 0, out.stderr
    assert out.stdout == (
        "\n"
        "Files:             session_0.mcap\n"
        f"Bag size:          {size_text}\n"
        "Storage id:        mcap\n"
        "ROS Distro:        jazzy\n"
        "Duration:          0.080000000s\n"
        "Start:             Nov 14 2023 22:13:20.123456789 (1700000000.123456789)\n"
        "End:               Nov 14 2023 22:13:20.203456789 (1700000000.203456789)\n"
        "Messages:          8\n"
        "Topic information: Topic: /protocad/step_info | Type: sensor_msgs/msg/JointState | Count: 5 | "
        "Serialization Format: cdr\n"
        "                   Topic: /protocad/action | Type: sensor_msgs/msg/JointState | Count: 3 | "
        "Serialization Format: cdr\n"
        "Service:           0\n"
        "Service information: \n")
    assert ros2("bag", "info", "-t", str(bag)).stdout == "/protocad/step_info\n/protocad/action\n"

    # A file on its own (and one cut short, as a killed recorder leaves it) is read from the file.
    mcap = bag / "session_0.mcap"
    alone = ros2("bag", "info", str(mcap), env={"TZ": "UTC"})
    assert alone.returncode == 0 and "Messages:          8\n" in alone.stdout
    cut = tmp_path / "cut.mcap"
    data = mcap.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    partial = ros2("bag", "info", str(cut))
    assert partial.returncode == 0 and "truncated" in partial.stderr and "Messages:" in partial.stdout
    missing = ros2("bag", "info", str(tmp_path / "nope"))
    assert missing.returncode == 1 and "nope" in missing.stderr
    # a folder of bags (what protocad-train --logs takes): each bag, not an empty 1970 one
    import shutil
    folder = tmp_path / "bags"
    for name in ("ep1", "ep2"):
        shutil.copytree(bag, folder / name)
    many = ros2("bag", "info", str(folder), env={"TZ": "UTC"})
    assert many.returncode == 0 and many.stdout.count("Messages:          8\n") == 2, many.stdout
    assert f"{folder / 'ep1'}:" in many.stdout and f"{folder / 'ep2'}:" in many.stdout
    empty = tmp_path / "empty"
    empty.mkdir()
    nothing = ros2("bag", "info", str(empty))
    assert nothing.returncode == 1 and "is not a bag" in nothing.stderr and "1970" not in nothing.stdout


def test_bag_record_is_the_recorder_and_the_rest_needs_ros():
    out = ros2("bag", "record", "--help")
    assert out.returncode == 0 and "--regex" in out.stdout and "--exclude-regex" in out.stdout
    for argv in (["launch", "pkg", "file.launch.py"], ["topic", "pub", "/x", "std_msgs/msg/String"],
                 ["bag", "play", "x"], ["interface", "show", "std_msgs/msg/String"]):
        res = ros2(*argv)
        assert res.returncode == 2 and "not supported by this front-end" in res.stderr, argv
        assert "ros2 topic list | info | echo | hz" in res.stderr
        assert "Instead: " in res.stderr, argv            # the project's own way to do it


def test_bad_input_is_one_clear_line_and_no_traceback(tmp_path):
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9}\n")
    cases = [
        (["topic", "hz", "/x", "--window", "0"], 2, "expected a positive integer"),
        (["topic", "echo", "/x", "--truncate-length", "-1"], 2, "expected an integer >= 0"),
        (["topic", "echo", "/x", "--filter", "m.("], 1, "is not a Python expression"),
        (["service", "call", "/x", "std_srvs/srv/Trigger", "{a: [1"], 1, "the values are not YAML"),
        (["service", "call", "/x", "std_msgs/msg/String"], 1, "The passed type is not a service"),
        # a type name is checked before anything is imported (idlelib.idle would start IDLE)
        (["topic", "echo", "/x", "idlelib/idle/X"], 1, "The passed message type is invalid"),
        (["service", "call", "/x", "os/srv/X"], 1, "The passed service type is invalid"),
        (["bag", "info", str(bag)], 1, "Could not read metadata"),
    ]
    for argv, code, needle in cases:
        res = ros2(*argv)
        assert res.returncode == code and needle in res.stderr and "Traceback" not in res.stderr, (argv, res.stderr)
