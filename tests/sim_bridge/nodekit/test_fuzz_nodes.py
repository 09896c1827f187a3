"""No message kills a node: property-based tests (hypothesis) drive every subscription,
service and parameter callback of the three nodes with generated messages of their types
(any float including NaN/+-inf/huge, any int, empty and long arrays, any string, any stamp),
in process; each callback must process or reject (counting it), never raise. A sample of the
hostile inputs then goes through real DDS to the policy node in its own process, which must
stay up and count them.

Found by this suite (and fixed): +inf in step_info `episode`/`step` raised OverflowError in
the policy node's callback (the process exited 1); a NaN `is_first` was taken as true.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import wait_until
from helpers.ros import Probe
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import Image, JointState

from sim_bridge.contract import qos, topics

pytestmark = pytest.mark.ros

NS = "/fuzz"
FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck),
                derandomize=True)

any_float = st.floats(allow_nan=True, allow_infinity=True, width=64)
hostile_float = st.one_of(st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 2.0 ** 63,
                                           -0.0, 0.5, 1.0, 0.0, 2.0]), any_float)
field_name = st.one_of(st.sampled_from(list(topics.STEP_INFO_FIELDS) + [topics.SPLIT_FIELD, "m", "d", "torque"]),
                       st.text(max_size=12))


@st.composite
def stamps(draw):
    return draw(st.integers(-2 ** 31, 2 ** 31 - 1)), draw(st.integers(0, 2 ** 32 - 1))


@st.composite
def joint_states(draw, contract_names: tuple[str, ...] | None = None):
    """A JointState: the contract's names with hostile values, or anything at all."""
    m = JointState()
    m.header.stamp.sec, m.header.stamp.nanosec = draw(stamps())
    m.header.frame_id = draw(st.text(max_size=8))
    if contract_names is not None and draw(st.booleans()):
        names = list(contract_names)
    else:
        names = draw(st.lists(field_name, max_size=12))
    m.name = names
    n = len(names) if draw(st.integers(0, 4)) else draw(st.integers(0, 20))
    for f in ("position", "velocity", "effort"):
        k = n if draw(st.booleans()) else draw(st.integers(0, 20))
        setattr(m, f, draw(st.lists(hostile_float, min_size=k, max_size=k)))
    return m


@st.composite
def images(draw):
    m = Image()
    m.header.stamp.sec, m.header.stamp.nanosec = draw(stamps())
    if draw(st.booleans()):       # well-formed geometry, hostile everything else
        h = w = 64
        step = 64 * 3
    else:
        h, w = (draw(st.one_of(st.integers(0, 70), st.integers(0, 2 ** 32 - 1))) for _ in range(2))
        step = draw(st.one_of(st.just(w * 3 % 2 ** 32), st.integers(0, 2 ** 32 - 1)))
    m.height, m.width, m.step = h, w, step
    m.encoding = draw(st.one_of(st.sampled_from(["rgb8", "bgr8", "mono8", ""]), st.text(max_size=10)))
    m.is_bigendian = draw(st.integers(0, 255))
    size = draw(st.one_of(st.just(h * step) if h * step <= 64 * 64 * 3 else st.just(0),
                          st.integers(0, 64 * 64 * 3 + 7)))
    m.data = bytes(size)
    return m


@pytest.fixture(scope="module")
def ros_context():
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


def overrides(**values):
    from rclpy.parameter import Parameter

    return [Parameter(k, value=v) for k, v in values.items()]


def in_process(node):
    yield node
    node.close()
    node.destroy_node()


@pytest.fixture(scope="module")
def policy_node(ros_context):
    from protocad_ros.node.policy_node import PolicyNode

    yield from in_process(PolicyNode(namespace=NS, context=ros_context, parameter_overrides=overrides(
        task="pendulum_swingup", num_threads=1)))


@pytest.fixture(scope="module")
def bridge_node(ros_context):
    from sim_bridge.bridge.node import SimBridgeNode

    # min_subscribers: it never starts stepping; only its callbacks are driven here.
    yield from in_process(SimBridgeNode(namespace=NS, context=ros_context, parameter_overrides=overrides(
        task="pendulum_swingup", min_subscribers=5)))


