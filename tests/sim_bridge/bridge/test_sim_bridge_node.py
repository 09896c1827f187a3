"""The sim-bridge node as a real process, driven over DDS from this (separate) test process.

Lock-step determinism, the action contract (reject / clip / stale / duplicate, counted on
/diagnostics), the timeout rule, run-time parameters, the reset service, /clock, real-time mode
holding the latest action, and clean exits. Behaviour and counts only: no timing asserts.
"""
from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest
from helpers import ROOT, wait_exit, wait_until
from helpers.ros import Probe, Responder
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, JointState
from std_srvs.srv import Trigger

from sim_bridge.contract import qos, topics

TASK = "pendulum_swingup"
START = 90.0   # generous: first start on a loaded 2-core machine (imports, EGL, discovery)


@pytest.fixture
def probe():
    p = Probe("bridge_test_probe")
    yield p
    p.close()


def bridge_args(*params: str, ns: str | None = None) -> list[str]:
    args = ["-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}",
            "-p", "diagnostics_period_s:=0.1"]
    for p in params:
        args += ["-p", p]
    if ns:
        args += ["-r", f"__ns:={ns}"]
    return args


def wait_counter(probe: Probe, node: str, key: str, value: float, timeout: float = 20.0):
    wait_until(lambda: probe.counter(node, key) == value, timeout,
               f"{node} diagnostics {key} == {value} (now {probe.counter(node, key)})")


def digest(steps) -> list[tuple]:
    return [(stamp, info.reward, info.discount, info.is_first, info.is_last, info.is_terminal,
             info.episode, info.step, hashlib.sha1(img).hexdigest()) for stamp, info, img in steps]


@pytest.mark.ros
@pytest.mark.process
def test_help_and_configuration_errors(spawn):
    h = spawn("help", "-m", "sim_bridge.bridge.node", "--help")
    assert wait_exit(h, 60) == 0
    out = h.output()
    for name in ("task", "split", "seed", "mode", "control_rate_hz", "render_quality",
                 "episode_length", "action_repeat", "lockstep_timeout_s", "max_episodes",
                 "--ros-args", "__ns"):
        assert name in out, name
    bad_task = spawn("bad_task", *bridge_args("task:=no_such_task"))
    bad_range = spawn("bad_range", *bridge_args("seed:=-1"))
    bad_mode = spawn("bad_mode", *bridge_args("mode:=fast"))
    typo_strict = spawn("typo_strict", *bridge_args("tsk:=walker_walk", "strict:=true"))
    for proc, words in ((bad_task, ["no_such_task", "walker_walk"]), (bad_range, ["seed", "range"]),
                        (bad_mode, ["mode", "lockstep"]), (typo_strict, ["unknown parameter(s) ['tsk']"])):
        assert wait_exit(proc, 60) == 2, proc.output()
        out = proc.output()
        assert "configuration error" in out and all(w in out for w in words), out
        assert "Traceback" not in out


