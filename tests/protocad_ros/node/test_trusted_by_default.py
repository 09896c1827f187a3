"""Trusted by default (msgs_docs/security.md, issue 39): a policy node that receives checkpoints
over ROS needs keys (or says allow_unsigned), keeps its rollback floor apart from FILE.sig, loads
the very bytes it verified, checks its random agent's variant and architecture, and rate-limits
its refusal lines. Real policy processes over DDS (this machine, the run's domain); the
strangers are this test process (helpers.checkpoints.FakeCheckpointPublisher)."""
from __future__ import annotations

import hashlib
import io
import math
import os
import time
from pathlib import Path

import pytest
from helpers import wait_until
from helpers.agents import save_agent
from helpers.checkpoints import FakeCheckpointPublisher, chunks, sign
from helpers.policy import START, TASK, policy_args
from helpers.ros import Probe

from protocad_ros.checkpoint.signing import (
    generate_keypair,
    load_private_key,
    load_trusted_keys,
    sign_file,
    signature_path,
)
from protocad_ros.node.refusal_log import DEFAULT_INTERVAL_S
from sim_bridge.contract import topics

SIZE = topics.DEFAULT_CHUNK_SIZE


@pytest.fixture
def probe():
    p = Probe("trusted_default_probe")
    yield p
    p.close()


def _keys(d: Path):
    d.mkdir(parents=True, exist_ok=True)
    for name in ("learner", "stranger"):
        generate_keypair(d / f"{name}.key", d / f"{name}.pub")
    return load_private_key(d / "learner.key"), load_private_key(d / "stranger.key"), d / "learner.pub"


def _version(tmp_path, name: str, updates: int, seed: int, **kw) -> tuple[bytes, topics.CheckpointAnnouncement]:
    path = tmp_path / name / "agent.pt"
    save_agent(path, updates, seed=seed)
    data = path.read_bytes()
    return data, topics.describe_checkpoint(data, SIZE, updates=updates, task=TASK, variant="protocad",
                                            preset="small", **kw)


@pytest.mark.ros
@pytest.mark.process
def test_a_checkpoint_topic_without_keys_does_not_start_unless_allow_unsigned(spawn, probe, tmp_path):
    served = tmp_path / "robot" / "agent.pt"
    refused = spawn("refused", *policy_args(f"checkpoint:={served}", "checkpoint_topic:=checkpoint"))
    wait_until(lambda: not refused.alive(), START, "the keyless policy to exit")
    errors = [ln for ln in refused.output().splitlines() if "configuration error:" in ln]
    assert refused.p.returncode == 2 and len(errors) == 1, refused.output()
    assert "without trusted_keys" in errors[0]
    assert "trusted_keys:=" in errors[0] and "allow_unsigned:=true" in errors[0]   # names the fix
    allowed = spawn("allowed", *policy_args(f"checkpoint:={served}", "checkpoint_topic:=checkpoint",
                                            "allow_unsigned:=true"))
    wait_until(lambda: probe.node_diag("policy").get("lifecycle_state") == "active", START,
               "the policy with allow_unsigned to serve")
    d = probe.node_diag("policy")
    assert d["unsigned_checkpoints_allowed"].lower() == "true" and d["_level"] == 1, d   # WARN, shown
    assert "UNSIGNED" in d["_message"] or d["_message"] == "random agent", d
    assert "accepts UNSIGNED checkpoints over checkpoint (allow_unsigned:=true)" in allowed.output()
    assert allowed.stop() == 0


def _keyed(served: Path, pub: Path, *extra: str) -> list[str]:
    return policy_args(f"checkpoint:={served}", "checkpoint_topic:=checkpoint", f"trusted_keys:={pub}",
                       "checkpoint_transfer_timeout_s:=5.0", *extra)


