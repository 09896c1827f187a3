"""The sim bridge as a real camera and a real robot would be seen by the policy node (issue 53),
as real processes over DDS: the camera option (a 480x640 bgr8 Image, a JPEG CompressedImage on
image/compressed) and the adapter mode (Float64MultiArray commands in a robot's permuted joint
order and units). Each is run beside the native bridge on the same seed in lock-step, so the
camera's frames and the commands' effects are compared step by step with the contract's."""
from __future__ import annotations

import math
import re
import threading

import numpy as np
import pytest
import yaml
from helpers import wait_exit, wait_until
from helpers.ros import Probe, publish_waiting_out_a_full_history
from sensor_msgs.msg import CompressedImage, Image, JointState
from std_msgs.msg import Float64MultiArray

from sim_bridge.contract import camera, qos, topics
from sim_bridge.contract.contexts import task_actuators
from sim_bridge.contract.joint_map import load_joint_map

START = 120.0   # generous: several bridges starting at once on a loaded 2-core machine
#: Mean absolute difference (of 255) allowed between the model image of a camera frame and the
#: native square render of the same step: the renderer rasterises 480 rows, not 64, so edges
#: differ (measured: 0.9 pendulum, 2.3 walker; JPEG at quality 90 adds about 0.1).
CAMERA_MEAN_TOLERANCE = 4.0


@pytest.fixture
def probe():
    p = Probe("camera_adapter_probe")
    yield p
    p.close()


def bridge_args(task: str, ns: str, *params: str) -> list[str]:
    args = ["-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={task}", "-p", "seed:=3",
            "-p", "episode_length:=6", "-p", "max_episodes:=1", "-p", "diagnostics_period_s:=0.2"]
    for p in params:
        args += ["-p", p]
    return args + ["-r", f"__ns:={ns}"]


def policy(step: int, n: int) -> np.ndarray:
    """A fixed action sequence, beyond [-1, 1] at times (clipped alike on both paths), in
    multiples of 1/64: with the map's power-of-two scales and quarter offsets every command is
    exact in binary and the round trip is exact (with any other map it is within an ulp)."""
    return np.array([round(64 * 1.3 * math.sin(0.7 * step + i)) / 64 for i in range(n)])


class Client:
    """Answers each (image, step_info) pair of one bridge: a JointState action stamped like the
    observation, or (joint_map given) the Float64MultiArray command a forward command controller
    would take. Keeps (stamp, step_info, model image, the image message's shape) per step."""

    def __init__(self, probe: Probe, ns: str, image_type=Image, image_topic: str = topics.IMAGE,
                 n_actions: int = 1, joint_map=None, wrong_length_at: int | None = None):
        self.probe, self.n, self.map, self.wrong_at = probe, n_actions, joint_map, wrong_length_at
        self.lock = threading.Lock()
        self.pending: dict[int, dict] = {}
        self.steps: list[tuple[int, topics.StepInfo, np.ndarray, tuple]] = []
        node = probe.node
        if joint_map is None:
            self.pub = node.create_publisher(JointState, probe.topic(topics.ACTION, ns), qos.action_qos())
        else:
            self.pub = node.create_publisher(Float64MultiArray, probe.topic("commands", ns), qos.action_qos())
        self.subs = [node.create_subscription(image_type, probe.topic(image_topic, ns),
                                              lambda m: self._on(m, "image"), qos.observation_qos()),
                     node.create_subscription(JointState, probe.topic(topics.STEP_INFO, ns),
                                              lambda m: self._on(m, "info"), qos.observation_qos())]

    def _on(self, msg, kind: str) -> None:
        stamp = topics.stamp_to_ns(msg.header.stamp)
        with self.lock:
            entry = self.pending.setdefault(stamp, {})
            entry[kind] = msg
            if len(entry) < 2:
                return
            del self.pending[stamp]
        img, info = entry["image"], topics.read_step_info(entry["info"])
        shape = (img.format,) if isinstance(img, CompressedImage) else (img.height, img.width, img.encoding)
        with self.lock:
            self.steps.append((stamp, info, camera.model_image(img, 64), shape))
        action = policy(info.step, self.n)
        if self.map is None:
            msg = topics.fill_action(JointState(), action, [f"a{i}" for i in range(self.n)], stamp)
        else:
            if info.step == self.wrong_at:   # refused, counted; the right one follows
                publish_waiting_out_a_full_history(self.pub, Float64MultiArray(data=[0.0]))
            msg = Float64MultiArray(data=[float(v) for v in self.map.to_robot(action)])
        publish_waiting_out_a_full_history(self.pub, msg)


