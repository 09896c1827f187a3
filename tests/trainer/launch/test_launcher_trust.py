"""The launchers trust by default (issue 39): protocad-fleet signs what it publishes and its
policy nodes serve only that, and the launchers believe only the /diagnostics of the nodes they
started. The stranger is this test process, on the same domain (this machine only)."""
from __future__ import annotations

import os
import signal
import stat
import threading
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from helpers import wait_until
from helpers.checkpoints import FakeCheckpointPublisher, chunks, sign
from helpers.ros import Probe

from protocad_ros.checkpoint.signing import generate_keypair, load_private_key
from sim_bridge.contract import qos, topics

pytestmark = [pytest.mark.ros, pytest.mark.process]


class Forger:
    """A stranger's /diagnostics writer: publishes `status` under a node's name, every 0.1 s
    while running."""

    def __init__(self, probe: Probe, name: str, level: int, message: str, values: dict[str, str]):
        self.pub = probe.node.create_publisher(DiagnosticArray, "/diagnostics", qos.diagnostics_qos())
        st = DiagnosticStatus(name=name, message=message, hardware_id="forged")
        st.level = bytes([level])
        st.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        self.msg = DiagnosticArray(status=[st])
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            self.pub.publish(self.msg)
            self.sent += 1

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(5)


@pytest.fixture
def probe():
    p = Probe("stranger")
    yield p
    p.close()


def test_a_forged_error_status_does_not_stop_a_stack(spawn, probe, tmp_path):
    (tmp_path / "stack.yaml").write_text("bridge: {task: pendulum_swingup, episode_length: 30}\n"
                                         "policy: {num_threads: 1}\nrecorder: false\n")
    stack = spawn("stack", "-m", "trainer.launch.stack", str(tmp_path / "stack.yaml"),
                  "--log-dir", str(tmp_path / "logs"))
    wait_until(lambda: "[stack] running" in stack.output() or not stack.alive(), 240, "the stack to run")
    with Forger(probe, "/protocad/policy", 2, "not answering: forged by a stranger", {}) as forger:
        wait_until(lambda: forger.sent >= 30, 30, "30 forged statuses sent")
        wait_until(lambda: "episode 1 " in stack.output() or not stack.alive(), 120, "an episode after the forgery")
    out = stack.output()
    assert stack.alive() and "refuses the bridge" not in out, out[-3000:]
    assert "ignored a /diagnostics status claiming to be /protocad/policy" in out, out[-3000:]
    assert stack.stop(signal.SIGINT, timeout=60) == 0, stack.output()[-3000:]
    assert "forged /diagnostics status(es) ignored" in stack.output()


