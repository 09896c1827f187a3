"""The policy node's camera (protocad_ros/robot/camera_input.py): a real camera's frames, in any
taken encoding, raw or compressed, reach the model as the image the native 64x64 path gives;
with observations:=image_only a camera alone drives the policy. Pixels are checked in-process
through the node's own CameraInput on a real rclpy node; the node's behaviour with real
processes over DDS and the shipped walker policy."""
from __future__ import annotations

import time

import numpy as np
import pytest
from helpers import wait_exit, wait_until
from helpers.camera_frames import CameraFeeder, compressed_msg, raw_msg, walker_frames
from helpers.policy import START, policy_args
from helpers.ros import Probe, publisher_node
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from PIL import Image as PILImage
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image, JointState

from protocad_ros.robot.camera_input import CameraInput
from sim_bridge.contract import camera, qos, topics
from sim_bridge.contract.contexts import task_actuators
from sim_bridge.nodekit.param_table import ConfigError

#: JPEG at quality 90 of a 480x640 walker render, center-cropped and area-resized to 64x64,
#: against the same of the raw frame, in levels of 255: measured mean 0.45, p99 2, max 8 over 16
#: frames here (the pixel tolerance: mean below 1, 99th percentile below 5).
JPEG_MEAN_TOL, JPEG_P99_TOL = 1.0, 5
#: The shipped walker's actions for JPEG frames against the native ones (see where it is used).
JPEG_ACTION_TOL = 0.05


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    return walker_frames(3)


@pytest.fixture
def ros_node():
    yield from publisher_node("camera_input_test")


class Taken:
    """What a CameraInput hands on, and what it counts."""

    def __init__(self):
        self.images: list[tuple[int, np.ndarray]] = []
        self.observations: list[tuple[int, dict]] = []
        self.counts: dict[str, int] = {}

    def count(self, key: str, why: str | None = None) -> None:
        self.counts[key] = self.counts.get(key, 0) + 1


def _camera(node, taken: Taken, **params) -> CameraInput:
    p = {"image_transport": "raw", "image_crop": "center", "observations": "paired", **params}
    return CameraInput(node, p, qos_profile=qos.observation_qos(), event_callbacks=lambda topic: None,
                       active=lambda: True, size=lambda: 64, count=taken.count,
                       image=lambda s, img, t: taken.images.append((s, img)),
                       observation=lambda s, entry, t: taken.observations.append((s, entry)))


def test_every_encoding_and_png_reach_the_model_as_the_native_image_jpeg_within_tolerance(ros_node, frames):
    taken = Taken()
    cam = _camera(ros_node, taken)
    for i, frame in enumerate(frames):
        native = camera.resize(frame, 64)
        for enc in ("rgb8", "bgr8", "rgba8", "bgra8"):
            cam._on_frame(raw_msg(frame, enc, i))
            assert np.array_equal(taken.images[-1][1], native), enc
        cam._on_frame(compressed_msg(frame, "png", i))
        assert np.array_equal(taken.images[-1][1], native), "png"
        # mono8 has one channel: the model sees the frame's luma in all three, resized alike.
        luma = np.asarray(PILImage.fromarray(frame).convert("L"))
        cam._on_frame(raw_msg(frame, "mono8", i))
        assert np.array_equal(taken.images[-1][1], camera.resize(np.repeat(luma[:, :, None], 3, axis=2), 64))
        cam._on_frame(compressed_msg(frame, "jpeg", i, quality=90))
        err = np.abs(taken.images[-1][1].astype(int) - native.astype(int))
        assert err.mean() < JPEG_MEAN_TOL and np.percentile(err, 99) < JPEG_P99_TOL, (err.mean(), err.max())
    assert all(img.shape == (64, 64, 3) and img.dtype == np.uint8 for _, img in taken.images)
    assert taken.counts == {"images_received": len(taken.images)}


def test_the_native_64x64_rgb8_frame_passes_bit_exact_and_bad_frames_are_counted(ros_node, frames):
    taken = Taken()
    cam = _camera(ros_node, taken)
    small = camera.resize(frames[0], 64)
    cam._on_frame(topics.fill_image(Image(), small, 7))      # what the sim bridge sends
    assert taken.images[-1][0] == 7 and np.array_equal(taken.images[-1][1], small)
    bad = raw_msg(frames[0], "rgb8", 8)
    bad.encoding = "yuv422"
    cam._on_frame(bad)
    assert len(taken.images) == 1
    assert taken.counts == {"images_received": 2, "images_rejected": 1, "rejected_image_encoding": 1}


def test_a_bad_crop_is_a_configuration_error(ros_node):
    with pytest.raises(ConfigError, match="image_crop: crop 'middle': expected center, full or x,y,w,h"):
        _camera(ros_node, Taken(), image_crop="middle")


