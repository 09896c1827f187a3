"""The policy node as a real process, fed over DDS from this (separate) test process.

Observations are hand-made here (no sim bridge), so the test controls stamps, order, duplicates
and malformed input: wrong image size / encoding / truncated data, broken step_info. The node
must stay up, count each kind on /diagnostics, answer every valid observation with exactly one
action stamped like it, and swap in a newer checkpoint only at an episode boundary.
"""
from __future__ import annotations

import os

import numpy as np
import pytest
from helpers import ROOT, wait_exit, wait_until
from helpers.agents import save_agent
from helpers.policy import START, TASK, Feeder, policy_args
from helpers.ros import Probe
from sensor_msgs.msg import Image, JointState

from sim_bridge.contract import qos, topics
from sim_bridge.contract.contexts import TASKS


@pytest.fixture
def probe():
    p = Probe("policy_test_probe")
    yield p
    p.close()


@pytest.mark.ros
@pytest.mark.process
def test_malformed_images_and_stamp_matching(spawn, probe):
    f = Feeder(probe)
    policy = spawn("policy", *policy_args())
    wait_until(f.ready, START, "the policy's subscriptions and publishers to match")
    node = "policy"
    wait_until(lambda: probe.node_diag(node).get("agent") == "random", 30, "diagnostics")

    f.obs(1_000, 0, is_first=True)                       # image, then step_info
    f.wait_answers(1, "the answer to the first observation")
    f.obs(2_000, 1, info_first=True)                     # step_info, then image
    f.wait_answers(2, "the answer to the second observation")

    # Malformed input (each with a valid partner, so only the bad half blocks the pair).
    # (bgr8, mono8 and other sizes are taken: tests/protocad_ros/robot/test_camera_input.py)
    f.raw_image(3_000, 5_000, 5_000, "rgb8", bytes(300))   # claims 25 M pixels
    f.info(3_000, 2)
    f.raw_image(4_000, 64, 64, "yuv422", bytes(64 * 64 * 2), step=128)
    f.raw_image(4_500, 64, 64, "bayer_rggb8", bytes(64 * 64), step=64)
    f.info(4_000, 2)
    f.raw_image(5_000, 64, 64, "rgb8", bytes(100))    # truncated
    f.info(5_000, 2)
    f.image(6_000)
    bad = JointState()
    topics.fill_named(bad, ["reward", "discount"], [1.0, 1.0], 6_000)   # lacks the flags/ids
    f.pub_info.publish(bad)
    wait_until(lambda: probe.counter(node, "images_rejected") == 4
               and probe.counter(node, "step_info_rejected") == 1, 20, "rejection counters")
    d = probe.node_diag(node)
    assert (d["rejected_image_size"], d["rejected_image_encoding"], d["rejected_image_data"]) == (
        "1", "2", "1"), d

    f.obs(2_000, 1)                                      # the bridge's timeout republish
    f.wait_answers(3, "the repeated answer")
    f.obs(1_500, 1)                                      # older than the last answered
    wait_until(lambda: probe.counter(node, "stale_observations") == 1, 20, "stale counter")
    f.obs(7_000, 2)
    f.obs(8_000, 3, is_last=True)
    f.wait_answers(5, "answers after the bad input")
    assert policy.alive()

    assert f.stamps() == [1_000, 2_000, 2_000, 7_000, 8_000]
    acts = [np.asarray(m.effort) for m in list(f.actions)]
    assert all(list(m.name) == ["torque"] for m in list(f.actions))
    assert all(a.shape == (1,) and np.all(np.abs(a) <= 1.0) for a in acts)
    assert np.array_equal(acts[1], acts[2])               # same answer, not filtered twice
    feats = [topics.read_context_features(m) for m in list(f.features)]
    assert [topics.stamp_to_ns(m.header.stamp) for m in list(f.features)] == f.stamps()
    K = TASKS[TASK].num_prototypes
    for x in feats:
        assert x["w"].shape == (K,) and x["u"].size > 0 and x["e"].shape == x["u"].shape
        assert x["w"].sum() == pytest.approx(1.0, abs=1e-4)
    wait_until(lambda: probe.counter(node, "observations_answered") == 4, 10, "answered count")
    d = probe.node_diag(node)
    assert d["duplicate_observations"] == "1" and d["checkpoint_updates"] == "-1"
    p50, p99 = float(d["latency_ms_p50"]), float(d["latency_ms_p99"])
    assert 0 < p50 <= p99

    # A new bridge run: sim time restarts at 0 with an episode start. That is answered (a new
    # episode), while an older observation that is not an episode start stays stale.
    f.image(500)                                          # a lone piece of the "old" run
    f.obs(0, 0, episode=0, is_first=True)
    f.wait_answers(6, "the first observation of a new sim run")
    f.obs(20, 1, episode=0)
    f.wait_answers(7, "the new run's second step")
    f.obs(10, 1, episode=0)                               # older, not an episode start
    wait_until(lambda: probe.counter(node, "stale_observations") == 2, 20, "second stale")
    assert f.stamps()[-2:] == [0, 20]
    assert probe.counter(node, "sim_time_restarts") == 1
    assert policy.stop() == 0
    out = policy.log_path.read_text()
    assert "RANDOMLY INITIALISED" in out and "Traceback" not in out