@pytest.mark.ros
@pytest.mark.process
def test_a_replayed_older_version_is_refused_live_after_a_restart_and_after_its_sig_is_lost(
        spawn, probe, tmp_path):
    learner, stranger, pub = _keys(tmp_path / "keys")
    served = tmp_path / "robot" / "agent.pt"
    served.parent.mkdir()
    v1, a1 = _version(tmp_path, "v1", 5, 1)
    v2, a2 = _version(tmp_path, "v2", 7, 2)
    s1 = sign(a1, learner)
    s2 = sign(a2, learner, s1.seq + 1)   # (two signatures may fall in one millisecond)
    fake = FakeCheckpointPublisher(probe)

    def start(name: str):
        with probe.lock:
            probe.diag.clear()
        proc = spawn(name, *_keyed(served, pub))
        wait_until(lambda: probe.node_diag("policy").get("lifecycle_state") == "active" or not proc.alive(),
                   START, f"{name} to be active")
        assert proc.alive(), proc.output()
        return proc

    def count(key: str) -> float:
        return probe.counter("policy", key)

    def replay_refused(proc, what: str) -> None:
        fake.send(s1, chunks(v1, SIZE))   # (a restarted node may also hear it from the history)
        wait_until(lambda: count("checkpoint_rollbacks_rejected") >= 1, 30, f"the replayed v1 refused {what}")
        assert "rollback: sequence number" in proc.output()

    p1 = start("live")
    fake.send(s1, chunks(v1, SIZE))
    wait_until(lambda: probe.node_diag("policy").get("pending_checkpoint_updates") == "5", 60, "v1 installed")
    fake.send(s2, chunks(v2, SIZE))
    wait_until(lambda: probe.node_diag("policy").get("pending_checkpoint_updates") == "7", 60, "v2 installed")
    assert served.read_bytes() == v2
    # Strangers: an unsigned version and one signed by another key, refused and counted.
    v3, a3 = _version(tmp_path, "v3", 9, 3)
    # One after the other: the announcement topic keeps the newest only (depth 1), so a second
    # sent at once can replace the first before the node has taken it.
    fake.send(a3, chunks(v3, SIZE))
    wait_until(lambda: count("checkpoint_signatures_rejected") == 1, 30, "the unsigned version refused")
    fake.send(sign(a3, stranger), chunks(v3, SIZE))
    wait_until(lambda: count("checkpoint_signatures_rejected") == 2, 30, "the stranger's version refused")
    replay_refused(p1, "live")
    floor = probe.node_diag("policy")["checkpoint_rollback_floor"]
    assert floor == str(s2.seq), floor
    assert p1.stop() == 0

    p2 = start("restarted")
    assert probe.node_diag("policy")["checkpoint_seq"] == str(s2.seq)
    replay_refused(p2, "after a restart")
    assert p2.stop() == 0

    # Whoever can write the checkpoint directory deletes FILE.sig and FILE: the floor is kept
    # beside the trusted key, so the captured v1 is still a rollback.
    signature_path(served).unlink()
    served.unlink()
    p3 = start("without_its_sig")
    assert probe.node_diag("policy")["checkpoint_rollback_floor"] == str(s2.seq)
    replay_refused(p3, "after FILE.sig was deleted")
    assert not served.exists()
    assert p3.stop() == 0

    # v1 put back as the served file with its own (older) signature: refused at start, saying
    # which state file holds the floor and how to accept it.
    served.write_bytes(v1)
    sign_file(served, learner, s1.seq)
    old = spawn("older_file", *_keyed(served, pub))
    wait_until(lambda: not old.alive(), START, "the node with an older served file to exit")
    assert old.p.returncode == 2 and f"below {s2.seq}" in old.output() and "delete the state file" in old.output()
    fake.close()