def test_image_only_numbers_episodes_and_steps_and_refuses_frames_that_are_not_newer(ros_node, frames):
    taken = Taken()
    cam = _camera(ros_node, taken, observations="image_only")
    for stamp in (10, 20, 20, 15, 30):
        cam._on_frame(raw_msg(frames[0], "bgr8", stamp))
    cam.restart_episode()
    cam._on_frame(raw_msg(frames[0], "bgr8", 40))
    cam.activated()
    cam._on_frame(raw_msg(frames[0], "bgr8", 50))
    got = [(s, e["info"].is_first, e["info"].episode, e["info"].step, e["info"].reward) for s, e in taken.observations]
    assert got == [(10, True, 0, 0, 0.0), (20, False, 0, 1, 0.0), (30, False, 0, 2, 0.0),
                   (40, True, 1, 0, 0.0), (50, True, 2, 0, 0.0)]
    assert taken.counts["stale_observations"] == 2 and taken.counts["episode_restarts"] == 1
    assert not taken.images        # nothing waits for a step_info


def _set_state(probe: Probe, fqn: str, label: str) -> None:
    """A lifecycle transition, asked again when Fast DDS lost the answer right after discovery."""
    client = probe.node.create_client(ChangeState, f"{fqn}/change_state")
    assert client.wait_for_service(timeout_sec=START)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        future = client.call_async(ChangeState.Request(transition=Transition(label=label)))
        end = time.monotonic() + 10
        while not future.done() and time.monotonic() < end:
            time.sleep(0.05)
        if future.done():
            return
        client.remove_pending_request(future)
    raise AssertionError(f"no answer to {label} from {fqn}")


def _walker(spawn, name: str, ns: str, *params: str):
    from protocad_ros.policy import shipped_policy

    path = shipped_policy("walker_walk")
    args = policy_args(f"checkpoint:={path}", "mode:=deterministic", *params) + ["-r", f"__ns:={ns}"]
    args[args.index("task:=pendulum_swingup")] = "task:=walker_walk"
    return spawn(name, *args)


@pytest.mark.ros
@pytest.mark.process
def test_the_shipped_walker_answers_a_cameras_frames_as_the_native_ones(spawn):
    """Four nodes, same checkpoint and seed: 64x64 rgb8 with step_info (the sim bridge's path),
    480x640 bgr8 with step_info, 480x640 JPEG over compressed transport with step_info, and
    480x640 bgr8 alone (image_only). The raw ones answer with identical actions; JPEG with
    actions close to them (below); an unknown encoding is counted and the next good frame
    answered; image_only starts an episode at its first frame and again after re-activation."""
    from protocad_ros.policy import shipped_policy

    if shipped_policy("walker_walk") is None:
        pytest.skip("the package ships no walker_walk policy")
    probe = Probe("camera_test_probe")
    try:
        _run_walkers(spawn, probe)
    finally:
        probe.close()


