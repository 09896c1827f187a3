"""Checkpoints delivered over ROS (msgs_docs/policy.md#checkpoints-over-ros): the learner's file
on one side, a policy node that only knows the topic on the other, real processes over DDS
(this machine only, the run's own domain).

The checkpoint publisher watches a learner directory written by save_checkpoint, as the trainer
writes it. The policy runs in a directory of its own, with its own checkpoint path, and is given
only the topic. Observations come from this test process (Feeder), so the test decides where
episodes start and can tell which version served each one.
"""
from __future__ import annotations

import hashlib
import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from std_msgs.msg import String, UInt8MultiArray

from ros_helpers import Probe, wait_until
from sim_bridge import qos, topics
from test_policy_node import START, TASK, Feeder, _save, policy_args

TIMEOUT_S = 5.0   # the policy's checkpoint_transfer_timeout_s: how long a version may be partial


@pytest.fixture
def probe():
    p = Probe("checkpoint_delivery_probe")
    yield p
    p.close()


class FakeCheckpointPublisher:
    """A FAKE sender, named as such: a healthy DDS link neither corrupts nor drops a reliable
    chunk, so the faults a receiver must survive (a flipped byte, a short chunk, bytes that are
    no checkpoint, a sender that stops half-way) are made here. It speaks the publisher's
    protocol (sim_bridge.topics helpers, the same QoS) but announces whatever it is told."""

    def __init__(self, probe: Probe):
        self.probe = probe
        self.announce = probe.publisher(topics.CHECKPOINT, String, qos.announcement_qos())
        self.chunk_pub = None

    def send(self, ann: topics.CheckpointAnnouncement, chunks: list[bytes]) -> None:
        node = self.probe.node
        if self.chunk_pub is not None:
            node.destroy_publisher(self.chunk_pub)
        self.chunk_pub = node.create_publisher(
            UInt8MultiArray, self.probe.topic(topics.chunks_topic(topics.CHECKPOINT)),
            qos.checkpoint_chunks_qos(len(chunks)))
        for i, piece in enumerate(chunks):
            self.chunk_pub.publish(topics.fill_checkpoint_chunk(UInt8MultiArray(), ann.sha256, i,
                                                                ann.n_chunks, piece))
        self.announce.publish(String(data=topics.checkpoint_announcement_json(ann)))

    def close(self) -> None:
        for pub in (self.announce, self.chunk_pub):
            if pub is not None:
                self.probe.node.destroy_publisher(pub)


def _chunks(data: bytes, size: int) -> list[bytes]:
    return [data[i:i + size] for i in range(0, len(data), size)]