@pytest.mark.ros
@pytest.mark.process
def test_checkpoint_reload_between_episodes(spawn, probe, tmp_path):
    from protocad_ros.policy import Policy

    ckpt = tmp_path / "run" / "checkpoints" / "latest.pt"
    ckpt.parent.mkdir(parents=True)
    save_agent(ckpt, 5, seed=1)
    missing = spawn("missing", *policy_args(f"checkpoint:={tmp_path / 'nope.pt'}"))
    f = Feeder(probe)
    # named by its run directory, as protocad-evaluate and protocad-visualize take it
    policy = spawn("policy", *policy_args(f"checkpoint:={tmp_path / 'run'}", "reload_poll_s:=0.1"))
    assert wait_exit(missing, START) == 2
    assert "does not exist" in missing.log_path.read_text()
    wait_until(f.ready, START, "the policy to match")
    node = "policy"
    wait_until(lambda: probe.node_diag(node).get("checkpoint_updates") == "5", 30, "updates=5")
    assert probe.node_diag(node)["checkpoint/env_steps"] == "500"

    f.obs(10, 0, is_first=True)
    f.obs(20, 1)
    f.wait_answers(2, "episode 0")
    new_agent = save_agent(ckpt, 7, seed=2)                   # the trainer writes a newer one
    wait_until(lambda: probe.node_diag(node).get("pending_checkpoint_updates") == "7", 30,
               "the new checkpoint to be loaded in the background")
    f.obs(30, 2)                                         # same episode: still the old model
    f.wait_answers(3, "episode 0, step 2")
    assert probe.node_diag(node)["checkpoint_updates"] == "5"
    episode1 = [(40, 0, True), (50, 1, False), (60, 2, False)]
    for stamp, step, first in episode1:
        f.obs(stamp, step, episode=1, is_first=first)
    f.wait_answers(6, "episode 1")
    wait_until(lambda: probe.node_diag(node).get("checkpoint_updates") == "7", 10, "updates=7")
    assert probe.counter(node, "checkpoint_reloads") == 1
    assert f.stamps() == [10, 20, 30, 40, 50, 60]        # no step dropped around the swap

    # Episode 1 was served by exactly the new checkpoint (same filter, same actions).
    ref = Policy(new_agent, mode="deterministic")
    ref.reset()
    prev = np.zeros(1, np.float32)
    for (stamp, _, first), msg in zip(episode1, list(f.actions)[3:]):
        a, _ = ref.act(f.images[stamp], prev, first)
        np.testing.assert_allclose(np.asarray(msg.effort), a, atol=1e-5)
        prev = a

    # A corrupt file at the path: logged and counted, the node keeps serving updates=7.
    tmp = tmp_path / "partial"
    tmp.write_bytes(b"not a checkpoint at all")
    os.replace(tmp, ckpt)
    wait_until(lambda: probe.counter(node, "checkpoint_load_errors") == 1, 30, "load error")
    f.obs(70, 3, episode=1)
    f.obs(80, 0, episode=2, is_first=True)
    f.wait_answers(8, "answers after the corrupt checkpoint")
    assert probe.node_diag(node)["checkpoint_updates"] == "7"
    assert policy.alive() and policy.stop() == 0
    out = policy.log_path.read_text()
    assert "cannot load checkpoint" in out and "now serving checkpoint" in out
    assert "Traceback" not in out

    corrupt = spawn("corrupt", *policy_args(f"checkpoint:={ckpt}"))
    assert wait_exit(corrupt, START) == 2
    assert "cannot load checkpoint" in corrupt.log_path.read_text()