@pytest.fixture(scope="module")
def recorder_node(ros_context, tmp_path_factory):
    from trainer.nodes.recorder import RecorderNode

    node = RecorderNode({"output": str(tmp_path_factory.mktemp("fuzzbag") / "bag"), "namespace": NS},
                        context=ros_context)
    node.writer.add_topic(f"{NS}/image", "sensor_msgs/msg/Image", [])
    yield from in_process(node)


@FUZZ
@given(msg=joint_states(topics.STEP_INFO_FIELDS))
def test_policy_step_info_callback_is_total(policy_node, msg):
    before = policy_node.counters["step_info_rejected"]
    policy_node.observation_pairing._on_info(msg)      # must not raise
    try:
        topics.read_step_info(msg)
    except ValueError:
        assert policy_node.counters["step_info_rejected"] == before + 1


def test_step_info_with_inf_nan_is_rejected_not_fatal(policy_node):
    for episode, is_first in ((math.inf, 0.0), (0.0, math.nan), (-math.inf, 1.0), (2.0 ** 80, 1.0)):
        m = JointState()
        topics.fill_named(m, topics.STEP_INFO_FIELDS, [0.0, 1.0, is_first, 0.0, 0.0, episode, 3.0], 99)
        before = policy_node.counters["step_info_rejected"]
        policy_node.observation_pairing._on_info(m)
        assert policy_node.counters["step_info_rejected"] == before + 1
    m = JointState()
    topics.fill_named(m, topics.STEP_INFO_FIELDS, [math.nan, 1.0, 0.0, 0.0, 0.0, 0.0, 3.0], 99)
    with pytest.raises(ValueError, match="reward is not finite"):
        topics.read_step_info(m)


@FUZZ
@given(msg=images())
def test_policy_image_callback_is_total(policy_node, msg):
    before = policy_node.counters["images_received"]
    policy_node.camera_input._on_frame(msg)   # the image subscription's callback
    assert policy_node.counters["images_received"] == before + 1


@FUZZ
@given(msg=joint_states(("torque",)))
def test_bridge_action_callback_is_total(bridge_node, msg):
    before = bridge_node.counters["actions_received"]
    bridge_node.action_intake._on_action(msg)
    c = bridge_node.counters
    assert c["actions_received"] == before + 1
    assert c["actions_accepted"] + c["actions_rejected"] == c["actions_received"]


def test_bridge_reset_service_answers_before_the_first_episode(bridge_node):
    from std_srvs.srv import Trigger

    resp = bridge_node.action_intake._on_reset(Trigger.Request(), Trigger.Response())
    assert resp.success is False and "waiting" in resp.message


@FUZZ
@given(data=st.binary(max_size=300), recv=st.one_of(st.none(), st.integers(-2 ** 70, 2 ** 70)),
       src=st.one_of(st.none(), st.integers(-2 ** 70, 2 ** 70)),
       seq=st.one_of(st.none(), st.integers(-2 ** 70, 2 ** 70)),
       topic=st.sampled_from([f"{NS}/image", "/not/registered"]))
def test_recorder_message_callback_is_total(recorder_node, data, recv, src, seq, topic):
    writing = recorder_node.recorder_writing
    before = writing.received + writing.errors
    writing.on_message(topic, data, {"received_timestamp": recv, "source_timestamp": src,
                                     "publication_sequence_number": seq})
    assert writing.received + writing.errors == before + 1


param_value = st.one_of(st.booleans(), st.integers(-2 ** 63, 2 ** 63 - 1), hostile_float, st.text(max_size=12),
                        st.lists(st.text(max_size=5), min_size=1, max_size=3))


@pytest.mark.parametrize("which", ["policy_node", "bridge_node", "recorder_node"])
def test_parameter_changes_are_answered_and_unknown_names_are_named(which, request):
    from rclpy.exceptions import ParameterNotDeclaredException
    from rclpy.parameter import Parameter

    node = request.getfixturevalue(which)
    names = sorted(node._parameters) + ["tsk", "no_such_parameter"]

    @FUZZ
    @given(name=st.sampled_from(names), value=param_value)
    def check(name, value):
        if name in ("use_sim_time",):
            return   # a real clock switch, not an input to reject
        try:
            result = node.set_parameters_atomically([Parameter(name, value=value)])
        except ParameterNotDeclaredException as exc:
            assert name in str(exc) and not node.has_parameter(name)
            return
        assert result.successful in (True, False)
        if not result.successful:
            assert result.reason

    check()
    assert node.callback_errors == 0