def test_new_versions_reach_a_policy_that_sees_only_the_topic_and_bad_ones_are_refused(
        spawn, probe, tmp_path):
    learner = tmp_path / "learner" / "agent.pt"
    _save(learner, 5, seed=1)
    publisher = spawn("publisher", "-m", "trainer.checkpoint_publisher", "--ros-args",
                      "-p", f"checkpoint:={learner}", "-p", "poll_s:=0.1",
                      "-p", "diagnostics_period_s:=0.1")
    wait_until(lambda: probe.node_diag("checkpoint_publisher").get("versions_announced") == "1",
               START, "the publisher's first announcement")

    # Started after the announcement: the latched topics must still bring it the version.
    robot = tmp_path / "robot"
    robot.mkdir()
    served = robot / "served.pt"
    f = Feeder(probe)
    policy = spawn("policy", *policy_args(f"checkpoint:={served}", "checkpoint_topic:=checkpoint",
                                          f"checkpoint_transfer_timeout_s:={TIMEOUT_S}"), cwd=robot)
    assert not any(str(learner.parent) in a for a in policy.args)
    wait_until(f.ready, START, "the policy's subscriptions and publishers to match")
    node = "policy"
    wait_until(lambda: probe.node_diag(node).get("pending_checkpoint_updates") == "5", 30,
               "version 1 (updates=5) to be received and loaded")
    v1 = learner.read_bytes()
    assert served.read_bytes() == v1
    f.obs(10, 0, is_first=True)
    f.obs(20, 1)
    f.wait_answers(2, "episode 0")
    wait_until(lambda: probe.node_diag(node).get("checkpoint_updates") == "5", 10, "updates=5")
    d = probe.node_diag(node)
    assert d["checkpoint/env_steps"] == "500"
    assert d["checkpoint_sha256"] == hashlib.sha256(v1).hexdigest()
    assert probe.node_diag("checkpoint_publisher")["sha256"] == d["checkpoint_sha256"]

    # The learner writes a new version: it reaches the policy, which serves it from the next
    # episode on (not in the middle of this one).
    _save(learner, 7, seed=2)
    wait_until(lambda: probe.node_diag(node).get("pending_checkpoint_updates") == "7", 30,
               "version 2 (updates=7) to be received and loaded")
    f.obs(30, 2)
    f.wait_answers(3, "episode 0, step 2")
    assert probe.node_diag(node)["checkpoint_updates"] == "5"
    f.obs(40, 0, episode=1, is_first=True)
    f.wait_answers(4, "episode 1")
    wait_until(lambda: probe.node_diag(node).get("checkpoint_updates") == "7", 10, "updates=7")
    v2 = learner.read_bytes()
    d = probe.node_diag(node)
    assert d["checkpoint_sha256"] == hashlib.sha256(v2).hexdigest() and served.read_bytes() == v2
    assert (d["checkpoint_transfers"], d["checkpoint_reloads"]) == ("2", "2")

    # Faulty transfers of another version: each is refused with its reason, counted, and the
    # policy goes on serving version 2 (file on disk included, for a restart).
    other = tmp_path / "other.pt"
    _save(other, 9, seed=3)
    data = other.read_bytes()
    size = topics.DEFAULT_CHUNK_SIZE
    ann = topics.describe_checkpoint(data, size, updates=9, task=TASK, variant="protocad")
    flipped = bytearray(data[size:2 * size])
    flipped[123] ^= 0xFF
    junk = bytes(range(256)) * 4000
    fake = FakeCheckpointPublisher(probe)
    cases = [
        (ann, [data[:size], bytes(flipped), *_chunks(data[2 * size:], size)], "checksum mismatch"),
        (ann, [*_chunks(data, size)[:-1], _chunks(data, size)[-1][:-10]], "size mismatch"),
        (topics.describe_checkpoint(junk, size), _chunks(junk, size), "not a usable checkpoint"),
        (ann, _chunks(data, size)[:-1], "incomplete"),     # the sender stops half-way
    ]
    for n, (announcement, chunks, reason) in enumerate(cases, start=1):
        fake.send(announcement, chunks)
        wait_until(lambda: probe.counter(node, "checkpoint_transfers_rejected") == n,
                   TIMEOUT_S + 30, f"the {reason} transfer to be rejected")
        assert reason in policy.output()
    f.obs(50, 1, episode=1)
    f.obs(60, 0, episode=2, is_first=True)
    f.wait_answers(6, "answers after the refused transfers")
    wait_until(lambda: probe.counter(node, "episodes") == 3, 10, "diagnostics after episode 2 began")
    d = probe.node_diag(node)
    assert d["checkpoint_updates"] == "7" and d["checkpoint_sha256"] == hashlib.sha256(v2).hexdigest()
    assert served.read_bytes() == v2 and d["_level"] == 1   # WARN: something was refused
    assert [topics.stamp_to_ns(m.header.stamp) for m in list(f.actions)] == [10, 20, 30, 40, 50, 60]

    assert policy.stop() == 0
    out = policy.output()
    assert out.count(f"checkpoint version {ann.short_id} (updates=9) from /protocad/checkpoint rejected") == 3
    assert "still serving checkpoint" in out and "Traceback" not in out

    # A restarted policy serves the version it received last at once, from its own file, and
    # does not fetch the same version again when the publisher's announcement reaches it.
    fake.close()
    wait_until(lambda: probe.node_diag("checkpoint_publisher").get("subscribers") == "0", 30,
               "the first policy to leave the graph")
    again = spawn("policy_again", *policy_args(f"checkpoint:={served}", "checkpoint_topic:=checkpoint"),
                  cwd=robot)
    wait_until(lambda: probe.node_diag(node).get("checkpoint_announced") == hashlib.sha256(v2).hexdigest(),
               START, "the publisher's announcement to reach the restarted policy")
    f.obs(70, 0, episode=0, is_first=True)
    f.wait_answers(7, "the restarted policy's first answer")
    wait_until(lambda: probe.counter(node, "episodes") == 1, 10, "the restarted policy's diagnostics")
    d = probe.node_diag(node)
    assert d["checkpoint_updates"] == "7" and d["checkpoint_sha256"] == hashlib.sha256(v2).hexdigest()
    assert (d["checkpoint_transfers"], d["checkpoint_transfers_rejected"]) == ("0", "0")
    assert again.stop() == 0 and publisher.stop() == 0
    assert "Traceback" not in again.output() + publisher.output()


