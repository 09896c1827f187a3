"""What a real camera sends, made from dm_control renders: walker frames at a camera's size
(480x640), and the sensor_msgs/Image and CompressedImage messages that carry them in each
encoding (the policy node's camera tests and scripts/bench_camera_latency.py)."""
from __future__ import annotations

import time

import numpy as np
from sensor_msgs.msg import CompressedImage, Image, JointState

from sim_bridge.contract import camera, qos, topics


def walker_frames(n: int, height: int = 480, width: int = 640, seed: int = 0) -> list[np.ndarray]:
    """n consecutive frames of a walker_walk episode under random actions, rendered at height x
    width by the task's own camera (what the 64x64 render shows, at a camera's resolution)."""
    from dm_control.mujoco.engine import Camera

    from sim_bridge.contract.contexts import CAMERA_IDS
    from sim_bridge.sim.envs import ContextDMCEnv

    rng = np.random.default_rng(seed)
    # "default" quality: its offscreen buffer is MuJoCo's 640x480 ("fast" sizes it to the render)
    with ContextDMCEnv("walker_walk", seed=seed, render_quality="default") as env:
        cam = Camera(env.physics, height=height, width=width, camera_id=CAMERA_IDS.get("walker", 0))
        try:
            env.reset()
            frames = []
            for _ in range(n):
                frames.append(cam.render().copy())
                env.step(rng.uniform(-1, 1, 6))
        finally:
            cam._scene.free()   # dm_control offers no public free
    return frames


def raw_msg(rgb: np.ndarray, encoding: str, stamp: int) -> Image:
    msg = Image()
    topics.set_stamp(msg.header.stamp, stamp)
    msg.height, msg.width, msg.encoding = int(rgb.shape[0]), int(rgb.shape[1]), encoding
    data, msg.step = camera.raw_payload(rgb, encoding)
    msg.data = data
    return msg


def compressed_msg(rgb: np.ndarray, kind: str, stamp: int, quality: int = 90) -> CompressedImage:
    """As image_transport's compressed plugin sends it (its format string names the kind)."""
    msg = CompressedImage()
    topics.set_stamp(msg.header.stamp, stamp)
    msg.format = f"rgb8; {kind} compressed rgb8"
    msg.data = camera.encode_compressed(rgb, kind, quality)
    return msg


class CameraFeeder:
    """A camera (and, paired, a bridge's step_info) for one policy node in namespace `ns`: frames
    go out as raw Image on `image` or, compressed, as CompressedImage on `image/compressed`; the
    node's actions are recorded with their arrival time (monotonic)."""

    def __init__(self, probe, ns: str, compressed: bool = False):
        self.probe, self.ns, self._clock = probe, ns, time.monotonic
        topic = topics.IMAGE + "/compressed" if compressed else topics.IMAGE
        self.pub_image = probe.publisher(topic, CompressedImage if compressed else Image,
                                         qos.observation_qos(), ns=ns)
        self.pub_info = probe.publisher(topics.STEP_INFO, JointState, qos.observation_qos(), ns=ns)
        self.actions: list = []
        self.arrived: dict[int, float] = {}    # stamp -> when its action arrived
        self._sub = probe.node.create_subscription(JointState, probe.topic(topics.ACTION, ns), self._on_action,
                                                   qos.action_qos())

    def _on_action(self, msg) -> None:
        t = self._clock()
        with self.probe.lock:
            self.actions.append(msg)
            self.arrived.setdefault(topics.stamp_to_ns(msg.header.stamp), t)

    def ready(self, paired: bool = True) -> bool:
        return (self.pub_image.get_subscription_count() >= 1 and self._sub.get_publisher_count() >= 1
                and (not paired or self.pub_info.get_subscription_count() >= 1))

    def send(self, msg, step: int | None = None, episode: int = 0) -> float:
        """Publish a frame (and, unless step is None, its step_info); the time it went out."""
        stamp = topics.stamp_to_ns(msg.header.stamp)
        if step is not None:
            info = topics.StepInfo(0.0, 1.0, step == 0, False, False, episode, step)
            self.pub_info.publish(topics.fill_step_info(JointState(), info, stamp))
        t = self._clock()
        self.pub_image.publish(msg)
        return t

    def effort(self, stamp: int) -> np.ndarray:
        with self.probe.lock:
            for m in self.actions:
                if topics.stamp_to_ns(m.header.stamp) == stamp:
                    return np.asarray(m.effort)
        raise KeyError(stamp)
