"""A ROS 2 node answering every observation with a uniform random action (the paper's prefill,
and the random baseline of `protocad-evaluate --through-ros --random`).

    python -m trainer.random_actor --task pendulum_swingup --seed 0 --ros-args -r __ns:=/protocad

Same contract as the policy node (msgs_docs/policy.md): subscribes to image and step_info,
pairs them by header stamp, publishes exactly one action per observation stamped like it
(an observation the bridge publishes again after a lock-step timeout gets the same action
again). Actions are U[-1, 1]^A from a generator seeded by --seed. No model, no torch.
"""
from __future__ import annotations

import argparse
import collections
import signal
import sys
import threading
from typing import Sequence

import numpy as np


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m trainer.random_actor",
                                 description="Answer every observation with a uniform random action.")
    ap.add_argument("--task", default="pendulum_swingup", help="task (for the action size and names)")
    ap.add_argument("--seed", type=int, default=0)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else [sys.argv[0], *argv])
    from rclpy.utilities import remove_ros_args

    a = build_parser().parse_args(remove_ros_args(argv)[1:])
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Image, JointState

    from sim_bridge.contexts import task_actuators
    from sim_bridge import qos, topics

    names = task_actuators(a.task)
    rng = np.random.default_rng(a.seed)
    stop = threading.Event()
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    node = Node("random_actor")
    pub = node.create_publisher(JointState, topics.ACTION, qos.action_qos())
    pending: collections.OrderedDict[int, set] = collections.OrderedDict()
    answered: collections.OrderedDict[int, JointState] = collections.OrderedDict()
    count = [0]

    def arrive(stamp: int, kind: str) -> None:
        if stamp in answered:
            if kind == "info":  # published again by the bridge: same answer again
                pub.publish(answered[stamp])
            return
        got = pending.setdefault(stamp, set())
        got.add(kind)
        if len(got) < 2:
            while len(pending) > 64:
                pending.popitem(last=False)
            return
        del pending[stamp]
        msg = topics.fill_action(JointState(), rng.uniform(-1.0, 1.0, len(names)), names, stamp)
        pub.publish(msg)
        answered[stamp] = msg
        while len(answered) > 64:
            answered.popitem(last=False)
        count[0] += 1

    node.create_subscription(Image, topics.IMAGE,
                             lambda m: arrive(topics.stamp_to_ns(m.header.stamp), "image"), qos.observation_qos())
    node.create_subscription(JointState, topics.STEP_INFO,
                             lambda m: arrive(topics.stamp_to_ns(m.header.stamp), "info"), qos.observation_qos())
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    node.get_logger().info(f"random actor ready: {len(names)}-d uniform actions {names} on "
                           f"{node.resolve_topic_name(topics.ACTION)} (seed {a.seed})")
    try:
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.1)
    finally:
        node.get_logger().info(f"stopped after answering {count[0]} observations")
        ex.remove_node(node)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