def test_start_without_a_file_to_work_with_is_a_configuration_error(spawn):
    publisher = spawn("publisher", "-m", "trainer.checkpoint_publisher")
    policy = spawn("policy", *policy_args("checkpoint_topic:=checkpoint"))
    for proc, says in ((publisher, "checkpoint is required"), (policy, "needs checkpoint:=FILE")):
        wait_until(lambda: not proc.alive(), START, f"{proc.args} to exit")
        assert proc.p.returncode == 2 and says in proc.output()


@pytest.mark.parametrize("text, why", [
    ("{not json", "not JSON"),
    ('{"format": "other"}', "format"),
    ('{"format": "protocad-ros/checkpoint-announcement", "sha256": "abc"}', "sha256"),
    ('{"format": "protocad-ros/checkpoint-announcement", "sha256": "' + "a" * 64 + '", "size": 10, '
     '"chunk_size": 4, "n_chunks": 2}', "n_chunks=2 does not match"),
    ('{"format": "protocad-ros/checkpoint-announcement", "sha256": "' + "a" * 64 + '", "size": -1, '
     '"chunk_size": 4, "n_chunks": 1}', "size must be"),
])
def test_a_malformed_announcement_says_what_is_wrong(text, why):
    with pytest.raises(ValueError, match=why):
        topics.read_checkpoint_announcement(text)


def test_announcement_round_trip_keeps_every_field():
    a = topics.describe_checkpoint(b"x" * 10, 4, updates=3, task=TASK, variant="dreamer", preset="small",
                                   seq=2, counters={"env_steps": 600})
    assert topics.read_checkpoint_announcement(topics.checkpoint_announcement_json(a)) == a
    assert (a.n_chunks, a.sha256) == (3, hashlib.sha256(b"x" * 10).hexdigest())


def test_docs_cover_every_publisher_parameter_and_counter():
    from conftest import ROOT
    from trainer.checkpoint_publisher import COUNTERS, PARAMS

    doc = (ROOT / "msgs_docs" / "checkpoint_publisher.md").read_text()
    missing = [n for n in [p.name for p in PARAMS] + list(COUNTERS) if f"`{n}`" not in doc]
    assert not missing, f"msgs_docs/checkpoint_publisher.md does not document {missing}"


@pytest.fixture(scope="module")
def receiving_policy(tmp_path_factory):
    """An in-process policy node with checkpoint_topic, for driving its receiver's callbacks."""
    import rclpy
    from rclpy.parameter import Parameter

    from protocad_ros.policy_node import PolicyNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    path = tmp_path_factory.mktemp("robot") / "agent.pt"
    node = PolicyNode(namespace="/fuzz_ckpt", context=ctx, parameter_overrides=[
        Parameter("task", value=TASK), Parameter("num_threads", value=1),
        Parameter("checkpoint", value=str(path)), Parameter("checkpoint_topic", value="checkpoint")])
    yield node
    node.close()
    node.destroy_node()
    rclpy.shutdown(context=ctx)