@pytest.mark.ros
@pytest.mark.process
def test_lockstep_is_deterministic_given_the_seed(spawn, probe):
    """Two bridges with seed 3 (own namespaces, concurrently) produce identical streams; seed 4
    differs. Each runs 2 episodes of 8 steps, every observation answered exactly once."""
    runs = {"/det_a": 3, "/det_b": 3, "/det_c": 4}
    from rosgraph_msgs.msg import Clock

    responders, contexts, procs, clocks = {}, {}, {}, {}
    for ns, seed in runs.items():
        responders[ns] = Responder(probe, lambda info: [math.sin(0.7 * info.step)],
                                   names=["torque"], ns=ns)
        contexts[ns] = probe.record(topics.CONTEXT, JointState, ns=ns)
        clocks[ns] = probe.record("clock", Clock, qos.clock_qos(True), ns=ns)   # NS/clock, not /clock
        procs[ns] = spawn(ns.strip("/"), *bridge_args(
            f"seed:={seed}", "episode_length:=8", "max_episodes:=2",
            ns=ns))
    for ns, proc in procs.items():
        assert wait_exit(proc, START) == 0, proc.output()
        assert "Traceback" not in proc.output()
    streams = {ns: digest(r.steps) for ns, r in responders.items()}
    ctx = {ns: [(topics.stamp_to_ns(m.header.stamp), topics.read_context(m)) for m in box]
           for ns, box in contexts.items()}
    a = streams["/det_a"]
    assert len(a) == 2 * 9                              # 2 episodes x (is_first + 8 steps)
    assert a == streams["/det_b"] and ctx["/det_a"] == ctx["/det_b"]
    assert a != streams["/det_c"]
    # Stamps: sim time from 0 in control_dt (40 ms for pendulum at action_repeat 2) steps,
    # never rewinding across the reset; ids and flags follow the Dreamer convention.
    dt = 40_000_000
    assert [s[0] for s in a] == [i * dt for i in range(len(a))]
    assert [(s[6], s[7]) for s in a] == [(e, t) for e in range(2) for t in range(9)]
    assert [s[3] for s in a] == [t == 0 for _ in range(2) for t in range(9)]
    assert [s[4] for s in a] == [t == 8 for _ in range(2) for t in range(9)]
    assert a[0][1] == 0.0                               # no reward on is_first
    # The context topic carries the same stamps, one context per episode.
    assert [c[0] for c in ctx["/det_a"]] == [s[0] for s in a]
    per_episode = {s[6]: c[1] for s, c in zip(a, ctx["/det_a"])}
    assert all(split == "train" and set(c) == {"m"} for c, split in per_episode.values())
    # Bridges in two namespaces keep their sim times apart: each clock runs on its own topic,
    # monotonic, one tick per step, and nothing of theirs lands on the global /clock.
    for ns in ("/det_a", "/det_c"):
        ticks = [topics.stamp_to_ns(m.clock) for m in clocks[ns]]
        assert ticks == [s[0] for s in streams[ns]] and ticks == sorted(ticks)
    assert probe.node.count_publishers("/clock") == 0
    # Every step_info carries the episode's return so far; the is_last one is the episode's
    # return, which the bridge also logs with the context.
    for ep in range(2):
        infos = [info for _, info, _ in responders["/det_a"].steps if info.episode == ep]
        running = np.cumsum([0.0 if i.is_first else i.reward for i in infos])
        assert np.allclose([i.episode_return for i in infos], running)
        assert f"episode {ep} finished: return {running[-1]:.1f} over 8 steps (train context m=" \
            in procs["/det_a"].output()
    # Each observation answered once; the answer to is_last is never executed.
    for ns, r in responders.items():
        assert sorted(r.answered) == sorted(set(r.answered)) == [s[0] for s in r.steps]


