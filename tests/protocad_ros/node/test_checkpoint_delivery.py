"""Checkpoints delivered over ROS (msgs_docs/policy.md#checkpoints-over-ros): the learner's file
on one side, a policy node that only knows the topic on the other, real processes over DDS
(this machine only, the run's own domain).

The checkpoint publisher watches a learner directory written by save_checkpoint, as the trainer
writes it. The policy runs in a directory of its own, with its own checkpoint path, and is given
only the topic. Observations come from this test process (Feeder), so the test decides where
episodes start and can tell which version served each one. With trusted keys
(msgs_docs/security.md) the strangers on the domain are this test process: plain rclpy writers
that announce and send whatever they are told.
"""
from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
from pathlib import Path
from typing import Any

import pytest
from helpers import Proc, wait_until
from helpers.agents import save_agent
from helpers.checkpoints import FakeCheckpointPublisher
from helpers.checkpoints import chunks as _chunks
from helpers.checkpoints import sign as _sign
from helpers.policy import START, TASK, Feeder, policy_args
from helpers.ros import Probe
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from std_msgs.msg import String, UInt8MultiArray

from protocad_ros.checkpoint.signing import generate_keypair, load_private_key, next_seq, sign_file, signature_path
from protocad_ros.node.checkpoint_receiver import CheckpointReceiver, ReceiverSettings
from sim_bridge.contract import qos, topics

TIMEOUT_S = 5.0   # the policy's checkpoint_transfer_timeout_s: how long a version may be partial


@pytest.fixture
def probe():
    p = Probe("checkpoint_delivery_probe")
    yield p
    p.close()


@dataclasses.dataclass
class _Delivery:
    """One publisher-to-policy run: the processes, the files and this process's ends."""
    probe: Probe
    feeder: Feeder
    publisher: Proc
    policy: Proc
    learner: Path   # the learner's checkpoint, watched by the publisher
    robot: Path     # the policy's own directory
    served: Path    # the policy's own checkpoint path

    def diag(self) -> dict[str, str]:
        return self.probe.node_diag("policy")

    def counter(self, key: str) -> float:
        return self.probe.counter("policy", key)


def _first_version_reaches_a_late_policy(spawn, probe, tmp_path) -> _Delivery:
    """The publisher announces version 1; a policy started afterwards, given only the topic,
    still gets it (latched topics) and serves it from its first episode."""
    learner = tmp_path / "learner" / "agent.pt"
    save_agent(learner, 5, seed=1)
    publisher = spawn("publisher", "-m", "trainer.nodes.checkpoint_publisher", "--ros-args",
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
                                          "allow_unsigned:=true",
                                          f"checkpoint_transfer_timeout_s:={TIMEOUT_S}"), cwd=robot)
    assert not any(str(learner.parent) in a for a in policy.args)
    run = _Delivery(probe, f, publisher, policy, learner, robot, served)
    wait_until(f.ready, START, "the policy's subscriptions and publishers to match")
    wait_until(lambda: run.diag().get("pending_checkpoint_updates") == "5", 30,
               "version 1 (updates=5) to be received and loaded")
    v1 = learner.read_bytes()
    assert served.read_bytes() == v1
    f.obs(10, 0, is_first=True)
    f.obs(20, 1)
    f.wait_answers(2, "episode 0")
    wait_until(lambda: run.diag().get("checkpoint_updates") == "5", 10, "updates=5")
    d = run.diag()
    assert d["checkpoint/env_steps"] == "500"
    assert d["checkpoint_sha256"] == hashlib.sha256(v1).hexdigest()
    assert probe.node_diag("checkpoint_publisher")["sha256"] == d["checkpoint_sha256"]
    return run


