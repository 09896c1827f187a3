"""Feeding a policy node process: its command line and a publisher of hand-made observations
that collects the node's answers (tests of the policy node and of what drives it)."""
from __future__ import annotations

import numpy as np
from sensor_msgs.msg import Image, JointState

from helpers import wait_until
from helpers.ros import Probe
from sim_bridge.contract import qos, topics

TASK = "pendulum_swingup"
START = 120.0   # torch import + model build on a loaded 2-core machine


def policy_args(*params: str) -> list[str]:
    args = ["-m", "protocad_ros.node.policy_node", "--ros-args", "-p", f"task:={TASK}",
            "-p", "diagnostics_period_s:=0.1", "-p", "num_threads:=1"]
    for p in params:
        args += ["-p", p]
    return args


class Feeder:
    """Publishes observations to the policy and collects its answers."""

    def __init__(self, probe: Probe):
        self.probe = probe
        self.pub_image = probe.publisher(topics.IMAGE, Image, qos.observation_qos())
        self.pub_info = probe.publisher(topics.STEP_INFO, JointState, qos.observation_qos())
        self.actions = probe.record(topics.ACTION, JointState, qos.action_qos())
        self.features = probe.record(topics.CONTEXT_FEATURES, JointState, qos.action_qos())
        self.rng = np.random.default_rng(0)
        self.images: dict[int, np.ndarray] = {}

    def ready(self) -> bool:
        return (self.pub_image.get_subscription_count() >= 1
                and self.pub_info.get_subscription_count() >= 1
                and self.actions.matched() >= 1 and self.features.matched() >= 1)

    def image(self, stamp: int, img: np.ndarray | None = None) -> None:
        if img is None:
            img = self.images.get(stamp)
        if img is None:
            img = self.rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
        self.images[stamp] = img
        self.pub_image.publish(topics.fill_image(Image(), img, stamp))

    def raw_image(self, stamp: int, h: int, w: int, encoding: str, data: bytes,
                  step: int | None = None) -> None:
        m = Image()
        topics.set_stamp(m.header.stamp, stamp)
        m.height, m.width, m.encoding = h, w, encoding
        m.step = w * 3 if step is None else step
        m.data = data
        self.pub_image.publish(m)

    def info(self, stamp: int, step: int, episode: int = 0, is_first: bool = False,
             is_last: bool = False) -> None:
        info = topics.StepInfo(0.0 if is_first else 0.5, 1.0, is_first, is_last, False,
                               episode, step)
        self.pub_info.publish(topics.fill_step_info(JointState(), info, stamp))

    def obs(self, stamp: int, step: int, episode: int = 0, info_first: bool = False, **kw) -> None:
        if info_first:
            self.info(stamp, step, episode, **kw)
            self.image(stamp)
        else:
            self.image(stamp)
            self.info(stamp, step, episode, **kw)

    def stamps(self) -> list[int]:
        return [topics.stamp_to_ns(m.header.stamp) for m in list(self.actions)]

    def wait_answers(self, n: int, what: str, timeout: float = 30.0) -> None:
        wait_until(lambda: len(self.actions) >= n and len(self.features) >= n, timeout, what)
