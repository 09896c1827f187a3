"""A ROS 2 node answering every observation with a uniform random action (the paper's prefill,
and the random baseline of `protocad-evaluate --through-ros --random`).

    python -m trainer.nodes.random_actor --ros-args -p task:=pendulum_swingup -p seed:=0 -r __ns:=/protocad

Same contract as the policy node (msgs_docs/policy.md): subscribes to image and step_info,
pairs them by header stamp, publishes exactly one action per observation stamped like it
(an observation the bridge publishes again after a lock-step timeout gets the same action
again). Actions are U[-1, 1]^A from a generator seeded by `seed`, named after the task's
actuators. No model, no torch.
"""
from __future__ import annotations

import collections
from typing import Any

import numpy as np
from sensor_msgs.msg import Image, JointState

from sim_bridge.contract import qos, topics
from sim_bridge.contract.contexts import TASKS, task_actuators
from sim_bridge.nodekit.param_table import Param
from sim_bridge.nodekit.rosbase import ProtocadNode
from sim_bridge.nodekit.rosnode import declare_all, run_node

NODE_NAME = "random_actor"
#: Stamps remembered (half-paired observations, answers to repeat): a bounded memory.
MEMORY = 64

PARAMS: tuple[Param, ...] = (
    Param("task", "pendulum_swingup", "Task: the action size and names.", choices=tuple(TASKS)),
    Param("seed", 0, "Seed of the action generator.", read_only=True),
)


class RandomActorNode(ProtocadNode):
    """See the module docstring; parameters in PARAMS."""

    def __init__(self, *, namespace: str = topics.DEFAULT_NAMESPACE, **kw: Any):
        super().__init__(NODE_NAME, namespace=namespace, **kw)
        p = declare_all(self, PARAMS)
        self.names = task_actuators(p["task"])
        self.rng = np.random.default_rng(p["seed"])
        self.answered_count = 0
        self._pending: collections.OrderedDict[int, set[str]] = collections.OrderedDict()
        self._answered: collections.OrderedDict[int, JointState] = collections.OrderedDict()
        self.pub = self.create_publisher(JointState, topics.ACTION, qos.action_qos())
        self.create_subscription(Image, topics.IMAGE, self._on_image, qos.observation_qos())
        self.create_subscription(JointState, topics.STEP_INFO, self._on_step_info, qos.observation_qos())
        self.get_logger().info(f"random actor ready: {len(self.names)}-d uniform actions {self.names} on "
                               f"{self.resolve_topic_name(topics.ACTION)} (seed {p['seed']})")

    def _on_image(self, msg: Image) -> None:
        self._arrive(topics.stamp_to_ns(msg.header.stamp), "image")

    def _on_step_info(self, msg: JointState) -> None:
        self._arrive(topics.stamp_to_ns(msg.header.stamp), "info")

    def _arrive(self, stamp: int, kind: str) -> None:
        if stamp in self._answered:
            if kind == "info":  # published again by the bridge: the same answer again
                self.pub.publish(self._answered[stamp])
            return
        got = self._pending.setdefault(stamp, set())
        got.add(kind)
        if len(got) < 2:
            while len(self._pending) > MEMORY:
                self._pending.popitem(last=False)
            return
        del self._pending[stamp]
        msg = topics.fill_action(JointState(), self.rng.uniform(-1.0, 1.0, len(self.names)), self.names, stamp)
        self.pub.publish(msg)
        self._answered[stamp] = msg
        while len(self._answered) > MEMORY:
            self._answered.popitem(last=False)
        self.answered_count += 1

    def close(self) -> None:
        self.get_logger().info(f"stopped after answering {self.answered_count} observations")


def main(argv: list[str] | None = None) -> int:
    return run_node(
        RandomActorNode, prog="random_actor", params=PARAMS, argv=argv,
        description="Answers every observation (image + step_info, paired by stamp) with a "
                    "uniform random action in [-1, 1], named after the task's actuators. "
                    "Contract: msgs_docs/policy.md.",
        example="python -m trainer.nodes.random_actor --ros-args -p task:=walker_walk -p seed:=3 "
                "-r __ns:=/protocad")


if __name__ == "__main__":
    raise SystemExit(main())