@pytest.mark.ros
@pytest.mark.process
def test_a_new_robot_with_a_minimum_seq_refuses_a_replayed_older_version_from_the_first_message(
        spawn, probe, tmp_path):
    """Issue 54, point 5: the publisher is down, a stranger replays a captured older signed
    version to a brand-new robot (no file, no rollback state). Without a floor the robot
    installs it; with min_checkpoint_seq (the publisher's current number) it is refused from the
    first message, and the publisher's next version is still taken."""
    learner, _, pub = _keys(tmp_path / "keys")
    v1, a1 = _version(tmp_path, "v1", 5, 1)
    old = sign(a1, learner)                         # captured earlier
    current = old.seq + 60_000                      # the publisher's number a minute later
    fake = FakeCheckpointPublisher(probe)

    def new_robot(name: str, *extra: str):
        with probe.lock:
            probe.diag.clear()
        served = tmp_path / name / "agent.pt"
        served.parent.mkdir()
        proc = spawn(name, *_keyed(served, pub, f"rollback_state:={tmp_path / name / 'floor.json'}", *extra))
        wait_until(lambda: probe.node_diag("policy").get("lifecycle_state") == "active" or not proc.alive(),
                   START, f"{name} to be active")
        assert proc.alive(), proc.output()
        assert probe.node_diag("policy")["checkpoint_rollback_floor"] == "-1"   # brand-new: no floor kept
        return proc, served

    # Before: a new robot without a minimum installs the replayed version.
    p0, served0 = new_robot("no_floor")
    fake.send(old, chunks(v1, SIZE))
    wait_until(lambda: probe.node_diag("policy").get("pending_checkpoint_updates") == "5", 60,
               "the replayed v1 installed by a robot without a floor")
    assert served0.read_bytes() == v1
    assert p0.stop() == 0

    # After: with min_checkpoint_seq the same replay is refused from the first message.
    p1, served1 = new_robot("with_floor", f"min_checkpoint_seq:={current}")
    assert f"no version signed below min_checkpoint_seq {current}" in p1.output()
    fake.send(old, chunks(v1, SIZE))
    wait_until(lambda: probe.counter("policy", "checkpoint_rollbacks_rejected") >= 1, 30, "the replay refused")
    assert f"rollback: sequence number {old.seq} is not above {current - 1}" in p1.output()
    d = probe.node_diag("policy")
    assert d["agent"] == "random" and d["pending_checkpoint_updates"] == "-1" and not served1.exists(), d
    v2, a2 = _version(tmp_path, "v2", 7, 2)         # the publisher is back: its next version is taken
    fake.send(sign(a2, learner, current), chunks(v2, SIZE))
    wait_until(lambda: probe.node_diag("policy").get("pending_checkpoint_updates") == "7", 60, "v2 installed")
    assert served1.read_bytes() == v2
    assert p1.stop() == 0
    fake.close()


@pytest.mark.ros
@pytest.mark.process
def test_min_checkpoint_seq_without_trusted_keys_is_a_configuration_error(spawn, tmp_path):
    proc = spawn("min_seq_unsigned", *policy_args(f"checkpoint:={tmp_path / 'agent.pt'}", "min_checkpoint_seq:=5"))
    wait_until(lambda: not proc.alive(), START, "the node to exit")
    assert proc.p.returncode == 2 and "min_checkpoint_seq:=5 without trusted_keys" in proc.output(), proc.output()


@pytest.mark.ros
@pytest.mark.process
def test_a_flood_of_refused_announcements_is_counted_and_logged_once_per_cause(spawn, probe, tmp_path):
    learner, stranger, pub = _keys(tmp_path / "keys")
    served = tmp_path / "robot" / "agent.pt"
    served.parent.mkdir()
    policy = spawn("policy", *_keyed(served, pub))
    wait_until(lambda: probe.node_diag("policy").get("lifecycle_state") == "active", START, "the policy")
    fake = FakeCheckpointPublisher(probe)
    n = 200
    t0 = time.monotonic()
    for i in range(n):   # fresh version ids, unsigned and signed by a stranger
        a = topics.describe_checkpoint(os.urandom(64) + bytes([i]), SIZE, task=TASK)
        fake.announce_only(a if i % 2 else sign(a, stranger))
        # paced: the announcement topic keeps the newest only, and every one is to be heard
        wait_until(lambda i=i: probe.counter("policy", "checkpoint_signatures_rejected") == i + 1, 30,
                   f"refusal {i + 1} counted")
    # the refusals' own lines (a held-back summary, said when an interval ends during a slow
    # run, names its cause too: it is counted below, not here)
    intervals = math.ceil((time.monotonic() - t0) / DEFAULT_INTERVAL_S)   # 1 when quiet, more on a loaded machine
    lines = [ln for ln in policy.output().splitlines() if "rejected:" in ln and "more refusal(s)" not in ln]
    assert 2 <= len(lines) <= 2 * (intervals + 1), lines   # one per cause (unsigned, another key) per interval
    assert policy.stop() == 0   # closing says what was held back, with the count
    held = [ln for ln in policy.output().splitlines() if "more refusal(s) of this kind" in ln]
    assert held and sum(int(ln.split(" more refusal")[0].rsplit(" ", 1)[-1]) for ln in held) == n - len(lines)
    fake.close()