@pytest.mark.ros
@pytest.mark.process
def test_malformed_actions_timeouts_parameters_and_reset(spawn, probe):
    from sim_bridge.sim.envs import ContextDMCEnv

    r = Responder(probe, None, names=["torque"])          # answers only when told to
    clock = probe.record(topics.CLOCK, Clock, qos.clock_qos())
    bridge = spawn("bridge", *bridge_args("seed:=5", "episode_length:=20",
                                          "lockstep_timeout_s:=60.0", "bogus_param:=1"))
    wait_until(lambda: len(r.steps) >= 1, START, "the first observation")
    s0, info0, img0 = r.steps[0]
    assert info0.is_first and s0 == 0

    nan, inf = float("nan"), float("inf")
    r.send([0.1, 0.2], s0, names=["a", "b"])            # wrong length
    r.send([nan], s0)                                     # NaN
    r.send([inf], s0)                                     # inf
    r.send([-inf], s0)
    r.send([0.1, 0.2], s0, names=["torque"])            # names/effort disagree
    r.send([0.0], s0 + 1)                                 # answers no observation
    node = "sim_bridge"
    wait_counter(probe, node, "actions_rejected", 6)
    d = probe.node_diag(node)
    assert (d["rejected_wrong_length"], d["rejected_nonfinite"], d["rejected_malformed"],
            d["rejected_stale_stamp"]) == ("1", "3", "1", "1"), d
    assert d["steps"] == "0" and len(r.steps) == 1        # none of them was executed
    assert bridge.alive()

    r.send([5.0], s0)                                     # out of bounds: clipped to 1.0
    wait_until(lambda: len(r.steps) >= 2, 20, "the second observation")
    r.send([0.0], s0)                                     # already answered
    wait_counter(probe, node, "rejected_duplicate", 1)
    d = probe.node_diag(node)
    assert (d["actions_clipped"], d["actions_accepted"], d["steps"]) == ("1", "1", "1"), d
    s1, info1, img1 = r.steps[1]
    assert s1 == 40_000_000 and info1.step == 1 and not info1.is_first
    # Clipping, checked against the same env stepped here with the clipped action.
    with ContextDMCEnv(TASK, seed=5, time_limit=40) as env:
        o0 = env.reset()
        assert o0.image.tobytes() == img0
        o1 = env.step([1.0])
        assert o1.image.tobytes() == img1 and o1.reward == pytest.approx(info1.reward)

    # Run-time parameters: ranges, read-only and unknown names are refused.
    client = AsyncParameterClient(probe.node, "/protocad/sim_bridge")
    assert client.wait_for_services(20.0)

    def set_param(name, value, reason: list | None = None) -> bool:
        fut = client.set_parameters([Parameter(name, value=value)])
        wait_until(fut.done, 10, f"set {name}")
        if reason is not None:
            reason.append(fut.result().results[0].reason)
        return fut.result().results[0].successful

    assert not set_param("lockstep_timeout_s", -1.0)
    assert not set_param("seed", 7)
    why: list = []
    assert not set_param("no_such_parameter", 1, why)
    assert "no_such_parameter" in why[0], why          # rclpy alone says "...parameter(s): []"
    assert not set_param("control_rate_hz", "fast")
    assert set_param("lockstep_timeout_s", 0.3)
    wait_counter(probe, node, "parameters_rejected", 4)
    d = probe.node_diag(node)
    assert d["unknown_parameters"] == "1"          # bogus_param at start
    assert d["_level"] == 1 and "bogus_param" in d["_message"], d      # WARN, naming it

    # Timeout rule: no answer -> the same observation again (same stamp, same bytes), counted.
    wait_until(lambda: len(r.steps) >= 3, 20, "a republished observation")
    assert r.steps[2][0] == s1 and r.steps[2][2] == img1 and r.steps[2][1] == info1
    wait_until(lambda: probe.counter(node, "lockstep_timeouts") >= 1, 10, "lockstep_timeouts")
    assert set_param("lockstep_timeout_s", 60.0)

    # Reset service: ends episode 0 at once; the next observation is episode 1's first.
    cli = probe.node.create_client(Trigger, "/protocad/reset")
    assert cli.wait_for_service(timeout_sec=10.0)
    n = len(r.steps)
    fut = cli.call_async(Trigger.Request())
    wait_until(fut.done, 20, "the reset service")
    assert fut.result().success, fut.result().message
    assert "episode 1 started" in fut.result().message
    wait_until(lambda: any(i.is_first and i.episode == 1 for _, i, _ in r.steps[n:]), 20,
               "episode 1's first observation")
    s2, info2, _ = next(x for x in r.steps[n:] if x[1].is_first)
    assert (info2.episode, info2.step, info2.reward) == (1, 0, 0.0) and s2 > s1
    r.send([0.0], s1)                                     # answers the abandoned observation
    wait_counter(probe, node, "rejected_stale_stamp", 2)
    r.send([0.0], s2)
    wait_until(lambda: r.steps[-1][1].step == 1 and r.steps[-1][1].episode == 1, 20,
               "episode 1 step 1")
    wait_counter(probe, node, "resets_requested", 1)

    # /clock follows the observation stamps (sim time), never rewinding.
    clock_ns = [topics.stamp_to_ns(m.clock) for m in list(clock)]
    assert clock_ns == sorted(clock_ns)
    assert {s for s, _, _ in r.steps} <= set(clock_ns)
    assert bridge.alive()
    assert bridge.stop() == 0
    out = bridge.log_path.read_text()
    assert "Traceback" not in out and "stopped:" in out
    assert "unknown parameter 'bogus_param' ignored" in out


