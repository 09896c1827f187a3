"""The recorder writes a contract `bridge_info` only from its namespace's bridge (issue 54,
point 3): the participant that also writes image and step_info there, told by the writer's GID.
A stranger's bridge_info naming another task is left out of the bag, counted in its metadata
and logged once. Real processes over DDS: the recorder, and two participants in this process
(the "bridge" and the stranger, each an rclpy Context of its own)."""
from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
from helpers import interrupt, wait_until
from helpers.ros import Probe, publisher_node

from sim_bridge.contract import qos
from sim_bridge.contract import topics as T
from trainer.bag.reader import BagReader
from trainer.nodes.recorder_announcements import IGNORED_KEY

pytestmark = [pytest.mark.ros, pytest.mark.process]


def test_a_strangers_bridge_info_is_left_out_of_the_bag(tmp_path):
    from sensor_msgs.msg import Image, JointState

    bag = tmp_path / "bag"
    rec = subprocess.Popen([sys.executable, "-m", "trainer.nodes.recorder", "-o", str(bag)],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    bridge_gen = publisher_node("fake_bridge")
    bridge = next(bridge_gen)
    stranger = Probe("stranger")
    try:
        pub_img = bridge.create_publisher(Image, T.IMAGE, qos.observation_qos())
        pub_info = bridge.create_publisher(JointState, T.STEP_INFO, qos.observation_qos())
        pub_bi = bridge.create_publisher(JointState, T.BRIDGE_INFO, qos.announcement_qos())
        forged = stranger.node.create_publisher(JointState, T.BRIDGE_INFO, qos.announcement_qos())
        wait_until(lambda: min(p.get_subscription_count() for p in (pub_img, pub_info, pub_bi, forged)) >= 1
                   or rec.poll() is not None, 60, "the recorder's subscriptions")
        pub_bi.publish(T.fill_bridge_info(JointState(), T.BridgeInfo("pendulum_swingup", ["torque"], 0.04, 64)))
        forged.publish(T.fill_bridge_info(JointState(), T.BridgeInfo("walker_walk", ["a"] * 6, 0.025, 64)))
        for i in range(5):
            pub_img.publish(T.fill_image(Image(), np.zeros((64, 64, 3), np.uint8), i))
            pub_info.publish(JointState(name=["reward"], position=[0.0]))
            time.sleep(0.05)
        time.sleep(7.0)   # past the grace a stranger's message gets to show it writes observations
        out = interrupt(rec)
    finally:
        if rec.poll() is None:
            rec.kill()
        stranger.close()
        next(bridge_gen, None)
    assert rec.returncode == 0, out
    announced = [BagReader(bag).decode(m) for m in BagReader(bag).messages([T.topic_name(T.DEFAULT_NAMESPACE,
                                                                                                T.BRIDGE_INFO)])]
    assert [m.header.frame_id for m in announced] == ["pendulum_swingup"], out
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert json.loads(info["custom_data"][IGNORED_KEY]) == {"/protocad/bridge_info": 1}
    assert len([x for x in out.splitlines() if "left a message out of the bag" in x]) == 1, out
    assert "LEFT OUT (not written by the bridge" in out, out