def test_a_default_fleet_serves_only_signed_checkpoints_and_forged_status_completes_no_wait(
        spawn, probe, tmp_path):
    """Machine A publishes the learner's checkpoint, signed with the run key it makes; machine
    B's policy trusts that key (--trusted-key) and B waits until it serves a checkpoint. A
    stranger pushes an unsigned version and one signed by another key (refused, counted) and
    forges B's policy's diagnostics saying one is loaded (ignored: B keeps waiting). Then the
    learner's checkpoint appears: it is the one B serves."""
    from helpers.agents import save_agent

    from protocad_ros.checkpoint.agent_file import save_checkpoint
    from protocad_ros.model.agent import make_agent
    from protocad_ros.model.config import make_config

    dom = ["--domain-id", os.environ["ROS_DOMAIN_ID"]]
    topic = "/protocad/checkpoint"
    learner = tmp_path / "learner" / "latest.pt"   # not there yet: the publisher waits for it
    a = spawn("machine_a", "-m", "trainer.launch.fleet", "--no-actors", "--run-dir", str(tmp_path / "a"),
              "--publish-checkpoint", str(learner), "--checkpoint-topic", topic, *dom)
    wait_until(lambda: "publishing" in a.output() or not a.alive(), 90, "machine A's publisher")
    assert a.alive() and "signed: checkpoints signed with the run key" in a.output(), a.output()
    key, pub = tmp_path / "a" / "keys" / "checkpoint.key", tmp_path / "a" / "keys" / "checkpoint.pub"
    assert stat.S_IMODE(key.stat().st_mode) == 0o600

    own = tmp_path / "b" / "policy.pt"
    b = spawn("machine_b", "-m", "trainer.launch.fleet", "--robots", "1", "--first-robot", "0", "--episodes", "1",
              "--episode-length", "12", "--min-subscribers", "1", "--task", "pendulum_swingup", "--checkpoint", str(own),
              "--checkpoint-topic", topic, "--wait-for-checkpoint", "--trusted-key", str(pub),
              "--run-dir", str(tmp_path / "b"), *dom)
    fqn = "/protocad/robot0/policy"
    wait_until(lambda: probe.node_diag(fqn).get("lifecycle_state") == "active" or not b.alive(), 180,
               "B's policy to be active")
    stranger_dir = tmp_path / "stranger"
    stranger_dir.mkdir()
    generate_keypair(stranger_dir / "s.key", stranger_dir / "s.pub")
    save_agent(stranger_dir / "agent.pt", 666)
    data = (stranger_dir / "agent.pt").read_bytes()
    ann = topics.describe_checkpoint(data, topics.DEFAULT_CHUNK_SIZE, updates=666, task="pendulum_swingup",
                                     variant="protocad", preset="small")
    fake = FakeCheckpointPublisher(probe)
    fake.send(ann, chunks(data, topics.DEFAULT_CHUNK_SIZE))
    wait_until(lambda: probe.counter(fqn, "checkpoint_signatures_rejected") == 1, 60, "the unsigned push refused")
    fake.send(sign(ann, load_private_key(stranger_dir / "s.key")), chunks(data, topics.DEFAULT_CHUNK_SIZE))
    wait_until(lambda: probe.counter(fqn, "checkpoint_signatures_rejected") == 2, 60, "the other key's push refused")
    assert probe.node_diag(fqn)["agent"] == "random" and not own.exists()

    with Forger(probe, fqn, 0, "serving", {"checkpoint_updates": "666", "pending_checkpoint_updates": "666",
                                           "lifecycle_state": "active"}) as forger:
        wait_until(lambda: forger.sent >= 50, 30, "50 forged statuses sent")
        time.sleep(1.0)
        assert "running 1 actor group" not in b.output(), b.output()   # still waiting
    fake.close()

    agent = make_agent(make_config("pendulum_swingup", "small"), 1)
    agent.updates.fill_(3)
    save_checkpoint(learner, agent)
    try:
        wait_until(lambda: not b.alive(), 180, "B to finish its episode")
    except AssertionError:
        logs = tmp_path / "b" / "logs"
        raise AssertionError(b.output()[-3000:] + "".join(
            f"\n--- {f.name}\n" + f.read_text()[-2500:] for f in sorted(logs.glob("*.log")))
            + a.output()[-2000:]) from None
    assert b.p.returncode == 0 and "every bridge finished" in b.output(), b.output()
    assert "ignored a /diagnostics status claiming to be /protocad/robot0/policy" in b.output(), b.output()
    assert own.read_bytes() == learner.read_bytes() and (own.parent / "policy.pt.sig").is_file()
    log = (tmp_path / "b" / "logs" / "policy_robot0.log").read_text()
    assert f"now serving checkpoint {own} (updates=3)" in log
    assert not [ln for ln in log.splitlines() if "updates=666" in ln and "rejected" not in ln], log
    assert "serving only checkpoints signed by trusted key(s)" in log
    assert a.stop() == 0, a.output()


def test_fleet_refuses_a_checkpoint_topic_without_a_key_to_trust(tmp_path):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "trainer.launch.fleet", "--checkpoint", str(tmp_path / "p.pt"),
                        "--checkpoint-topic", "/protocad/checkpoint", "--run-dir", str(tmp_path / "run"),
                        "--domain-id", os.environ["ROS_DOMAIN_ID"]], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--trusted-key" in r.stderr and "--allow-unsigned" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "run" / "logs").exists()