def test_docs_cover_every_parameter_and_counter():
    from protocad_ros.node.policy_node import COUNTERS, PARAMS

    doc = (ROOT / "msgs_docs" / "policy.md").read_text()
    missing = [n for n in [p.name for p in PARAMS] + list(COUNTERS) if f"`{n}`" not in doc]
    assert not missing, f"msgs_docs/policy.md does not document {missing}"


@pytest.mark.ros
@pytest.mark.process
def test_live_rerun_stream_saved_by_the_node(spawn, probe, tmp_path):
    from trainer.viz.rerun_log import read_recording

    rrd = tmp_path / "live.rrd"
    f = Feeder(probe)
    policy = spawn("policy", *policy_args("rerun_mode:=save", f"rerun_path:={rrd}"))
    wait_until(f.ready, START, "the policy to match")
    for step, stamp in enumerate((1_000, 2_000, 3_000)):
        f.obs(stamp, step, is_first=step == 0)
    f.wait_answers(3, "answers with the live view on")
    assert policy.stop() == 0
    rec = read_recording(rrd)
    for path in ("/policy/image", "/policy/assignment", "/policy/action", "/policy/reward"):
        assert path in rec, f"{path} missing; have {sorted(rec)}"
    assert sorted(rec["/policy/image"]["columns"]["sim_time"]) == [1_000, 2_000, 3_000]

    bad = spawn("bad", *policy_args("rerun_mode:=save"))    # save mode without a path
    assert wait_exit(bad, START) == 2
    assert "configuration error" in bad.log_path.read_text()


@pytest.mark.ros
@pytest.mark.process
def test_deploys_without_the_simulator_and_names_the_real_actuators(spawn, probe):
    """On a robot there is no mujoco or dm_control: the node still starts, and its actions carry
    the task's real actuator names (from the task table), not a0, a1, ..."""
    from helpers import HELPERS

    f = Feeder(probe)
    env = {"PROTOCAD_BLOCK_IMPORTS": "mujoco,dm_control",
           "PYTHONPATH": os.pathsep.join([str(HELPERS / "import_blocker"), str(ROOT)])}
    args = policy_args()
    args[args.index(f"task:={TASK}")] = "task:=walker_walk"
    policy = spawn("policy", *args, env=env)
    wait_until(f.ready, START, "the policy's subscriptions and publishers to match")
    f.obs(1_000, 0, is_first=True)
    f.wait_answers(1, "an answer")
    assert list(f.actions[0].name) == ["right_hip", "right_knee", "right_ankle", "left_hip", "left_knee",
                                       "left_ankle"]
    assert policy.alive()
    assert "blocked by the test's import blocker" not in policy.output()


@pytest.mark.ros
@pytest.mark.process
def test_realtime_latest_only_skips_to_the_newest_observation(spawn, probe):
    """A real-time bridge at 500 steps/s, faster than this policy answers on 2 shared cores:
    with latest_only the policy never answers an older observation after a newer one, skips to
    the newest, and counts what it skipped."""
    actions = probe.record(topics.ACTION, JointState, qos.action_qos())
    policy = spawn("policy", *policy_args("latest_only:=true"))
    wait_until(lambda: actions.matched() >= 1, START, "the policy's action publisher")
    bridge = spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}",
                   "-p", "mode:=realtime", "-p", "control_rate_hz:=500", "-p", "episode_length:=1500",
                   "-p", "min_subscribers:=1", "-p", "diagnostics_period_s:=0.1")
    wait_until(lambda: len(actions) >= 200, START, "200 answers")
    wait_until(lambda: probe.counter("policy", "observations_skipped") > 0, 30, "skipped observations")
    assert bridge.stop() == 0
    stamps = [topics.stamp_to_ns(m.header.stamp) for m in list(actions)]
    assert stamps == sorted(set(stamps)), "answered an older observation after a newer one"
    d = probe.node_diag("policy")
    assert int(d["observations_lost"]) == 0 and int(d["stale_observations"]) == 0, d
    assert policy.alive()