def _a_new_version_is_served_from_the_next_episode(run: _Delivery) -> bytes:
    """The learner writes a new version: it reaches the policy, which serves it from the next
    episode on (not in the middle of this one). Its bytes."""
    f = run.feeder
    save_agent(run.learner, 7, seed=2)
    wait_until(lambda: run.diag().get("pending_checkpoint_updates") == "7", 30,
               "version 2 (updates=7) to be received and loaded")
    f.obs(30, 2)
    f.wait_answers(3, "episode 0, step 2")
    assert run.diag()["checkpoint_updates"] == "5"
    f.obs(40, 0, episode=1, is_first=True)
    f.wait_answers(4, "episode 1")
    wait_until(lambda: run.diag().get("checkpoint_updates") == "7", 10, "updates=7")
    v2 = run.learner.read_bytes()
    d = run.diag()
    assert d["checkpoint_sha256"] == hashlib.sha256(v2).hexdigest() and run.served.read_bytes() == v2
    assert (d["checkpoint_transfers"], d["checkpoint_reloads"]) == ("2", "2")
    return v2


def _faulty_transfers_are_refused(run: _Delivery, tmp_path, v2: bytes) -> FakeCheckpointPublisher:
    """Faulty transfers of another version: each is refused with its reason, counted, and the
    policy goes on serving version 2 (file on disk included, for a restart). With per-chunk
    hashes a flipped byte or a short chunk is dropped alone (the version then never completes);
    without them (an older sender) the whole version fails its sha256. Stops the policy."""
    f, policy = run.feeder, run.policy
    other = tmp_path / "other.pt"
    save_agent(other, 9, seed=3)
    data = other.read_bytes()
    size = topics.DEFAULT_CHUNK_SIZE
    ann = topics.describe_checkpoint(data, size, updates=9, task=TASK, variant="protocad")
    legacy = dataclasses.replace(ann, chunk_sha256=())
    flipped = bytearray(data[size:2 * size])
    flipped[123] ^= 0xFF
    pieces = _chunks(data, size)
    junk = bytes(range(256)) * 4000
    fake = FakeCheckpointPublisher(run.probe)
    dropped = run.counter("checkpoint_chunks_dropped")
    cases = [
        (ann, [pieces[0], bytes(flipped), *pieces[2:-1], pieces[-1][:-10]], "incomplete"),
        (legacy, [pieces[0], bytes(flipped), *pieces[2:]], "checksum mismatch"),
        (topics.describe_checkpoint(junk, size), _chunks(junk, size), "not a usable checkpoint"),
    ]
    for n, (announcement, chunks, reason) in enumerate(cases, start=1):
        fake.send(announcement, chunks)
        wait_until(lambda: run.counter("checkpoint_transfers_rejected") == n,
                   TIMEOUT_S + 30, f"the {reason} transfer to be rejected")
        assert reason in policy.output()
    # The flipped and the short chunk (and the chunks that beat each announcement) were dropped.
    assert run.counter("checkpoint_chunks_dropped") >= dropped + 2
    f.obs(50, 1, episode=1)
    f.obs(60, 0, episode=2, is_first=True)
    f.wait_answers(6, "answers after the refused transfers")
    wait_until(lambda: run.counter("episodes") == 3, 10, "diagnostics after episode 2 began")
    d = run.diag()
    assert d["checkpoint_updates"] == "7" and d["checkpoint_sha256"] == hashlib.sha256(v2).hexdigest()
    assert run.served.read_bytes() == v2 and d["_level"] == 1   # WARN: something was refused
    assert [topics.stamp_to_ns(m.header.stamp) for m in list(f.actions)] == [10, 20, 30, 40, 50, 60]

    assert policy.stop() == 0
    out = policy.output()
    assert out.count(f"checkpoint version {ann.short_id} (updates=9) from /protocad/checkpoint rejected") == 2
    assert "still serving checkpoint" in out and "Traceback" not in out
    assert "accepts UNSIGNED checkpoints over checkpoint" in out     # no trusted_keys: said at start
    return fake