class _RecordingStack:
    """Stands in for RosStack in protocad-fleet's run(): records what would be started, in order."""

    calls: list = []

    def __init__(self, *a, **kw):
        self.procs, self.domain_id = {}, 0

    def describe_discovery(self) -> str:
        return "recorded"

    def start_checkpoint_publisher(self, checkpoint, **kw):
        self.calls.append(("publisher", time.time_ns() // 1_000_000))

    def start_policy(self, **kw):
        self.calls.append(("policy", kw))

    def start_bridge(self, **kw):
        return type("Done", (), {"p": type("P", (), {"poll": staticmethod(lambda: 0)})()})()

    def stop_all(self):
        return {}

    def forged_note(self):
        return ""


@pytest.mark.parametrize("publishes", [True, False])
def test_a_fleet_gives_its_policies_the_publishers_current_seq_as_their_floor(tmp_path, monkeypatch, publishes):
    """Issue 54, point 5: with --publish-checkpoint and keys, the policy nodes start with
    min_checkpoint_seq = the time the fleet starts its publisher (the publisher signs every
    version with its clock, so all it announces is above and every version signed before is
    refused); an actor machine (no publisher) has none unless --min-checkpoint-seq says."""
    from trainer.launch import fleet

    _RecordingStack.calls = []
    monkeypatch.setattr(fleet, "RosStack", _RecordingStack)
    before = time.time_ns() // 1_000_000
    args = ["--checkpoint", str(tmp_path / "p.pt"), "--checkpoint-topic", "/protocad/checkpoint",
            "--run-dir", str(tmp_path / "run"), "--episodes", "1"]
    if publishes:
        args += ["--publish-checkpoint", str(tmp_path / "learner.pt")]
    else:
        generate_keypair(tmp_path / "k.key", tmp_path / "k.pub")
        args += ["--trusted-key", str(tmp_path / "k.pub")]
    assert fleet.run(fleet.build_parser().parse_args(args)) == 0
    policy = next(kw for what, kw in _RecordingStack.calls if what == "policy")
    if publishes:
        published = next(t for what, t in _RecordingStack.calls if what == "publisher")
        assert before <= policy["min_checkpoint_seq"] <= published, (before, policy, published)
    else:
        assert policy["min_checkpoint_seq"] == 0
    args += ["--min-checkpoint-seq", "1234"]
    _RecordingStack.calls = []
    assert fleet.run(fleet.build_parser().parse_args(args)) == 0
    assert next(kw for what, kw in _RecordingStack.calls if what == "policy")["min_checkpoint_seq"] == 1234


def test_a_contract_topic_claimed_with_another_type_ends_the_stack_non_zero_in_one_line(spawn, probe, tmp_path):
    """Issue 54, point 4: a stranger advertises /protocad/step_info as std_msgs/String before a
    default stack starts. Before, the recorder subscribed with the stranger's type, the bridge
    waited for its second reader forever (0 steps in 90 s). Now the recorder's ERROR line names
    the topic and both types, and protocad-stack exits non-zero within 60 s."""
    from std_msgs.msg import String

    squat = probe.node.create_publisher(String, "/protocad/step_info", 10)
    squat.publish(String(data="mine"))
    (tmp_path / "stack.yaml").write_text("bridge: {task: pendulum_swingup, episode_length: 30}\n"
                                         f"policy: {{num_threads: 1}}\nrecorder: {{output: {tmp_path / 'bag'}}}\n")
    started = time.monotonic()
    stack = spawn("stack", "-m", "trainer.launch.stack", str(tmp_path / "stack.yaml"),
                  "--log-dir", str(tmp_path / "logs"))
    wait_until(lambda: not stack.alive(), 60, "the stack to exit")
    took = time.monotonic() - started
    out = stack.output()
    assert stack.p.returncode not in (0, None), out[-3000:]
    log = (tmp_path / "logs" / "recorder.log").read_text()
    errors = [ln for ln in log.splitlines() if "[ERROR]" in ln]
    assert len(errors) == 1, log   # the node says it once (the stack shows it, then the log's tail)
    assert "/protocad/step_info is offered as std_msgs/msg/String" in errors[0], errors
    assert "its contract type is sensor_msgs/msg/JointState" in errors[0], errors
    assert errors[0].split("] ", 1)[-1] in out and "recorder exited with code 5" in out, out[-3000:]
    print(f"the stack exited {stack.p.returncode} after {took:.1f} s")


def test_a_forged_bridge_info_does_not_stop_a_stack(spawn, probe, tmp_path):
    """Issue 54, point 3: a stranger publishes one bridge_info naming another task to a running
    stack. Before, the policy refused its real bridge ("not answering ...: the checkpoint is for
    pendulum_swingup, the bridge runs walker_walk") and protocad-stack stopped 4 s later with
    exit 1. Now the policy believes bridge_info only from the writer of its observations (by
    writer GID): the forged one is ignored, counted and logged once, and the stack keeps
    answering."""
    from sensor_msgs.msg import JointState

    (tmp_path / "stack.yaml").write_text("bridge: {task: pendulum_swingup, episode_length: 30}\n"
                                         "policy: {num_threads: 1}\nrecorder: false\n")
    stack = spawn("stack", "-m", "trainer.launch.stack", str(tmp_path / "stack.yaml"),
                  "--log-dir", str(tmp_path / "logs"))
    wait_until(lambda: "[stack] running" in stack.output() or not stack.alive(), 240, "the stack to run")
    wait_until(lambda: "episode 1 " in stack.output() or not stack.alive(), 120, "a first episode")
    forged = probe.node.create_publisher(JointState, "/protocad/bridge_info", qos.announcement_qos())
    forged.publish(topics.fill_bridge_info(JointState(), topics.BridgeInfo(
        task="walker_walk", action_names=[f"a{i}" for i in range(6)], control_dt=0.025, image_size=64)))
    wait_until(lambda: probe.counter("/protocad/policy", "bridge_info_ignored") >= 1 or not stack.alive(), 60,
               "the forged bridge_info ignored")
    episodes = stack.output().count("finished: return")
    wait_until(lambda: stack.output().count("finished: return") >= episodes + 2 or not stack.alive(), 120,
               "two more episodes after the forgery")
    out = stack.output()
    assert stack.alive() and "not answering this sim bridge" not in out, out[-3000:]
    ignored = [ln for ln in out.splitlines() if "ignored a bridge_info (task 'walker_walk')" in ln]
    assert len(ignored) == 1, out[-3000:]
    assert stack.stop(signal.SIGINT, timeout=60) == 0, stack.output()[-3000:]