@pytest.mark.process
def test_hostile_inputs_over_dds_leave_the_policy_process_up_and_counted(spawn):
    """A sample through real DDS from this process to the policy node's own process."""
    probe = Probe("fuzz_probe")
    try:
        pub_image = probe.publisher(topics.IMAGE, Image, qos.observation_qos())
        pub_info = probe.publisher(topics.STEP_INFO, JointState, qos.observation_qos())
        policy = spawn("policy", "-m", "protocad_ros.node.policy_node", "--ros-args", "-p", "task:=pendulum_swingup",
                       "-p", "diagnostics_period_s:=0.1", "-p", "num_threads:=1")
        wait_until(lambda: pub_image.get_subscription_count() >= 1 and pub_info.get_subscription_count() >= 1,
                   120, "the policy's subscriptions")
        wait_until(lambda: probe.node_diag("policy").get("agent") == "random", 60, "its diagnostics")
        hostile = [math.inf, -math.inf, math.nan, 1e308, 2.0 ** 64]
        rng = np.random.default_rng(0)
        for i, v in enumerate(hostile):
            for pos in (0, 2, 5, 6):       # reward, is_first, episode, step
                vals = [0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0]
                vals[pos] = v
                m = JointState()
                topics.fill_named(m, topics.STEP_INFO_FIELDS, vals, 10_000 + i)
                pub_info.publish(m)
        img = Image()
        img.height, img.width, img.step, img.encoding = 2 ** 31, 2 ** 31, 2 ** 32 - 1, "rgb8"
        pub_image.publish(img)
        pub_image.publish(topics.fill_image(Image(), rng.integers(0, 256, (64, 64, 3), dtype=np.uint8), 20_000))
        wait_until(lambda: probe.counter("policy", "step_info_rejected") >= 18
                   and probe.counter("policy", "images_rejected") >= 1, 30, "the rejections counted")
        assert policy.alive()
        assert probe.counter("policy", "callback_errors") == 0
    finally:
        probe.close()


@pytest.mark.process
def test_a_flood_is_accounted_for_answered_plus_lost_equals_published(spawn):
    """5,000 observations as fast as this process can publish them: the policy answers what it
    can, and every other one is counted as lost (from the step numbering)."""
    probe = Probe("flood_probe")
    try:
        pub_image = probe.publisher(topics.IMAGE, Image, qos.observation_qos())
        pub_info = probe.publisher(topics.STEP_INFO, JointState, qos.observation_qos())
        answers = probe.record(topics.ACTION, JointState, qos.action_qos())
        policy = spawn("policy", "-m", "protocad_ros.node.policy_node", "--ros-args", "-p", "task:=pendulum_swingup",
                       "-p", "diagnostics_period_s:=0.1", "-p", "num_threads:=1")
        wait_until(lambda: pub_image.get_subscription_count() >= 1 and pub_info.get_subscription_count() >= 1
                   and answers.matched() >= 1, 120, "the policy's subscriptions")
        img = topics.fill_image(Image(), np.zeros((64, 64, 3), np.uint8), 0)

        def publish(step: int) -> None:
            stamp = 1_000_000 * (step + 1)
            topics.set_stamp(img.header.stamp, stamp)
            info = topics.StepInfo(0.0, 1.0, step == 0, False, False, 0, step)
            pub_image.publish(img)
            pub_info.publish(topics.fill_step_info(JointState(), info, stamp))

        n = 5000
        publish(0)
        wait_until(lambda: len(answers) >= 1, 60, "the first answer")
        for step in range(1, n - 1):
            publish(step)
        wait_until(lambda: probe.node_diag("policy").get("step_info_received") is not None, 10, "diagnostics")
        import time

        time.sleep(2.0)              # the flood drains; then the last observation, as a bridge would
        publish(n - 1)

        def accounted() -> bool:
            d = probe.node_diag("policy")
            return int(d.get("step", -1)) == n - 1 and \
                int(d["observations_answered"]) + int(d["observations_lost"]) == n
        wait_until(accounted, 60, "answered + lost to account for every observation published")
        d = probe.node_diag("policy")
        assert int(d["observations_lost"]) > 0 and int(d["stale_observations"]) == 0, d
        assert policy.alive()
    finally:
        probe.close()