@pytest.mark.ros
@pytest.mark.process
def test_a_checkpoint_for_another_task_is_refused_at_the_first_observation(spawn, probe):
    """A pendulum policy next to a walker bridge (the README's mistake): the policy says so at
    once and never publishes a wrong-sized action; the bridge's image never gets an answer."""
    import time

    actions = probe.record(topics.ACTION, JointState, qos.action_qos())
    images = probe.record(topics.IMAGE, Image, qos.observation_qos())
    policy = spawn("policy", *policy_args())          # pendulum_swingup, random agent
    wait_until(lambda: actions.matched() >= 1, START, "the policy's action publisher")
    bridge = spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", "task:=walker_walk",
                   "-p", "diagnostics_period_s:=0.1")
    wait_until(lambda: len(images) >= 1, START, "the walker bridge's first observation")
    t_first = time.monotonic()
    wait_until(lambda: "the checkpoint is for pendulum_swingup, the bridge runs walker_walk"
               in policy.output(), 10, "the mismatch in the policy's log")
    assert time.monotonic() - t_first < 2.0
    wait_until(lambda: probe.node_diag("policy").get("_level") == 2, 10, "the policy's status ERROR")
    time.sleep(1.0)
    assert len(actions) == 0
    assert "not answering" in probe.node_diag("policy")["_message"]
    assert bridge.alive() and policy.alive()


@pytest.mark.ros
@pytest.mark.process
def test_two_bridges_in_one_namespace_are_reported_by_both(spawn, probe):
    """...and by the policy that reads them: both announce themselves on bridge_info and
    publish image and step_info (the policy warns once per topic and counts on /diagnostics)."""
    policy = spawn("policy", *policy_args())
    a = spawn("bridge_a", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}", "-p", "seed:=1",
              "-p", "diagnostics_period_s:=0.1", "-r", "__node:=sim_bridge_a")
    b = spawn("bridge_b", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}", "-p", "seed:=2",
              "-p", "diagnostics_period_s:=0.1", "-r", "__node:=sim_bridge_b")
    for name in ("sim_bridge_a", "sim_bridge_b"):
        wait_until(lambda: "/protocad/image" in probe.node_diag(name).get("other_publishers", ""), START,
                   f"{name} to report the other bridge")
        assert probe.node_diag(name)["_level"] == 2
    for proc in (a, b):
        wait_until(lambda: "another node also publishes /protocad/image" in proc.output(), 10, "the error line")
    for name in ("sim_bridge_a", "sim_bridge_b"):
        assert int(probe.node_diag(name)["multiple_publishers_detected"]) >= 1
    wait_until(lambda: "/protocad/bridge_info (2)" in probe.node_diag("policy").get("multiple_publishers", ""),
               START, "the policy to report the second bridge's announcement")
    d = probe.node_diag("policy")
    assert "/protocad/image (2)" in d["multiple_publishers"] and int(d["multiple_publishers_detected"]) >= 3, d
    assert d["_level"] >= 1 and policy.output().count("2 publishers on /protocad/bridge_info") == 1


@pytest.mark.ros
@pytest.mark.process
def test_serves_a_bf16_policy_in_float32_on_a_cpu_without_bf16(spawn, probe, tmp_path):
    """A policy whose config says bfloat16 (the machine that trained it had bf16; the shipped
    walker's weights): on a CPU without bf16 arithmetic ($PROTOCAD_CPU_NO_BF16 makes this one
    such a CPU for the node's process) the node loads its weights into float32, says so at
    start, and answers."""
    from helpers.agents import bf16_request_policy

    from protocad_ros.model.precision import NO_BF16_ENV

    path = bf16_request_policy(tmp_path / "bf16.pt")
    if path is None:
        pytest.skip("the package ships no walker_walk policy")
    f = Feeder(probe)
    args = policy_args(f"checkpoint:={path}")
    args[args.index(f"task:={TASK}")] = "task:=walker_walk"
    policy = spawn("policy", *args, env={NO_BF16_ENV: "1"})
    wait_until(f.ready, START, "the policy's subscriptions and publishers to match")
    said = "precision float32: the config asks for bfloat16, which cpu would emulate"
    wait_until(lambda: said in policy.output(), 30, "the node's precision line")
    assert f"hidden by ${NO_BF16_ENV}" in policy.output()
    f.obs(1_000, 0, is_first=True)
    f.wait_answers(1, "an answer")
    assert policy.alive() and np.all(np.abs(np.asarray(f.actions[0].effort)) <= 1.0)