def _a_restarted_policy_serves_its_last_version_at_once(run: _Delivery, spawn, v2: bytes) -> None:
    """A restarted policy serves the version it received last at once, from its own file, and
    does not fetch the same version again when the publisher's announcement reaches it."""
    probe, f = run.probe, run.feeder
    wait_until(lambda: probe.node_diag("checkpoint_publisher").get("subscribers") == "0", 30,
               "the first policy to leave the graph")
    again = spawn("policy_again", *policy_args(f"checkpoint:={run.served}", "checkpoint_topic:=checkpoint",
                                               "allow_unsigned:=true"), cwd=run.robot)
    wait_until(lambda: run.diag().get("checkpoint_announced") == hashlib.sha256(v2).hexdigest(),
               START, "the publisher's announcement to reach the restarted policy")
    f.obs(70, 0, episode=0, is_first=True)
    f.wait_answers(7, "the restarted policy's first answer")
    wait_until(lambda: run.counter("episodes") == 1, 10, "the restarted policy's diagnostics")
    d = run.diag()
    assert d["checkpoint_updates"] == "7" and d["checkpoint_sha256"] == hashlib.sha256(v2).hexdigest()
    assert (d["checkpoint_transfers"], d["checkpoint_transfers_rejected"]) == ("0", "0")
    assert again.stop() == 0 and run.publisher.stop() == 0
    assert "Traceback" not in again.output() + run.publisher.output()


@pytest.mark.ros
@pytest.mark.process
def test_new_versions_reach_a_policy_that_sees_only_the_topic_and_bad_ones_are_refused(
        spawn, probe, tmp_path):
    run = _first_version_reaches_a_late_policy(spawn, probe, tmp_path)
    v2 = _a_new_version_is_served_from_the_next_episode(run)
    fake = _faulty_transfers_are_refused(run, tmp_path, v2)
    fake.close()
    _a_restarted_policy_serves_its_last_version_at_once(run, spawn, v2)


WALKER = "walker_walk"   # 6-d actions, as cheetah_run: another task of the same action size


def _save_task(path, task: str, updates: int, seed: int = 0) -> bytes:
    """A small-preset checkpoint of `task`, written as the trainer writes it; its bytes."""
    from protocad_ros.checkpoint.agent_file import save_checkpoint
    from protocad_ros.model.agent import make_agent
    from protocad_ros.model.config import make_config
    from sim_bridge.contract.contexts import task_actuators

    agent = make_agent(make_config(task, "small", **{"train.seed": seed}), len(task_actuators(task)))
    agent.updates.fill_(updates)
    save_checkpoint(path, agent, counters={"env_steps": 100 * updates})
    return Path(path).read_bytes()


def _with_config(data: bytes, section: str, key: str, value) -> bytes:
    """The checkpoint's bytes with one config field changed (its weights left as they are)."""
    import torch

    payload = torch.load(io.BytesIO(data), weights_only=True)
    payload["config"][section][key] = value
    buf = io.BytesIO()
    torch.save(payload, buf)
    return buf.getvalue()


def _rss_anon_mb(pid: int) -> float:
    """The process's private resident memory (heap; shared-memory transport pages excluded)."""
    status = Path(f"/proc/{pid}/status").read_text()
    return int(next(line.split()[1] for line in status.splitlines() if line.startswith("RssAnon:"))) / 1024


def _write_signed(path: Path, data: bytes, key, seq: int) -> None:
    """The file, then its FILE.sig, each appearing at once: both are made beside it first, since
    signing reads the checkpoint back and on loaded cores that alone can outlast the policy's
    grace for a missing signature (which would count a refusal the test did not mean)."""
    staged = path.with_name(path.name + ".staged")
    staged.write_bytes(data)
    sign_file(staged, key, seq)
    os.replace(staged, path)
    os.replace(signature_path(staged), signature_path(path))


def _keyed_policy_args(served, pub, *extra: str) -> list[str]:
    args = ["-m", "protocad_ros.node.policy_node", "--ros-args", "-p", f"task:={WALKER}",
            "-p", "diagnostics_period_s:=0.1", "-p", "num_threads:=1", "-p", f"checkpoint:={served}",
            "-p", "checkpoint_topic:=checkpoint", "-p", f"trusted_keys:={pub}",
            "-p", f"checkpoint_transfer_timeout_s:={TIMEOUT_S}"]
    for p in extra:
        args += ["-p", p]
    return args


@dataclasses.dataclass
class _Signed:
    """A run with trusted keys: the learner signs, the policy trusts its public key."""
    run: _Delivery
    learner: Any          # the learner's private key
    learner_pub: Path     # its public key file, the policy's trusted_keys
    stranger: Any         # another private key
    announcements: list   # every announcement this process saw
    v1: bytes
    v1_announcement: str