# ---------------------------------------------------------------------- in process
@pytest.fixture
def keyed_node(tmp_path):
    """make(checkpoint, **params): an in-process policy node with trusted keys (the learner's)."""
    import rclpy
    from rclpy.parameter import Parameter

    from protocad_ros.node.policy_node import PolicyNode

    learner, stranger, pub = _keys(tmp_path / "keys")
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    made = []

    def make(checkpoint: Path, **params):
        node = PolicyNode(namespace=f"/trusted_{len(made)}", context=ctx, parameter_overrides=[
            Parameter("task", value=TASK), Parameter("num_threads", value=1),
            Parameter("checkpoint", value=str(checkpoint)), Parameter("trusted_keys", value=str(pub)),
            *[Parameter(k, value=v) for k, v in params.items()]])
        made.append(node)
        return node

    yield make, learner, stranger
    for node in made:
        node.close()
        node.destroy_node()
    rclpy.shutdown(context=ctx)


@pytest.mark.ros
def test_a_file_swapped_between_verification_and_load_is_never_served(keyed_node, tmp_path, monkeypatch):
    """The attack: exchange the checkpoint for a stranger's between the read that is hashed and
    verified and the read that is loaded, then exchange it back (the file's (mtime, inode, size)
    are the verified one's again). A hook on every open of the checkpoint (open, and os.open: the
    bounded read opens a descriptor) makes exactly that exchange around any read after the first; the node reads the file once, so it serves the
    signed version and the stranger's bytes are never loaded."""
    import builtins

    make, learner, _ = keyed_node
    path = tmp_path / "robot" / "agent.pt"
    save_agent(path, 5, seed=1)
    sign_file(path, learner)
    node = make(path, reload_poll_s=0.0)
    assert node.checkpoint_serving.checkpoint_updates == 5
    save_agent(path, 7, seed=2)
    sign_file(path, learner)
    signed_v2 = path.read_bytes()
    evil = tmp_path / "evil.pt"
    save_agent(evil, 666, seed=3)    # unsigned: a stranger's
    reads, real_open = [], builtins.open

    def hooked_open(file, mode="r", *args, **kw):
        if not isinstance(file, (str, os.PathLike)) or os.fspath(file) != str(path) or "r" not in mode:
            return real_open(file, mode, *args, **kw)
        reads.append(1)
        if len(reads) == 1:
            return real_open(file, mode, *args, **kw)
        os.rename(path, tmp_path / "genuine.pt")       # exchange ...
        os.rename(evil, path)
        try:
            data = real_open(file, "rb").read()
        finally:
            os.rename(path, evil)                      # ... and back
            os.rename(tmp_path / "genuine.pt", path)
        return io.BytesIO(data) if "b" in mode else io.StringIO(data.decode(errors="replace"))

    real_os_open = os.open

    def hooked_os_open(file, flags, *args, **kw):   # the checkpoint reader opens a descriptor
        if isinstance(file, int) or os.fspath(file) != str(path):
            return real_os_open(file, flags, *args, **kw)
        reads.append(1)
        if len(reads) == 1:
            return real_os_open(file, flags, *args, **kw)
        os.rename(path, tmp_path / "genuine.pt")       # exchange: the descriptor is the stranger's ...
        os.rename(evil, path)
        try:
            return real_os_open(file, flags, *args, **kw)
        finally:
            os.rename(path, evil)                      # ... and back
            os.rename(tmp_path / "genuine.pt", path)

    monkeypatch.setattr(builtins, "open", hooked_open)
    monkeypatch.setattr(io, "open", hooked_open)
    monkeypatch.setattr(os, "open", hooked_os_open)
    node.checkpoint_serving._check_file(str(path))
    monkeypatch.undo()
    pending = node.checkpoint_serving._pending_policy
    assert pending is not None, node.counters
    assert pending[1]["updates"] == 7 and pending[3] == hashlib.sha256(signed_v2).hexdigest()
    assert len(reads) == 1, f"the checkpoint was read {len(reads)} times"


@pytest.mark.ros
def test_the_random_agent_refuses_another_variant_or_architecture(keyed_node, tmp_path):
    """While a node still serves its random agent (no file yet), a signed checkpoint of another
    variant, or of its variant with other layer sizes, is refused before it is installed."""
    from protocad_ros.checkpoint.files import CheckpointMismatch

    make, learner, _ = keyed_node
    node = make(tmp_path / "robot" / "agent.pt", checkpoint_topic="checkpoint")
    assert node.checkpoint_serving.agent_kind == "random"
    dreamer = _with_config(_saved(tmp_path / "d.pt"), "variant", None, "dreamer")
    wider = _with_config(_saved(tmp_path / "w.pt"), "world_model", "mlp_units", 7)
    for data, says in ((dreamer, "variant"), (wider, "world_model.mlp_units")):
        with pytest.raises(CheckpointMismatch, match=says):
            node.checkpoint_serving._load_checked("the received file", data)
    ann = topics.describe_checkpoint(dreamer, SIZE, task=TASK, variant="dreamer")
    assert "dreamer agent, this node serves protocad" in node.checkpoint_serving._announced_fits(ann)
    assert not (tmp_path / "robot" / "agent.pt").exists()   # nothing installed