json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                           lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                                       max_size=3), max_leaves=8)
announcements = st.one_of(st.text(max_size=40), json_values.map(json.dumps), st.fixed_dictionaries(
    {"format": st.just(topics.ANNOUNCEMENT_FORMAT), "sha256": st.text("0123456789abcdef", min_size=63, max_size=65),
     "size": json_values, "chunk_size": json_values, "n_chunks": json_values, "updates": json_values,
     "seq": json_values, "counters": json_values}).map(json.dumps))


@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(text=announcements, label=st.text(max_size=80), data=st.binary(max_size=64))
def test_no_announcement_or_chunk_breaks_the_receiver(receiving_policy, text, label, data):
    from std_msgs.msg import MultiArrayDimension

    receiver = receiving_policy.receiver
    before = receiving_policy.counters["checkpoint_transfers_rejected"]
    receiver._on_announcement(String(data=text))      # must not raise
    try:
        topics.read_checkpoint_announcement(text)
    except ValueError:
        assert receiving_policy.counters["checkpoint_transfers_rejected"] == before + 1
    chunk = UInt8MultiArray(data=data)
    chunk.layout.dim = [MultiArrayDimension(label=label, size=len(data), stride=len(data))]
    receiver._on_chunk(chunk)
    assert receiving_policy.callback_errors == 0


def test_receiver_order_supersession_and_disagreeing_chunks():
    """In process, callbacks driven directly: chunks may beat their announcement (two topics);
    the newest announcement wins over a version still coming in; chunks numbered for another
    chunk count never complete a version, and one of them after the announcement rejects it."""
    import rclpy
    from rclpy.node import Node

    from protocad_ros.checkpoint_receiver import CheckpointReceiver

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node("receiver_probe", namespace="/receiver_test", context=ctx)
    woken, counted = [], []
    r = CheckpointReceiver(node, "checkpoint", timeout_s=60.0, wake=lambda: woken.append(1),
                           next_sha=lambda: None, serving=lambda: "nothing",
                           count=lambda key, why=None: counted.append((key, why)))

    def chunk(a, i, data, n=None):
        return topics.fill_checkpoint_chunk(UInt8MultiArray(), a.sha256, i, n or a.n_chunks, data)

    def announce(a):
        r._on_announcement(String(data=topics.checkpoint_announcement_json(a)))

    try:
        one, two = b"1" * 10, b"2" * 10
        a1, a2 = topics.describe_checkpoint(one, 4), topics.describe_checkpoint(two, 4)
        for i, piece in enumerate(_chunks(one, 4)):
            r._on_chunk(chunk(a1, i, piece))
        assert woken == []                                   # nothing announced yet
        announce(a1)
        assert woken == [1] and r._received.verify() == one  # whole as soon as announced
        r._received = None

        announce(a2)
        r._on_chunk(chunk(a2, 0, two[:4]))
        announce(a1)                                         # the newest: a2 is dropped
        r._on_chunk(chunk(a2, 1, two[4:8]))
        r._on_chunk(chunk(a2, 2, two[8:]))
        assert woken == [1]                                  # a2 whole, but not announced now
        for i, piece in enumerate(_chunks(one, 4)):          # a1's new writer sends it again
            r._on_chunk(chunk(a1, i, piece))
        assert woken == [1, 1] and r._received.verify() == one
        r._received = None

        # Chunks of a2 numbered as if it had 5 chunks: they never complete it, and one that
        # arrives after the announcement rejects it at once (a sender that contradicts itself).
        three = b"3" * 10
        a3 = topics.describe_checkpoint(three, 4)
        for i in (3, 4):
            r._on_chunk(chunk(a3, i, b"x", n=5))
        announce(a3)
        r._on_chunk(chunk(a3, 0, three[:4]))
        r._on_chunk(chunk(a3, 1, three[4:8]))
        assert woken == [1, 1] and r.announced == a3        # still waiting for chunk 2
        r._on_chunk(chunk(a3, 2, three[8:], n=5))
        assert woken == [1, 1] and counted == [(CheckpointReceiver.REJECTED, None)]
        assert r.announced is None                           # rejected, nothing coming in
    finally:
        r.destroy()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