@pytest.mark.ros
@pytest.mark.process
def test_realtime_holds_the_latest_action(spawn, probe):
    from sim_bridge.sim.envs import ContextDMCEnv

    r = Responder(probe, None, names=["torque"])
    bridge = spawn("bridge_rt", *bridge_args("mode:=realtime", "control_rate_hz:=50",
                                             "seed:=9", "episode_length:=400"))
    # Steps without any policy: zeros are held before the first action.
    wait_until(lambda: len(r.steps) >= 10, START, "10 real-time observations")
    k_sent = len(r.steps) - 1
    r.send([1.0], r.steps[k_sent][0])
    wait_until(lambda: len(r.steps) >= k_sent + 30, 30, "30 more observations")
    r.send([-1.0], r.steps[2][0])                         # late, and older than the held one
    r.send([0.5], 10**15)                                 # answers nothing ever published
    wait_until(lambda: probe.counter("sim_bridge", "rejected_stale_stamp") == 1, 10,
               "the unknown stamp to be rejected")
    late = probe.counter("sim_bridge", "late_actions")
    assert late >= 1                                      # at least the [-1.0] one
    d = probe.node_diag("sim_bridge")
    assert d["mode"] == "realtime" and float(d["control_rate_hz"]) == 50.0
    assert bridge.stop() == 0                             # SIGINT: clean exit
    assert "Traceback" not in bridge.log_path.read_text()

    steps = list(r.steps)
    stamps = [s for s, _, _ in steps]
    assert stamps == [i * 40_000_000 for i in range(len(steps))]   # no gaps, no repeats
    images = [img for _, _, img in steps]

    def rollout(switch: int) -> list[bytes]:
        """Zeros until observation `switch`, then 1.0 held (the late -1.0 never applied)."""
        with ContextDMCEnv(TASK, seed=9, time_limit=800) as env:
            out = [env.reset().image.tobytes()]
            for i in range(1, len(steps)):
                out.append(env.step([0.0] if i <= switch else [1.0]).image.tobytes())
        return out

    zeros = rollout(len(steps))
    first_diff = next(i for i in range(len(steps)) if zeros[i] != images[i])
    assert first_diff > k_sent                            # nothing applied before it was sent
    # The action took effect at some tick after it was sent and was held from then on.
    assert any(rollout(sw) == images for sw in reversed(range(k_sent, first_diff)))


def test_docs_cover_every_parameter_and_counter():
    from sim_bridge.bridge.node import COUNTERS, PARAMS

    doc = (ROOT / "msgs_docs" / "sim_bridge.md").read_text()
    missing = [n for n in [p.name for p in PARAMS] + list(COUNTERS) if f"`{n}`" not in doc]
    assert not missing, f"msgs_docs/sim_bridge.md does not document {missing}"


@pytest.mark.ros
@pytest.mark.process
def test_fixed_context_outside_the_split_is_a_configuration_error(spawn):
    bad = spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", "task:=pendulum_swingup",
                "-p", "split:=test", "-p", "context:=m=1.0")
    wait_until(lambda: not bad.alive(), 120, "the bridge to refuse m=1.0 on the test split")
    assert bad.p.returncode == 2
    out = bad.output()
    assert "configuration error" in out and "belongs to the train split" in out


@pytest.mark.ros
@pytest.mark.process
def test_image_qos_is_overridable_by_parameter(spawn, probe):
    """`-p qos_overrides./protocad/image.publisher.reliability:=best_effort` (rclpy's QoS
    overriding) turns the image writer best effort, e.g. for a viewer over a lossy link."""
    from rclpy.qos import ReliabilityPolicy

    bridge = spawn("bridge_qos", *bridge_args("qos_overrides./protocad/image.publisher.reliability:=best_effort"))

    def offered(topic: str):
        infos = probe.node.get_publishers_info_by_topic(topic)
        return infos[0].qos_profile.reliability if infos else None

    # each writer is discovered on its own: wait for both before reading either
    wait_until(lambda: offered("/protocad/image") is not None and offered("/protocad/step_info") is not None,
               START, "the bridge's image and step_info publishers")
    assert offered("/protocad/image") == ReliabilityPolicy.BEST_EFFORT
    assert offered("/protocad/step_info") == ReliabilityPolicy.RELIABLE
    assert "unknown parameter" not in bridge.output()


@pytest.mark.ros
@pytest.mark.process
def test_a_second_action_publisher_is_reported_and_refused_with_first_publisher_only(spawn, probe):
    """An impostor publishes actions the bridge would otherwise take (the pending stamp, valid
    values) next to the stand-in policy: the bridge warns once, reports the topic and counts it,
    and with first_action_publisher_only refuses every impostor action while stepping on."""
    resp = Responder(probe, lambda info: [0.0], names=["torque"])
    bridge = spawn("bridge", *bridge_args("first_action_publisher_only:=true", "episode_length:=1000"))
    wait_until(lambda: len(resp.steps) >= 50, START, "50 lock-step steps")
    impostor = probe.node.create_publisher(JointState, probe.topic(topics.ACTION), qos.action_qos())
    wait_until(lambda: "/protocad/action (2)" in probe.node_diag("sim_bridge").get("multiple_publishers", ""),
               30, "the bridge to report two action publishers")
    n_fake = 20
    for _ in range(n_fake):
        msg = JointState()
        topics.set_stamp(msg.header.stamp, resp.steps[-1][0])   # the observation awaiting an answer
        msg.name, msg.effort = ["torque"], [1.0]
        impostor.publish(msg)
    wait_counter(probe, "sim_bridge", "rejected_other_publisher", n_fake)
    stepped = len(resp.steps)
    wait_until(lambda: len(resp.steps) >= stepped + 20, 60, "20 more steps from the first publisher")
    d = probe.node_diag("sim_bridge")
    assert int(d["rejected_stale_stamp"]) == int(d["rejected_duplicate"]) == 0, d   # refused before those checks
    assert int(d["multiple_publishers_detected"]) >= 1 and d["_level"] == 1, d       # WARN
    assert bridge.output().count("2 publishers on /protocad/action") == 1              # warned once
    probe.node.destroy_publisher(impostor)
    wait_until(lambda: probe.node_diag("sim_bridge").get("multiple_publishers") == "", 30,
               "the report to clear once the impostor is gone")
    assert bridge.alive()