@pytest.mark.ros
@pytest.mark.process
def test_camera_option_publishes_what_a_real_camera_would(spawn, probe):
    """480x640 bgr8 Image and JPEG CompressedImage, each reaching the model's 64x64 through
    camera.model_image within CAMERA_MEAN_TOLERANCE of the native frame of the same step; the
    steps themselves (rewards, flags) are the native ones."""
    task = "pendulum_swingup"
    runs = {"/cam_native": (Image, topics.IMAGE, ()),
            "/cam_bgr": (Image, topics.IMAGE, ("camera_height:=480", "camera_width:=640",
                                               "camera_encoding:=bgr8")),
            "/cam_jpeg": (CompressedImage, "image/compressed",
                          ("camera_height:=480", "camera_width:=640", "camera_transport:=compressed",
                           "camera_format:=jpeg", "jpeg_quality:=90"))}
    clients, procs = {}, {}
    for ns, (msg_type, topic, params) in runs.items():
        clients[ns] = Client(probe, ns, msg_type, topic)
        procs[ns] = spawn(ns.strip("/"), *bridge_args(task, ns, *params))
    for ns, proc in procs.items():
        assert wait_exit(proc, START) == 0, proc.output()
        assert "Traceback" not in proc.output()
    assert "camera 480x640 jpeg quality 90 on image/compressed" in procs["/cam_jpeg"].output()
    native = sorted(clients["/cam_native"].steps, key=lambda s: s[0])
    assert len(native) == 7 and all(s[3] == (64, 64, "rgb8") for s in native)
    for ns, shape in (("/cam_bgr", (480, 640, "bgr8")), ("/cam_jpeg", ("jpeg",))):
        steps = sorted(clients[ns].steps, key=lambda s: s[0])
        assert [(s[0], s[1]) for s in steps] == [(s[0], s[1]) for s in native], ns
        assert all(s[3] == shape for s in steps), ns
        for (_, _, got, _), (_, _, want, _) in zip(steps, native):
            diff = np.abs(got.astype(int) - want.astype(int))
            assert diff.mean() <= CAMERA_MEAN_TOLERANCE, (ns, diff.mean())


def write_map(path, names: list[str]) -> str:
    """A robot whose controller lists the joints in reverse order, in its own units."""
    scales = (0.5, -2.0, 4.0, 1.0, -0.25, 8.0)
    joints = [{"name": f"joint_{a}", "action": a, "scale": scales[i % 6], "offset": 0.25 * i}
              for i, a in enumerate(names)][::-1]
    path.write_text(yaml.safe_dump({"joints": joints}))
    return str(path)


