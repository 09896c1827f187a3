"""Test-side rclpy node for the node tests (the ROS node tests, tests/e2e/test_ros_e2e.py).

The probe lives in the pytest process, i.e. in a different process from the nodes under test,
so everything it sends and receives crosses DDS (localhost only, the run's own domain; see
conftest.py). It has its own rclpy Context, spun by a background thread.
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Any, Callable

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import ExternalShutdownException, ShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from sensor_msgs.msg import Image, JointState

from sim_bridge.contract import qos, topics

NS = topics.DEFAULT_NAMESPACE


def publisher_node(name: str, namespace: str = NS):
    """A plain rclpy node in a Context of its own, for a test to publish from (a generator:
    yield it from a fixture; the node and its context are shut down after the test)."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node(name, namespace=namespace, context=ctx)
    yield node
    node.destroy_node()
    rclpy.try_shutdown(context=ctx)


class Probe:
    def __init__(self, name: str = "probe", namespace: str = NS):
        self.ns = namespace
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = Node(name, namespace=namespace, context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.lock = threading.Lock()
        self.diag: dict[str, dict[str, str]] = {}
        self._keep = []
        self._closing = False
        #: What callbacks raised (the spin goes on): a test that waits in vain can print them.
        self.callback_errors: list[str] = []
        self.sub_diag = self.node.create_subscription(
            DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, qos.diagnostics_qos())
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        """Spin until close(). A callback that raises is recorded and the spin goes on: the
        executor's own spin() would end there and leave the probe deaf for the rest of the test."""
        while not self._closing and self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except (ShutdownException, ExternalShutdownException):
                return
            except Exception as exc:  # noqa: BLE001 - a callback's error: recorded, the spin goes on
                if self._closing or not self.ctx.ok():
                    return
                self.callback_errors.append(f"{type(exc).__name__}: {exc}")

    def _on_diag(self, msg) -> None:
        with self.lock:
            for st in msg.status:
                # The status's own level and message ride along under reserved keys.
                self.diag[st.name] = {"_level": int.from_bytes(st.level, "little") if isinstance(
                    st.level, bytes) else int(st.level), "_message": st.message,
                    **{kv.key: kv.value for kv in st.values}}

    # -------------------------------------------------------------- helpers
    def topic(self, rel: str, ns: str | None = None) -> str:
        return topics.topic_name(self.ns if ns is None else ns, rel)

    def record(self, rel: str, msgtype, qos_profile=None, ns: str | None = None) -> list:
        """Subscribe and append every message to the returned list."""
        box: list = []

        def cb(msg):
            with self.lock:
                box.append(msg)

        sub = self.node.create_subscription(msgtype, self.topic(rel, ns), cb,
                                            qos_profile or qos.observation_qos())
        self._keep.append(sub)
        return _Recorded(box, sub)

    def publisher(self, rel: str, msgtype, qos_profile=None, ns: str | None = None):
        pub = self.node.create_publisher(msgtype, self.topic(rel, ns),
                                         qos_profile or qos.action_qos())
        self._keep.append(pub)
        return pub

    def node_diag(self, node: str) -> dict[str, str]:
        """Latest diagnostics KeyValues of a node, by name ('sim_bridge' or '/ns/sim_bridge')."""
        with self.lock:
            for name, values in self.diag.items():
                if name == node or name.rstrip("/").endswith("/" + node.lstrip("/")):
                    return dict(values)
        return {}

    def counter(self, node: str, key: str) -> float:
        v = self.node_diag(node).get(key)
        return float(v) if v is not None else float("nan")

    def close(self) -> None:
        self._closing = True
        try:
            self.executor.shutdown(timeout_sec=1.0)
        except Exception:  # noqa: BLE001 - closing: best effort
            pass
        try:
            self.node.destroy_node()
        except Exception:  # noqa: BLE001 - closing: best effort
            pass
        rclpy.try_shutdown(context=self.ctx)
        self._thread.join(5.0)


class _Recorded(collections.UserList):
    def __init__(self, box: list, sub):
        super().__init__()
        self.data = box
        self.sub = sub

    def matched(self) -> int:
        return self.sub.get_publisher_count()


#: What rclpy raises when the middleware refuses a sample (a full KEEP_ALL history).
RCLError = _rclpy.RCLError


def publish_waiting_out_a_full_history(pub, msg, timeout_s: float = 120.0) -> None:
    """Publish on a KEEP_ALL writer (the action QoS), waiting while its history is full: Fast DDS
    refuses a sample once 5000 are held that a reliable reader (a recorder frozen that many
    steps) has not acknowledged; the acknowledgements come on DDS's own threads, as the bridge's
    lossless writers also wait (sim_bridge/bridge/observation_publishing.py)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return pub.publish(msg)
        except RCLError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


class Responder:
    """Answers every (image, step_info) pair with `policy(info: StepInfo) -> action` stamped
    like the observation (a trivial stand-in for the policy node)."""

    def __init__(self, probe: Probe, policy: Callable[[topics.StepInfo], Any] | None = None,
                 names: list[str] | None = None, ns: str | None = None):
        self.probe, self.policy, self.names = probe, policy, names
        self.enabled = policy is not None
        self.pending: dict[int, dict[str, Any]] = {}
        self.answered: list[int] = []
        self.received: list[tuple[str, int]] = []
        self.steps: list[tuple[int, topics.StepInfo, bytes]] = []   # (stamp, info, image bytes)
        self.pub = probe.publisher(topics.ACTION, JointState, ns=ns)
        node = probe.node
        self._subs = [
            node.create_subscription(Image, probe.topic(topics.IMAGE, ns),
                                     lambda m: self._on(m, "image"), qos.observation_qos()),
            node.create_subscription(JointState, probe.topic(topics.STEP_INFO, ns),
                                     lambda m: self._on(m, "info"), qos.observation_qos()),
        ]

    def ready(self) -> bool:
        return all(s.get_publisher_count() > 0 for s in self._subs)

    def _on(self, msg, kind: str) -> None:
        stamp = topics.stamp_to_ns(msg.header.stamp)
        with self.probe.lock:
            self.received.append((kind, stamp))
        entry = self.pending.setdefault(stamp, {})
        entry[kind] = msg
        if len(entry) < 2:
            return
        del self.pending[stamp]
        info = topics.read_step_info(entry["info"])
        with self.probe.lock:
            self.steps.append((stamp, info, bytes(entry["image"].data)))
        if not self.enabled:
            return
        action = np.asarray(self.policy(info), np.float64).reshape(-1)
        names = self.names or [f"a{i}" for i in range(action.size)]
        self.send(action, stamp, names)

    def send(self, action, stamp: int, names: list[str] | None = None) -> None:
        """Publish an action (any values, any names) stamped `stamp`."""
        msg = JointState()
        topics.set_stamp(msg.header.stamp, stamp)
        msg.name = list(names if names is not None else
                        self.names or [f"a{i}" for i in range(len(action))])
        msg.effort = [float(v) for v in action]
        publish_waiting_out_a_full_history(self.pub, msg)
        with self.probe.lock:
            self.answered.append(stamp)