def _run_walkers(spawn, probe: Probe) -> None:
    nodes = {"native": ("/cam_native",), "big": ("/cam_big",),
             "jpeg": ("/cam_jpeg", "image_transport:=compressed"), "alone": ("/cam_alone", "observations:=image_only")}
    procs = {k: _walker(spawn, k, ns, *params) for k, (ns, *params) in nodes.items()}
    feeders = {k: CameraFeeder(probe, ns, compressed=k == "jpeg") for k, (ns, *_) in nodes.items()}
    for k, f in feeders.items():
        wait_until(lambda f=f, k=k: f.ready(paired=k != "alone"), START, f"the {k} policy to match")
    # As a sim bridge announces itself: believed only from the writer of the image (on the topic
    # the camera reads: image/compressed for the JPEG node) and step_info, else never answered.
    walker = topics.BridgeInfo("walker_walk", task_actuators("walker_walk"), 0.025, 64)
    for k, (ns, *_) in nodes.items():
        if k != "alone":
            pub = probe.publisher(topics.BRIDGE_INFO, JointState, qos.announcement_qos(), ns=ns)
            pub.publish(topics.fill_bridge_info(JointState(), walker))
    frames = walker_frames(8, seed=1)
    stamps = [1_000_000_000 + 20_000_000 * i for i in range(len(frames))]
    for i, (frame, stamp) in enumerate(zip(frames, stamps)):
        feeders["native"].send(topics.fill_image(Image(), camera.resize(frame, 64), stamp), step=i)
        if i == 3:   # a camera in an encoding not taken: counted, the same stamp's good frame answered
            bad = raw_msg(frame, "bgr8", stamp)
            bad.encoding, bad.step = "yuv422", frame.shape[1] * 2
            bad.data = bytes(frame.shape[0] * bad.step)
            feeders["big"].send(bad)
        feeders["big"].send(raw_msg(frame, "bgr8", stamp), step=i)
        feeders["jpeg"].send(compressed_msg(frame, "jpeg", stamp, quality=90), step=i)
        feeders["alone"].send(raw_msg(frame, "bgr8", stamp))
        for k, f in feeders.items():
            wait_until(lambda f=f: stamp in f.arrived, 60, f"the {k} policy's answer to frame {i}")
    acts = {k: np.stack([f.effort(s) for s in stamps]) for k, f in feeders.items()}
    assert np.array_equal(acts["big"], acts["native"])
    assert np.array_equal(acts["alone"], acts["native"])      # is_first at its first frame, then steps
    # JPEG: the model sees a few levels of difference (JPEG_P99_TOL). The first answer has no
    # history behind it: on these frames it is the native one exactly, for the walker shipped on
    # 2026-12-07 and the one before it, where the mistakes this must catch move it far more
    # (channels swapped: 2.0 and 1.78, the full frame squashed instead of the center crop: 0.99
    # and 0.96). Later answers carry the recurrent state, which a few levels of difference can
    # send down another path (in process, 8 frames of seeds 1-4: later gaps up to 0.94 for the
    # shipped walker, 2.0 for the one before it), so only the first is held to JPEG_ACTION_TOL.
    gap = np.abs(acts["jpeg"] - acts["native"])
    assert gap[0].max() < JPEG_ACTION_TOL, gap

    for k in ("native", "big", "jpeg"):
        wait_until(lambda k=k: probe.node_diag(f"cam_{k}/policy").get("bridge", "").startswith("walker_walk"),
                   20, f"the {k} policy to name its bridge")
        assert probe.counter(f"cam_{k}/policy", "bridge_info_ignored") == 0
    wait_until(lambda: probe.counter("cam_big/policy", "rejected_image_encoding") == 1, 20, "the yuv422 count")
    assert probe.counter("cam_big/policy", "images_rejected") == 1
    assert "image encoding 'yuv422' is not taken" in procs["big"].output()
    wait_until(lambda: probe.node_diag("cam_alone/policy").get("step") == str(len(frames) - 1), 20,
               "the image_only node's diagnostics after the last frame")
    d = probe.node_diag("cam_alone/policy")
    assert (d["episodes"], d["episode"]) == ("1", "0"), d
    assert d["step_info_received"] == "0"

    # image_only after deactivate/activate: the next frame starts an episode; an older one is stale.
    fqn = "/cam_alone/policy"
    _set_state(probe, fqn, "deactivate")
    _set_state(probe, fqn, "activate")
    late = stamps[-1] + 1_000_000_000
    feeders["alone"].send(raw_msg(frames[0], "bgr8", late))
    wait_until(lambda: late in feeders["alone"].arrived, 60, "the answer after re-activation")
    wait_until(lambda: probe.node_diag("cam_alone/policy").get("episodes") == "2", 20, "a second episode")
    assert probe.node_diag("cam_alone/policy")["step"] == "0"
    feeders["alone"].send(raw_msg(frames[0], "bgr8", late - 1))
    wait_until(lambda: probe.counter("cam_alone/policy", "stale_observations") == 1, 20, "the stale frame")
    for k, proc in procs.items():
        assert proc.alive(), k
        assert "Traceback" not in proc.output(), k


@pytest.mark.ros
@pytest.mark.process
def test_a_bad_image_crop_stops_the_node_with_one_line(spawn):
    bad = spawn("bad_crop", *policy_args("image_crop:=middle"))
    assert wait_exit(bad, START) == 2
    out = bad.output()
    assert "image_crop: crop 'middle': expected center, full or x,y,w,h" in out and "Traceback" not in out


@pytest.mark.ros
@pytest.mark.process
def test_a_best_effort_camera_is_answered_with_the_qos_override_the_docs_name(spawn, frames):
    """A real camera driver publishes best effort (sensor data QoS), which the node's reliable
    reader never matches; msgs_docs/policy.md names the override that makes it match. (160x120
    frames: a best-effort 480x640 raw frame mostly does not arrive whole over Fast DDS's default
    transports here, measured by scripts/bench_camera_latency.py --best-effort, not tested.)"""
    probe = Probe("camera_qos_probe")
    try:
        ns = topics.DEFAULT_NAMESPACE
        policy = spawn("policy", *policy_args("observations:=image_only",
                                              f"qos_overrides.{ns}/image.subscription.reliability:=best_effort"))
        feeder = CameraFeeder(probe, ns)
        feeder.pub_image = probe.publisher(topics.IMAGE, Image, qos_profile_sensor_data)
        wait_until(lambda: feeder.ready(paired=False), START, "the policy to match a best-effort camera")
        for i, stamp in enumerate((1_000, 2_000)):
            small = np.asarray(PILImage.fromarray(frames[i]).resize((160, 120)))
            feeder.send(raw_msg(small, "bgr8", stamp))
            wait_until(lambda s=stamp: s in feeder.arrived, 30, f"the answer to frame {i}")
        assert policy.alive() and "unknown parameter" not in policy.output()
    finally:
        probe.close()