def _saved(path: Path) -> bytes:
    save_agent(path, 3)
    return path.read_bytes()


def _with_config(data: bytes, section: str, key: str | None, value) -> bytes:
    import torch

    payload = torch.load(io.BytesIO(data), weights_only=True)
    if key is None:
        payload["config"][section] = value
    else:
        payload["config"][section][key] = value
    buf = io.BytesIO()
    torch.save(payload, buf)
    return buf.getvalue()


def test_unknown_fields_in_a_sig_are_refused(tmp_path):
    import json

    from protocad_ros.checkpoint.signing import SignatureRejected, verify_file

    key = tmp_path / "k"
    generate_keypair(key.with_suffix(".key"), key.with_suffix(".pub"))
    trusted = load_trusted_keys([key.with_suffix(".pub")])
    path = tmp_path / "agent.pt"
    save_agent(path, 3)
    sign_file(path, load_private_key(key.with_suffix(".key")))
    data = path.read_bytes()
    sha, good = hashlib.sha256(data).hexdigest(), json.loads(signature_path(path).read_text())
    assert verify_file(path, sha, len(data), trusted).updates == 3
    for extra in ({"payload_url": "http://x"}, {"manifest": {**good["manifest"], "note": "hi"}}):
        signature_path(path).write_text(json.dumps({**good, **extra}))
        with pytest.raises(SignatureRejected, match="does not know"):
            verify_file(path, sha, len(data), trusted)


def test_a_received_version_is_loaded_from_the_verified_bytes(tmp_path):
    from protocad_ros.node.checkpoint_receiver import RECEIVED, install

    got = []
    out = install(b"verified", tmp_path / "agent.pt", lambda name, data: got.append((name, data)) or "ok")
    assert out == "ok" and got == [(RECEIVED, b"verified")] and (tmp_path / "agent.pt").read_bytes() == b"verified"


def test_refusal_lines_are_one_per_cause_per_interval_with_a_count():
    from protocad_ros.node.refusal_log import RefusalLog

    lines, now = [], [0.0]
    log = RefusalLog(lines.append, interval_s=10.0, clock=lambda: now[0])
    for i in range(500):
        log.refuse("unsigned", f"version {i} unsigned")
        log.refuse("rollback", f"version {i} rollback")
    assert lines == ["version 0 unsigned", "version 0 rollback"]
    log.flush()
    assert len(lines) == 2   # the interval is not over
    now[0] = 10.5
    log.flush()
    assert lines[2:] == ["499 more refusal(s) of this kind (unsigned) in the last 10 s, the last: version 499 unsigned",
                         "499 more refusal(s) of this kind (rollback) in the last 10 s, the last: version 499 rollback"]
    log.refuse("unsigned", "again")
    assert lines[-1] != "again"   # the flush line opened a new interval
    log.flush(force=True)
    assert lines[-1].startswith("1 more refusal(s)")


def test_the_rollback_floor_is_kept_apart_and_only_grows(tmp_path):
    from protocad_ros.node.rollback_floor import RollbackFloor, RollbackStateError, default_state_path

    state = default_state_path(tmp_path / "keys" / "learner.pub", tmp_path / "robot" / "agent.pt")
    assert state.parent == tmp_path / "keys" and state.name.startswith("learner.pub.served-")
    assert state != default_state_path(tmp_path / "keys" / "learner.pub", tmp_path / "robot2" / "agent.pt")
    floor = RollbackFloor(state, tmp_path / "robot" / "agent.pt")
    assert floor.seq == -1 and not state.exists()
    floor.raise_to(10)
    floor.raise_to(5)
    assert RollbackFloor(state, "x").seq == 10
    floor.check_served(10, "it")
    with pytest.raises(RollbackStateError, match="below 10"):
        floor.check_served(9, "it")
    state.write_text("junk")
    with pytest.raises(RollbackStateError, match="delete it"):
        RollbackFloor(state, "x")