def test_read_image_checks_the_size_before_copying_the_payload():
    """A wrong-sized payload is refused from its length alone; a right one is read without a copy."""
    import array

    import numpy as np

    class NoCopy:   # a payload whose bytes must not be touched
        def __len__(self):
            return 5

        def __iter__(self):
            raise AssertionError("the payload was copied before its size was checked")

    msg = Image(height=64, width=64, encoding="rgb8", step=192)
    msg.data = array.array("B", bytes(64 * 192))
    with pytest.raises(ValueError, match="5 bytes, expected 64x192"):
        topics.read_image(type("Msg", (), {"height": 64, "width": 64, "step": 192, "encoding": "rgb8",
                                           "data": NoCopy()})())
    img = topics.read_image(msg, (64, 64))
    assert img.shape == (64, 64, 3) and np.shares_memory(img, np.frombuffer(msg.data, np.uint8))
    with pytest.raises(ValueError, match="image is 64x64, expected 32x32"):
        topics.read_image(msg, (32, 32))


def test_a_full_lossless_history_is_waited_for_not_fatal():
    """Fast DDS refuses a sample once a KEEP_ALL writer holds 5000 a reader has not acknowledged
    (a recorder stalled that long): the bridge waits and publishes it then, counting the waits;
    only when it is stopping, or not lossless, does the error go up."""
    from types import SimpleNamespace

    from sim_bridge.bridge.camera_out import CameraOut
    from sim_bridge.bridge.handover import BridgeShared, Handover
    from sim_bridge.bridge.node import PARAMS, RCLError
    from sim_bridge.bridge.observation_publishing import ObservationPublishing

    class FullThenFree:
        topic_name = "/protocad/image"

        def __init__(self, refusals: int):
            self.refusals, self.sent = refusals, []

        def publish(self, msg):
            if self.refusals:
                self.refusals -= 1
                raise RCLError("Failed to publish: cannot publish data")
            self.sent.append(msg)

    def bridge(lossless: bool) -> ObservationPublishing:
        # The part alone: no node needed to publish (only an is_last observation logs).
        shared = BridgeShared(node=None, params={}, handover=Handover(), counters={"publish_waits": 0},
                              throttle=SimpleNamespace(warning=lambda *a: None), lockstep=True)
        return ObservationPublishing(shared, camera_out=CameraOut({p.name: p.default for p in PARAMS}),
                                     observation_pubs=(None, None, None), pub_clock=None, lossless=lossless)

    b, pub = bridge(True), FullThenFree(3)
    with b.handover.cond:
        b._send(pub, "obs")
    assert pub.sent == ["obs"] and b.counters["publish_waits"] == 3
    stopping = bridge(True)
    stopping.handover.stop.set()
    for b in (bridge(False), stopping):
        with b.handover.cond, pytest.raises(RCLError):
            b._send(FullThenFree(1), "obs")


def test_the_first_publisher_lock_follows_one_writers_sequence_numbers():
    from sim_bridge.nodekit.publisher_watch import FirstPublisherLock

    lock = FirstPublisherLock()
    assert lock.admit(7, matched=2) is not None            # two before any sample: neither is first
    assert lock.admit(7, matched=1) is None                # alone: it takes the lock
    assert lock.admit(8, matched=2) is None                # its next number, a second one matched
    assert "another publisher" in lock.admit(1, matched=2)  # the newcomer's own numbering
    assert lock.admit(8, matched=2) is not None            # a repeat is not the locked writer's
    assert lock.admit(9, matched=2) is None
    assert lock.admit(3, matched=1) is not None            # alone but not continuing: the impostor stayed
    lock.release()                                         # nobody matched any more
    assert lock.admit(1, matched=1) is None and lock.last == 1   # a restarted policy takes it