def _signed_version_1_is_served(spawn, probe, tmp_path, keys) -> _Signed:
    learner_key, learner_pub, learner = keys["learner"]
    path = tmp_path / "learner" / "agent.pt"
    v1 = _save_task(path, WALKER, 5, seed=1)
    announcements = probe.record(topics.CHECKPOINT, String, qos.announcement_qos())
    publisher = spawn("publisher", "-m", "trainer.nodes.checkpoint_publisher", "--ros-args",
                      "-p", f"checkpoint:={path}", "-p", "poll_s:=0.1", "-p", "diagnostics_period_s:=0.1",
                      "-p", f"signing_key:={learner_key}")
    robot = tmp_path / "robot"
    robot.mkdir()
    served = robot / "served.pt"
    f = Feeder(probe)
    policy = spawn("policy", *_keyed_policy_args(served, learner_pub), cwd=robot)
    run = _Delivery(probe, f, publisher, policy, path, robot, served)
    wait_until(f.ready, START, "the policy's subscriptions and publishers to match")
    wait_until(lambda: run.diag().get("pending_checkpoint_updates") == "5", 60,
               "signed version 1 to be received and loaded")
    assert served.read_bytes() == v1 and (robot / "served.pt.sig").is_file()
    v1_announcement = next(m.data for m in list(announcements)
                           if json.loads(m.data)["sha256"] == hashlib.sha256(v1).hexdigest())
    f.obs(10, 0, is_first=True)
    f.wait_answers(1, "the first answer")
    return _Signed(run, learner, learner_pub, keys["stranger"][2], announcements, v1, v1_announcement)