@pytest.mark.ros
@pytest.mark.process
def test_adapter_mode_drives_the_bridge_like_the_contracts_actions(spawn, probe, tmp_path):
    """The same actions as JointState and as permuted, scaled Float64MultiArray commands give the
    same episode (rewards, flags, frames); a wrong-length command is refused and counted, and
    the bridge goes on with the next one."""
    task = "walker_walk"
    names = task_actuators(task)
    path = write_map(tmp_path / "robot.yaml", names)
    joint_map = load_joint_map(path, names)
    assert list(joint_map.joint_names) != [f"joint_{a}" for a in names]   # permuted indeed
    native = Client(probe, "/adp_native", n_actions=len(names))
    adapted = Client(probe, "/adp_cmd", n_actions=len(names), joint_map=joint_map, wrong_length_at=2)
    p_native = spawn("adp_native", *bridge_args(task, "/adp_native"))
    p_cmd = spawn("adp_cmd", *bridge_args(task, "/adp_cmd", "action_input:=float64_multi_array",
                                          f"command_map:={path}"))
    for proc in (p_native, p_cmd):
        assert wait_exit(proc, START) == 0, proc.output()
        assert "Traceback" not in proc.output()
    a = sorted(native.steps, key=lambda s: s[0])
    b = sorted(adapted.steps, key=lambda s: s[0])
    assert len(a) == 7
    assert [(s[0], s[1]) for s in a] == [(s[0], s[1]) for s in b]
    assert all(np.array_equal(x[2], y[2]) for x, y in zip(a, b))
    # The exit line lists the counters: one refused command; clipping counted alike.
    out_native, out_cmd = p_native.output(), p_cmd.output()
    assert "rejected_wrong_length=1" in out_cmd and "rejected_wrong_length" not in out_native
    clipped = [re.findall(r"actions_clipped=(\d+)", out) for out in (out_native, out_cmd)]
    assert clipped[0] == clipped[1] and len(clipped[0]) == 1 and clipped[0][0] != "0", clipped


@pytest.mark.ros
@pytest.mark.process
def test_a_command_map_that_does_not_fit_is_a_configuration_error(spawn, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"joints": [{"name": "shoulder", "action": "no_such_actuator"}]}))
    proc = spawn("bad_map", *bridge_args("pendulum_swingup", "/adp_bad", "action_input:=float64_multi_array",
                                         f"command_map:={bad}"))
    assert wait_exit(proc, START) == 2, proc.output()
    out = proc.output()
    assert "configuration error" in out and "command_map" in out and "no_such_actuator" in out, out
    assert "Traceback" not in out


@pytest.mark.ros
@pytest.mark.process
def test_a_command_while_no_observation_awaits_an_answer_is_counted_and_dropped(spawn, probe):
    """Lock-step, adapter mode: a command has no stamp, so one arriving before any observation
    (the bridge active, waiting for a second reader) answers nothing: counted, dropped."""
    ns = "/adp_early"
    pub = probe.publisher("commands", Float64MultiArray, ns=ns)
    proc = spawn("adp_early", *bridge_args("pendulum_swingup", ns, "action_input:=float64_multi_array",
                                           "min_subscribers:=2"))
    wait_until(lambda: probe.node_diag(f"{ns}/sim_bridge").get("lifecycle_state") == "active"
               and pub.get_subscription_count() == 1, START, "the bridge active, the command matched")
    pub.publish(Float64MultiArray(data=[0.5]))
    wait_until(lambda: probe.counter(f"{ns}/sim_bridge", "commands_unsolicited") == 1, 30,
               "commands_unsolicited == 1")
    diag = probe.node_diag(f"{ns}/sim_bridge")
    assert (diag["actions_received"], diag["actions_accepted"], diag["steps"]) == ("1", "0", "0"), diag
    assert proc.alive()


@pytest.mark.ros
@pytest.mark.process
def test_adapter_mode_in_real_time_takes_the_latest_command(spawn, probe, tmp_path):
    """Real time: each command (no stamp) is taken as the one to hold, none refused as stale."""
    names = task_actuators("walker_walk")
    path = write_map(tmp_path / "robot.yaml", names)
    client = Client(probe, "/adp_rt", n_actions=len(names), joint_map=load_joint_map(path, names))
    proc = spawn("adp_rt", *bridge_args("walker_walk", "/adp_rt", "mode:=realtime", "control_rate_hz:=40.0",
                                        "episode_length:=20", "action_input:=float64_multi_array",
                                        f"command_map:={path}"))
    assert wait_exit(proc, START) == 0, proc.output()
    out = proc.output()
    accepted = re.findall(r"actions_accepted=(\d+)", out)
    assert accepted and int(accepted[0]) >= 1 and len(client.steps) == 21, out
    assert "rejected" not in out.split("stopped:")[-1] and "commands_unsolicited" not in out, out
