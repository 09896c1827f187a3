"""A contract topic claimed with another type is a clear error in the nodes too (issue 54,
point 4; sim_bridge/nodekit/type_watch.py): a stranger (this test process, over DDS) advertises
a topic the node joins as std_msgs/String before the node starts; the sim bridge and the policy
node each log one ERROR line naming the topic and both types, report it on /diagnostics (ERROR
while it lasts), stay alive, and clear the report once the stranger is gone."""
from __future__ import annotations

import pytest
from helpers import wait_until
from helpers.policy import policy_args
from helpers.ros import Probe
from std_msgs.msg import String

from sim_bridge.contract.topics import contract_topic_type as contract_type

START = 120.0   # two nodes starting side by side on a loaded 2-core machine
CONTRACT = "sensor_msgs/msg/JointState"


@pytest.fixture
def probe():
    p = Probe("stranger")
    yield p
    p.close()


def test_contract_types_of_the_topics_a_node_joins():
    assert contract_type("/robot1/action", "/robot1") == CONTRACT
    assert contract_type("/protocad/image", "/protocad") == "sensor_msgs/msg/Image"
    assert contract_type("/robot1/clock", "/robot1") == contract_type("/clock", "/protocad") == "rosgraph_msgs/msg/Clock"
    assert contract_type("/diagnostics", "/robot1") == "diagnostic_msgs/msg/DiagnosticArray"
    assert contract_type("/protocad/checkpoint", "/protocad") is None       # not in the contract's TYPES
    assert contract_type("/other/action", "/robot1") is None                # another namespace's
    assert contract_type("/parameter_events", "/robot1") is None
    # a recorder of a fleet sees the robots' namespaces below its own
    assert contract_type("/protocad/robot0/action", "/protocad") is None
    assert contract_type("/protocad/robot0/action", "/protocad", nested=True) == CONTRACT
    assert contract_type("/protocad/robot0/clock", "/protocad", nested=True) == "rosgraph_msgs/msg/Clock"


@pytest.mark.ros
@pytest.mark.process
def test_a_topic_claimed_with_another_type_is_one_error_line_and_an_error_status_and_the_node_lives(spawn, probe):
    squats = {"/tw_bridge/action": "sim_bridge", "/tw_policy/image": "policy"}
    pubs = [probe.node.create_publisher(String, topic, 10) for topic in squats]
    bridge = spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", "task:=pendulum_swingup",
                   "-p", "diagnostics_period_s:=0.2", "-r", "__ns:=/tw_bridge")
    policy = spawn("policy", *policy_args("diagnostics_period_s:=0.2"), "-r", "__ns:=/tw_policy")
    procs = {"sim_bridge": bridge, "policy": policy}

    def reported(topic: str, node: str) -> bool:
        return topic in probe.node_diag(f"{topic.rsplit('/', 1)[0]}/{node}").get("type_mismatches", "")

    for topic, node in squats.items():
        wait_until(lambda: reported(topic, node) or not procs[node].alive(), START, f"{node} to report {topic}")
        d = probe.node_diag(f"{topic.rsplit('/', 1)[0]}/{node}")
        assert d["type_mismatches"] == f"{topic} (std_msgs/msg/String)", d
        assert d["_level"] == 2 and int(d["type_mismatches_detected"]) == 1, d   # ERROR
        assert "another type" in d["_message"], d
        errors = [ln for ln in procs[node].output().splitlines() if "[ERROR]" in ln]
        assert len(errors) == 1, errors
        expected = "sensor_msgs/msg/Image" if node == "policy" else CONTRACT
        assert f"{topic} is offered as " in errors[0] and "std_msgs/msg/String" in errors[0], errors
        assert f"its contract type is {expected}" in errors[0], errors
    for pub in pubs:
        probe.node.destroy_publisher(pub)
    for topic, node in squats.items():
        wait_until(lambda: probe.node_diag(f"{topic.rsplit('/', 1)[0]}/{node}").get("type_mismatches") == "",
                   30, f"{node}'s report to clear once the stranger is gone")
        assert procs[node].alive(), procs[node].output()[-3000:]
        assert sum("[ERROR]" in ln for ln in procs[node].output().splitlines()) == 1   # said once