def _strangers_chunks_do_not_stop_version_2(signed: _Signed, tmp_path) -> tuple[bytes, int, Any]:
    """A stranger's chunks for the learner's next version, sent before it is announced: wrong
    bytes and a wrong length. The genuine version still completes. Its bytes, its sequence
    number, the stranger's chunk writer."""
    run, probe, f = signed.run, signed.run.probe, signed.run.feeder
    scratch = tmp_path / "scratch" / "agent.pt"
    v2 = _save_task(scratch, WALKER, 7, seed=2)
    sha2, n2 = hashlib.sha256(v2).hexdigest(), -(-len(v2) // topics.DEFAULT_CHUNK_SIZE)
    stranger_pub = probe.publisher(topics.chunks_topic(topics.CHECKPOINT), UInt8MultiArray,
                                   qos.checkpoint_chunks_qos(2))
    wait_until(lambda: stranger_pub.get_subscription_count() >= 1, START, "the stranger's chunk writer to match")
    dropped = run.counter("checkpoint_chunks_dropped")
    stranger_pub.publish(topics.fill_checkpoint_chunk(UInt8MultiArray(), sha2, 0, n2,
                                                      bytes(topics.DEFAULT_CHUNK_SIZE)))
    stranger_pub.publish(topics.fill_checkpoint_chunk(UInt8MultiArray(), sha2, 1, n2, b"short"))
    os.replace(scratch, run.learner)
    wait_until(lambda: run.diag().get("pending_checkpoint_updates") == "7", 60,
               "signed version 2 to arrive despite the stranger's chunks")
    wait_until(lambda: run.counter("checkpoint_chunks_dropped") >= dropped + 2, 30, "the stranger's chunks dropped")
    f.obs(20, 0, episode=1, is_first=True)
    f.wait_answers(2, "episode 1")
    wait_until(lambda: run.diag().get("checkpoint_updates") == "7", 10, "version 2 served")
    seq2 = int(run.diag()["checkpoint_seq"])
    # what the node serves is what the learner announced for version 2 (the probe may see that
    # announcement a moment after the node: wait for it rather than read the newest one so far)
    wait_until(lambda: any(json.loads(m.data)["seq"] == seq2 and json.loads(m.data)["sha256"] == sha2
                           for m in list(signed.announcements)), 30, "version 2's announcement with the served seq")
    return v2, seq2, stranger_pub


def _refused_versions_are_counted_by_kind(signed: _Signed, tmp_path, v2: bytes):
    """Refused versions, each counted by kind (and in checkpoint_transfers_rejected); then one
    signed by the learner with chunk 0 too short. Version 3's bytes, a cheetah checkpoint's
    bytes, the fake sender."""
    run, stranger, learner = signed.run, signed.stranger, signed.learner
    count, policy = run.counter, run.policy
    size = topics.DEFAULT_CHUNK_SIZE
    v3 = _save_task(tmp_path / "v3" / "agent.pt", WALKER, 9, seed=3)
    ann3 = topics.describe_checkpoint(v3, size, updates=9, task=WALKER, variant="protocad", preset="small")
    huge = _with_config(v2, "world_model", "deter", 16384)   # the largest a config may ask for
    cheetah = _save_task(tmp_path / "cheetah" / "agent.pt", "cheetah_run", 9)
    fake = FakeCheckpointPublisher(run.probe)
    fake_sha = "f" * 64

    def huge_ann(size_, chunk):
        return topics.CheckpointAnnouncement(fake_sha, size_, chunk, -(-size_ // chunk), task=WALKER)

    cases = [   # (how it is sent, counter, what the log says)
        (lambda: fake.send(_sign(ann3, stranger), _chunks(v3, size)), "checkpoint_signatures_rejected",
         "which is not trusted here"),
        (lambda: fake.send(ann3, _chunks(v3, size)), "checkpoint_signatures_rejected", "unsigned"),
        (lambda: fake.announce_only(signed.v1_announcement), "checkpoint_rollbacks_rejected", "rollback"),
        (lambda: fake.announce_only(huge_ann(1 << 30, size)), "checkpoint_limits_rejected",
         "max_checkpoint_bytes"),
        (lambda: fake.announce_only(huge_ann(256 << 20, 4096)), "checkpoint_limits_rejected", "chunks, more than"),
        (lambda: fake.announce_only(huge_ann(200 << 20, 128 << 20)), "checkpoint_limits_rejected", "chunk_size"),
        (lambda: fake.send(_sign(topics.describe_checkpoint(huge, size, updates=7, task=WALKER,
                                                            variant="protocad"), learner), _chunks(huge, size)),
         "checkpoint_mismatches", "world_model.deter: 128 != 16384"),
        (lambda: fake.send(_sign(topics.describe_checkpoint(cheetah, size, updates=9, task="cheetah_run",
                                                            variant="protocad"), learner), _chunks(cheetah, size)),
         "checkpoint_mismatches", "it is for cheetah_run, this node serves walker_walk"),
    ]
    rejected = count("checkpoint_transfers_rejected")
    for send, key, says in cases:
        before = count(key)
        send()
        wait_until(lambda: count(key) == before + 1, 60, f"a refusal counted in {key} ({says})")
        rejected += 1
        assert count("checkpoint_transfers_rejected") == rejected
        wait_until(lambda: says in policy.output(), 10, f"{says!r} in the policy's log")
    # Signed by the learner, but chunk 0 too short and no good copy: dropped, then incomplete.
    dropped = count("checkpoint_chunks_dropped")
    signed3 = _sign(ann3, learner)
    fake.send(signed3, [_chunks(v3, size)[0][:-1], *_chunks(v3, size)[1:]])
    wait_until(lambda: count("checkpoint_transfers_rejected") == rejected + 1, TIMEOUT_S + 30,
               "the transfer with a short chunk to time out")
    assert count("checkpoint_chunks_dropped") > dropped and "incomplete" in policy.output()
    return v3, cheetah, fake


def _a_flood_of_unannounced_chunks_leaves_memory_flat(run: _Delivery):
    """A flood of chunks of a version nobody announced, ever new indices: dropped unbuffered,
    memory stays flat. The flood's writer."""
    probe, count, size = run.probe, run.counter, topics.DEFAULT_CHUNK_SIZE
    flood = probe.node.create_publisher(UInt8MultiArray, probe.topic(topics.chunks_topic(topics.CHECKPOINT)),
                                        qos.checkpoint_chunks_qos(16))
    wait_until(lambda: flood.get_subscription_count() >= 1, START, "the flood writer to match")
    rss0, dropped = _rss_anon_mb(run.policy.p.pid), count("checkpoint_chunks_dropped")
    payload, flood_sha = os.urandom(size), hashlib.sha256(b"flood").hexdigest()
    for batch in range(12):
        for i in range(16):
            flood.publish(topics.fill_checkpoint_chunk(UInt8MultiArray(), flood_sha, batch * 16 + i,
                                                       1_000_000, payload))
        wait_until(lambda: count("checkpoint_chunks_dropped") >= dropped + 16 * (batch + 1), 60,
                   f"flood batch {batch} to be dropped")
    grown = _rss_anon_mb(run.policy.p.pid) - rss0
    assert grown < 96, f"{grown:.0f} MB more after 192 MB of unannounced chunks"
    assert run.diag()["checkpoint_buffered_bytes"] == "0"
    return flood


def _a_restarted_policy_keeps_its_sequence_number(signed: _Signed, spawn, seq2: int, v3: bytes,
                                                  cheetah: bytes) -> None:
    """Restarted, the policy knows the sequence number it served (served.pt.sig): the learner's
    own old announcement replayed is a rollback still. Its file is checked the same way."""
    from protocad_ros.atomic import atomic_open

    run, probe, count = signed.run, signed.run.probe, signed.run.counter
    served, stranger, learner = run.served, signed.stranger, signed.learner
    with probe.lock:
        probe.diag.clear()   # what the first policy said last
    again = spawn("policy_again", *_keyed_policy_args(served, signed.learner_pub, "reload_poll_s:=0.1"),
                  cwd=run.robot)
    wait_until(lambda: run.diag().get("lifecycle_state") == "active", START,
               "the restarted policy to be active")
    assert run.diag()["checkpoint_seq"] == str(seq2)
    fake = FakeCheckpointPublisher(probe)
    fake.announce_only(signed.v1_announcement)
    wait_until(lambda: count("checkpoint_rollbacks_rejected") == 1, 30, "the replayed version 1 refused")
    _write_signed(served, v3, stranger, next_seq())                     # another key's FILE.sig
    wait_until(lambda: count("checkpoint_signatures_rejected") == 1, 30, "a file signed by a stranger")
    _write_signed(served, cheetah, learner, next_seq())                 # another task
    wait_until(lambda: count("checkpoint_mismatches") == 1, 30, "a file of another task")
    _write_signed(served, signed.v1, learner, seq2 - 1)                 # an older one
    wait_until(lambda: count("checkpoint_rollbacks_rejected") == 2, 30, "an older file")
    _write_signed(served, v3, learner, next_seq())                      # the learner's: served
    wait_until(lambda: run.diag().get("pending_checkpoint_updates") == "9", 30,
               "a newer file signed by the learner")
    (run.robot / "served.pt.sig").unlink()
    with atomic_open(served, "wb") as out:                              # unsigned: refused after the grace
        out.write(signed.v1)
    wait_until(lambda: count("checkpoint_signatures_rejected") == 2, 30, "an unsigned file")
    assert count("checkpoint_load_errors") == 4
    assert again.stop() == 0 and run.publisher.stop() == 0
    assert "Traceback" not in again.output() + run.publisher.output()


@pytest.mark.ros
@pytest.mark.process
def test_with_trusted_keys_only_the_learners_newer_versions_are_served(spawn, probe, tmp_path, keys):
    """The learner signs, the robot trusts its public key. Strangers on the domain (this test
    process) send a bad chunk into a genuine transfer, versions signed by another key, unsigned,
    rolled back, too large, of another architecture or task: each is refused and counted, the
    genuine versions still arrive, memory stays flat under a flood of chunks, and the sequence
    number survives a restart (FILE.sig), which also guards the file-reload path."""
    signed = _signed_version_1_is_served(spawn, probe, tmp_path, keys)
    run = signed.run
    v2, seq2, stranger_pub = _strangers_chunks_do_not_stop_version_2(signed, tmp_path)
    v3, cheetah, fake = _refused_versions_are_counted_by_kind(signed, tmp_path, v2)
    flood = _a_flood_of_unannounced_chunks_leaves_memory_flat(run)

    # Through all of that the policy kept serving version 2.
    run.feeder.obs(30, 0, episode=2, is_first=True)
    run.feeder.wait_answers(3, "episode 2")
    wait_until(lambda: run.counter("episodes") == 3, 10, "diagnostics after episode 2 began")
    d = run.diag()
    assert (d["checkpoint_updates"], d["pending_checkpoint_updates"]) == ("7", "-1")
    assert d["checkpoint_sha256"] == hashlib.sha256(v2).hexdigest() and run.served.read_bytes() == v2
    assert d["checkpoint_transfers"] == "2"
    assert run.policy.stop() == 0 and "Traceback" not in run.policy.output()
    fake.close()
    for pub in (flood, stranger_pub):
        probe.node.destroy_publisher(pub)

    _a_restarted_policy_keeps_its_sequence_number(signed, spawn, seq2, v3, cheetah)


@pytest.mark.ros
@pytest.mark.process
def test_start_without_a_file_to_work_with_is_a_configuration_error(spawn):
    publisher = spawn("publisher", "-m", "trainer.nodes.checkpoint_publisher")
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
    from helpers import ROOT

    from trainer.nodes.checkpoint_publisher import COUNTERS, PARAMS

    doc = (ROOT / "msgs_docs" / "checkpoint_publisher.md").read_text()
    missing = [n for n in [p.name for p in PARAMS] + list(COUNTERS) if f"`{n}`" not in doc]
    assert not missing, f"msgs_docs/checkpoint_publisher.md does not document {missing}"


@pytest.fixture(scope="module")
def receiving_policy(tmp_path_factory):
    """An in-process policy node with checkpoint_topic, for driving its receiver's callbacks."""
    import rclpy
    from rclpy.parameter import Parameter

    from protocad_ros.node.policy_node import PolicyNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    path = tmp_path_factory.mktemp("robot") / "agent.pt"
    node = PolicyNode(namespace="/fuzz_ckpt", context=ctx, parameter_overrides=[
        Parameter("task", value=TASK), Parameter("num_threads", value=1),
        Parameter("checkpoint", value=str(path)), Parameter("checkpoint_topic", value="checkpoint"),
        Parameter("allow_unsigned", value=True)])
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


@pytest.mark.ros
@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(text=announcements, label=st.text(max_size=80), data=st.binary(max_size=64))
def test_no_announcement_or_chunk_breaks_the_receiver(receiving_policy, text, label, data):
    from std_msgs.msg import MultiArrayDimension

    receiver = receiving_policy.checkpoint_serving.receiver
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


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    """Two key pairs: `learner` (trusted by the nodes under test) and `stranger`."""
    d = tmp_path_factory.mktemp("keys")
    out = {}
    for name in ("learner", "stranger"):
        generate_keypair(d / f"{name}.key", d / f"{name}.pub")
        out[name] = (d / f"{name}.key", d / f"{name}.pub", load_private_key(d / f"{name}.key"))
    return out


@pytest.fixture
def bare_receiver():
    """In process, callbacks driven directly: make(**kw) -> (receiver, woken, counted)."""
    import rclpy
    from rclpy.node import Node

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node("receiver_probe", namespace="/receiver_test", context=ctx)
    made = []

    def make(**kw):
        woken, counted = [], []
        r = CheckpointReceiver(node, "checkpoint", ReceiverSettings(
            timeout_s=60.0, wake=lambda: woken.append(1), next_sha=kw.pop("next_sha", lambda: None),
            serving=lambda: "nothing", count=lambda key, why=None: counted.append(key), **kw))
        made.append(r)
        return r, woken, counted

    yield make
    for r in made:
        r.destroy()
    node.destroy_node()
    rclpy.shutdown(context=ctx)


def _chunk(a, i, data, n=None):
    return topics.fill_checkpoint_chunk(UInt8MultiArray(), a.sha256, i, n or a.n_chunks, data)


def _announce(r, a):
    r._on_announcement(String(data=topics.checkpoint_announcement_json(a)))


@pytest.mark.ros
def test_receiver_buffers_only_announced_versions_and_drops_bad_chunks_alone(bare_receiver):
    """Chunks that beat their announcement are dropped unbuffered (the chunk subscription is
    then made anew, so the publisher's history brings them again); a chunk with a wrong hash,
    length, index or chunk count is dropped alone and a good copy still completes the version;
    the newest announcement wins over a version still coming in."""
    r, woken, counted = bare_receiver()
    size = topics.MIN_CHUNK_SIZE
    one, two = os.urandom(2 * size + 100), os.urandom(size + 1)
    a1, a2 = topics.describe_checkpoint(one, size), topics.describe_checkpoint(two, size)
    p1 = _chunks(one, size)
    for i, piece in enumerate(p1):
        r._on_chunk(_chunk(a1, i, piece))
    assert woken == [] and r.buffered_bytes() == 0 and counted.count(r.DROPPED) == 3
    sub = r.sub_chunks
    _announce(r, a1)
    assert r.sub_chunks is not sub                           # history read again
    bad = bytearray(p1[0])
    bad[7] ^= 1
    r._on_chunk(_chunk(a1, 0, bytes(bad)))                   # a stranger's chunk 0: wrong hash
    r._on_chunk(_chunk(a1, 1, p1[1][:-1]))                   # wrong length
    r._on_chunk(_chunk(a1, 2, p1[2], n=4))                   # claims another chunk count
    assert r._parts == {} and counted.count(r.DROPPED) == 6
    for i, piece in enumerate(p1):                           # the publisher's history
        r._on_chunk(_chunk(a1, i, piece))
    assert woken == [1] and r._received.verify() == one and r.buffered_bytes() == len(one)
    r._on_chunk(_chunk(a1, 0, p1[0]))                        # late duplicate: not buffered
    assert counted.count(r.DROPPED) == 7
    r._received = None

    _announce(r, a2)
    r._on_chunk(_chunk(a2, 0, two[:size]))
    assert r.buffered_bytes() == size
    _announce(r, a1)                                         # newer: a2 is dropped
    assert r.buffered_bytes() == 0
    r._on_chunk(_chunk(a2, 1, two[size:]))
    assert woken == [1]
    assert counted.count(r.REJECTED) == 0


@pytest.mark.ros
def test_receiver_with_trusted_keys_refuses_before_buffering(bare_receiver, keys):
    learner, stranger = keys["learner"][2], keys["stranger"][2]
    from protocad_ros.checkpoint.signing import load_trusted_keys

    trusted = load_trusted_keys([keys["learner"][1]])
    held = {"seq": 100}
    r, woken, counted = bare_receiver(trusted=trusted, newest_seq=lambda: held["seq"],
                                      max_bytes=1 << 20)
    size = topics.MIN_CHUNK_SIZE
    data = os.urandom(3 * size)
    ann = topics.describe_checkpoint(data, size, task=TASK, variant="protocad")
    refused = [
        (ann, r.SIGNATURE),                                          # unsigned
        (_sign(ann, stranger, 200), r.SIGNATURE),                    # a key not trusted here
        (dataclasses.replace(_sign(ann, learner, 200), updates=5), r.SIGNATURE),   # altered
        (dataclasses.replace(_sign(ann, learner, 200), signature="AAAA"), r.SIGNATURE),
        (_sign(dataclasses.replace(ann, chunk_sha256=()), learner, 200), r.SIGNATURE),
        (_sign(ann, learner, 100), r.ROLLBACK),                      # not above the held one
        (_sign(topics.describe_checkpoint(b"x" * (2 << 20), 1 << 20), learner, 200), r.LIMITS),
        (_sign(topics.describe_checkpoint(data, 1024), learner, 200), r.LIMITS),
    ]
    for a, counter in refused:
        _announce(r, a)
        for i, piece in enumerate(_chunks(data, size)):
            r._on_chunk(_chunk(a, i, piece))
        assert (counted[-len(_chunks(data, size)) - 2:-len(_chunks(data, size))]
                == [r.REJECTED, counter]), a
        assert r.announced is None and r.buffered_bytes() == 0 and woken == []
    good = _sign(ann, learner, 200)
    _announce(r, good)
    r._on_chunk(_chunk(good, 0, data[:size]))
    _announce(r, _sign(ann, stranger, 300))                  # refused: does not stop it
    _announce(r, _sign(ann, learner, 150))                   # an older signature of it: heard again
    assert r.announced == good
    for i, piece in enumerate(_chunks(data, size)):
        r._on_chunk(_chunk(good, i, piece))
    assert woken == [1] and r._received.verify() == data
