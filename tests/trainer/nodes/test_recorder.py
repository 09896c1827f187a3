"""The recorder node as a separate process, fed by real DDS traffic from this process."""
from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from helpers import interrupt, wait_until

from sim_bridge.contract import topics as T
from trainer.bag.reader import BagReader, read_bag_metadata
from trainer.bag.rosmsg import TypeSupportError, type_hash

NS = T.DEFAULT_NAMESPACE
STEPS = 150
BASE = 5_000_000_000  # sim-time stamp of step 0 (ns); step i is BASE + i * 20 ms
TOPICS = [T.topic_name(NS, t) for t in (T.IMAGE, T.STEP_INFO, T.CONTEXT, T.ACTION,
                                         T.CONTEXT_FEATURES)] + [T.CLOCK]


def stamp(i: int) -> int:
    return BASE + i * 20_000_000


@pytest.fixture
def ros():
    from helpers.ros import publisher_node

    yield from publisher_node("recorder_test_publisher")


def make_publishers(node):
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image, JointState

    from sim_bridge.contract import qos
    # The contract's reliability/durability; a history deep enough that a burst on a loaded
    # machine cannot overwrite samples the recorder's reader has not received yet (a KEEP_LAST
    # writer drops those: msgs_docs/recorder.md, "QoS, and why").
    obs, clock = qos.observation_qos(), qos.clock_qos()
    obs.depth = clock.depth = 1000
    pubs = {}
    for rel in (T.IMAGE, T.STEP_INFO, T.CONTEXT, T.ACTION, T.CONTEXT_FEATURES):
        pubs[T.topic_name(NS, rel)] = node.create_publisher(
            Image if rel == T.IMAGE else JointState, rel, obs)
    pubs[T.CLOCK] = node.create_publisher(Clock, T.CLOCK, clock)
    return pubs


def publish_steps(pubs, steps: int) -> None:
    """Lock-step-like traffic: one step (6 messages, same stamp) every ~2 ms."""
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image, JointState
    for i in range(steps):
        t = stamp(i)
        img = np.full((64, 64, 3), i % 256, np.uint8)
        pubs[TOPICS[0]].publish(T.fill_image(Image(), img, t))
        pubs[TOPICS[1]].publish(T.fill_step_info(
            JointState(), T.StepInfo(0.1 * i, 1.0, i == 0, False, False, 0, i), t))
        pubs[TOPICS[2]].publish(T.fill_context(JointState(), {"m": 1.5}, "train", t))
        pubs[TOPICS[3]].publish(T.fill_action(JointState(), [0.01 * i], ["a0"], t))
        pubs[TOPICS[4]].publish(T.fill_context_features(
            JointState(), np.zeros(2), np.ones(3) / 3, np.zeros(2), t))
        clock = Clock()
        T.set_stamp(clock.clock, t)
        pubs[TOPICS[5]].publish(clock)
        time.sleep(0.002)


def wait_matched(pubs) -> None:
    wait_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 60,
             "the recorder to subscribe to every contract topic")


def wait_acked(pubs) -> None:
    from rclpy.duration import Duration
    for topic, p in pubs.items():
        assert p.wait_for_all_acked(Duration(seconds=15)), f"{topic}: not acknowledged"


def check_recorded(reader: BagReader, steps: int) -> None:
    assert reader.report.ok, reader.report.summary()
    assert reader.report.counts == {t: steps for t in TOPICS}
    stamps: dict[str, list[int]] = {t: [] for t in TOPICS}
    for m in reader.messages():
        msg = reader.decode(m)
        stamps[m.topic].append(T.stamp_to_ns(msg.clock if m.topic == T.CLOCK
                                             else msg.header.stamp))
        assert m.publish_time_ns > 0 and m.log_time_ns >= m.publish_time_ns - 50_000_000
        if m.topic == TOPICS[0]:
            assert (T.read_image(msg) == (T.stamp_to_ns(msg.header.stamp) - BASE)
                    // 20_000_000 % 256).all()
    for t in TOPICS:  # every message once, with its stamp (sorted: log time ~ publish order)
        assert sorted(stamps[t]) == [stamp(i) for i in range(steps)], t


@pytest.mark.ros
@pytest.mark.process
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_recorder_records_every_message_and_closes_cleanly(tmp_path, spawn, ros, sig):
    bag = tmp_path / "run"
    rec = spawn("recorder", "-m", "trainer.nodes.recorder", "-o", str(bag), "--chunk-size", "65536",
                "-p", "100")
    pubs = make_publishers(ros)   # the recorder finds the topics when they appear
    wait_matched(pubs)
    publish_steps(pubs, STEPS)
    wait_acked(pubs)              # every sample is in the recorder's reader history
    assert rec.stop(sig) == 0, rec.output()
    out = rec.log_path.read_text()
    assert f"recorded {STEPS * len(TOPICS)} messages" in out, out

    info = read_bag_metadata(bag)
    assert info["relative_file_paths"] == ["run_0.mcap"]
    assert info["message_count"] == STEPS * len(TOPICS)
    tm = {x["topic_metadata"]["name"]: x["topic_metadata"]
          for x in info["topics_with_message_count"]}
    qos = tm[TOPICS[0]]["offered_qos_profiles"][0]
    assert (qos["reliability"], qos["durability"], qos["history"]) == \
        ("reliable", "volatile", "unknown")
    assert tm[TOPICS[0]]["type_description_hash"] == type_hash("sensor_msgs/msg/Image")
    r = BagReader(bag)
    assert not r.report.truncated
    check_recorded(r, STEPS)
    from helpers.bags import rerun_check
    res = rerun_check(bag / "run_0.mcap")
    assert res.returncode == 0, res.stdout + res.stderr
    from rosbags.rosbag2 import Reader
    with Reader(bag) as rb:
        assert rb.message_count == STEPS * len(TOPICS)


@pytest.mark.ros
@pytest.mark.process
def test_recorder_killed_with_sigkill_keeps_flushed_chunks(tmp_path, spawn, ros):
    bag = tmp_path / "killed"
    rec = spawn("recorder", "-m", "trainer.nodes.recorder", "-o", str(bag), "--chunk-size", "8192",
                "--flush-interval", "0.2", "-p", "100")
    pubs = make_publishers(ros)
    wait_matched(pubs)
    steps = 100
    publish_steps(pubs, steps)
    wait_acked(pubs)
    # the flush timer writes the open chunk within 0.2 s: wait until a reader sees it all
    wait_until(lambda: BagReader(bag).report.message_count == steps * len(TOPICS), 20,
             "the recorder to write every message in complete chunks")
    rec.stop(signal.SIGKILL)
    assert not (bag / "metadata.yaml").exists()
    r = BagReader(bag)
    assert str(bag / "killed_0.mcap") in r.report.truncated, r.report.summary()
    check_recorded(r, steps)


@pytest.mark.process
def test_recorder_help():
    res = subprocess.run([sys.executable, "-m", "trainer.nodes.recorder", "--help"], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0 and "--max-bag-size" in res.stdout and "--compression" in res.stdout


@pytest.mark.ros
@pytest.mark.process
def test_recording_into_a_full_disk_stops_cleanly_with_a_readable_bag(ros, small_disk):
    """Random (incompressible) 12 KB images until the disk is full: the recorder exits by itself
    with EXIT_WRITE_FAILED, prints the summary with the loss, and the bag is valid MCAP that the
    mcap library and rosbags read, with no temporary file left."""
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader
    from sensor_msgs.msg import Image, JointState

    from sim_bridge.contract import qos
    from trainer.nodes.recorder import EXIT_WRITE_FAILED

    bag = small_disk.path / "bag"
    obs = qos.observation_qos()
    obs.depth = 1000
    pub = ros.create_publisher(Image, T.IMAGE, obs)
    info_pub = ros.create_publisher(JointState, T.STEP_INFO, obs)   # two topics, two DDS readers
    rec = subprocess.Popen([sys.executable, "-m", "trainer.nodes.recorder", "-o", str(bag), T.topic_name(NS, T.IMAGE),
                            T.topic_name(NS, T.STEP_INFO), "--ros-args", "-p", "flush_interval:=0.2",
                            "-p", "min_free_disk:=0"],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_until(lambda: pub.get_subscription_count() >= 1 and info_pub.get_subscription_count() >= 1, 60,
                 "the recorder's subscriptions")
        rng = np.random.default_rng(0)
        sent = 0
        while rec.poll() is None and sent < 400:
            img = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
            pub.publish(T.fill_image(Image(), img, stamp(sent)))
            info_pub.publish(T.fill_named(JointState(), ["step"], [sent], stamp(sent)))
            sent += 1
            time.sleep(0.005)
        out, _ = rec.communicate(timeout=60)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == EXIT_WRITE_FAILED, out
    assert "RECORDING STOPPED EARLY" in out and "No space left on device" in out, out
    assert "metadata.yaml: written" in out, out
    files = sorted(p.name for p in bag.iterdir())
    assert files == ["bag_0.mcap", "metadata.yaml"], files      # no .tmp, no reserve left
    with open(bag / "bag_0.mcap", "rb") as f:
        n_mcap = sum(1 for _ in make_reader(f).iter_messages())
    assert n_mcap > 0
    # log times never go back in the file as written (no index): what streaming readers need
    from mcap.records import Message
    from mcap.stream_reader import StreamReader
    with open(bag / "bag_0.mcap", "rb") as f:
        times = [r.log_time for r in StreamReader(f, emit_chunks=False).records if isinstance(r, Message)]
    assert times == sorted(times) and len(times) == n_mcap
    with Reader(bag) as reader:
        n_rosbags = sum(1 for _ in reader.messages())
        assert reader.message_count == n_rosbags
    import yaml

    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["custom_data"]["protocad_write_error"].startswith("OSError")
    assert info["message_count"] == n_mcap
    assert n_rosbags == n_mcap == sum(1 for _ in BagReader(bag).messages()) > 0


# `ros2 bag record` options of Jazzy (rosbag2's ros2bag/verb/record.py and the MCAP storage
# plugin's --storage-preset-profile / --storage-config-file), with the meaning each must have.
JAZZY_RECORD_OPTIONS = [
    "-o", "--output", "-s", "--storage", "--topics", "--services", "--topic-types", "-a", "--all",
    "--all-topics", "--all-services", "-e", "--regex", "--exclude-regex", "--exclude-topic-types",
    "--exclude-topics", "--exclude-services", "--include-unpublished-topics", "--include-hidden-topics",
    "--no-discovery", "-p", "--polling-interval", "--ignore-leaf-topics", "--qos-profile-overrides-path",
    "-f", "--serialization-format", "-b", "--max-bag-size", "-d", "--max-bag-duration", "--max-cache-size",
    "--disable-keyboard-controls", "--start-paused", "--use-sim-time", "--node-name", "--custom-data",
    "--snapshot-mode", "--log-level", "--compression-queue-size", "--compression-threads",
    "--compression-mode", "--compression-format", "--storage-preset-profile", "--storage-config-file",
]


def test_every_jazzy_record_option_is_known_with_its_meaning_or_refused_with_a_reason():
    from trainer.nodes.recorder import UNSUPPORTED_OPTIONS, build_parser

    ap = build_parser()
    known = {s for a in ap._actions for s in a.option_strings}
    assert not [o for o in JAZZY_RECORD_OPTIONS if o not in known]
    a = ap.parse_args(["-e", "^/a/", "--exclude-regex", "skip", "-b", "4096", "-d", "30", "-o", "x"])
    assert (a.regex, a.exclude_regex, a.max_bagfile_size, a.max_bagfile_duration, a.output) == (
        "^/a/", "skip", 4096, 30.0, "x")           # -e includes (it excluded here before)
    assert ap.parse_args(["-a"]).all_topics and ap.parse_args(["--all-topics"]).all_topics
    for opt in UNSUPPORTED_OPTIONS:
        res = subprocess.run([sys.executable, "-m", "trainer.nodes.recorder", opt], capture_output=True, text=True,
                             timeout=60) if opt == "--snapshot-mode" else None
        if res is not None:
            assert res.returncode == 2 and "snapshot mode is not supported" in res.stderr


@pytest.mark.ros
@pytest.mark.process
def test_include_and_exclude_regex_select_topics_as_ros2_bag_record(ros, tmp_path):
    from std_msgs.msg import String

    pubs = {t: ros.create_publisher(String, t, 10) for t in ("/a/keep", "/a/skip_me", "/a/drop", "/b/other")}
    bag = tmp_path / "sel"
    rec = subprocess.Popen([sys.executable, "-m", "trainer.nodes.recorder", "-o", str(bag), "-e", "^/a/",
                            "--exclude-regex", "skip", "--exclude-topics", "/a/drop", "-p", "50"],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_until(lambda: pubs["/a/keep"].get_subscription_count() >= 1, 60, "the recorder on /a/keep")
        time.sleep(1.0)   # it had the chance to (wrongly) subscribe to the others too
        for i in range(20):
            for pub in pubs.values():
                pub.publish(String(data=str(i)))
            time.sleep(0.01)
        time.sleep(1.0)
        assert [t for t, p in pubs.items() if p.get_subscription_count()] == ["/a/keep"]
        out = interrupt(rec)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == 0, out
    assert BagReader(bag).report.counts == {"/a/keep": 20}


def test_the_topic_selection_is_a_part_readable_alone():
    """RecorderTopics' TopicSelection without a node: -e, the excludes, hidden topics and a bad
    regular expression (refused before any bag exists)."""
    from trainer.nodes.recorder_topics import TopicSelection

    p = {"all_topics": False, "regex": "^/a/", "include_hidden_topics": False, "topics": ["/b/other"],
         "namespace": NS, "exclude_regex": "skip", "exclude_topics": ["/a/drop"]}
    sel = TopicSelection(p, lambda t: t, {"/a/keep": {"depth": 5}})
    assert [t for t in ("/a/keep", "/a/skip_me", "/a/drop", "/b/other", "/c", "/a/_hidden") if sel.want(t)] \
        == ["/a/keep", "/b/other"]
    assert sel.text() == "/b/other, topics matching '^/a/'" and sel.qos_override("/a/keep") == {"depth": 5}
    assert TopicSelection({**p, "regex": "", "topics": []}, lambda t: t, None).wanted[0].startswith(NS)
    with pytest.raises(ValueError, match="bad regular expression"):
        TopicSelection({**p, "regex": "("}, lambda t: t, None)


@contextlib.contextmanager
def frozen_recorder(*args: str):
    """A recorder process the test freezes (SIGSTOP) and stops, reading its output at the end;
    continued and killed should the test fail first."""
    rec = subprocess.Popen([sys.executable, "-m", "trainer.nodes.recorder", *args],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        yield rec
    finally:
        if rec.poll() is None:
            rec.send_signal(signal.SIGCONT)
            rec.kill()


@pytest.mark.ros
@pytest.mark.process
def test_loss_while_frozen_is_counted_exactly_and_shown_by_the_dataset(ros, tmp_path):
    """A KEEP_LAST(50) writer at full speed while the recorder is frozen (SIGSTOP) for 3 s: what
    the bag lacks equals what the recorder counted as lost, in its summary, metadata.yaml and
    the dataset report."""
    import yaml
    from sensor_msgs.msg import JointState

    from sim_bridge.contract import qos
    from trainer.data.dataset import MCAPDataset

    q = qos.observation_qos()
    q.depth = 50
    pub = ros.create_publisher(JointState, T.STEP_INFO, q)
    bag = tmp_path / "frozen"
    with frozen_recorder("-o", str(bag), T.topic_name(NS, T.STEP_INFO), "-p", "100") as rec:
        wait_until(lambda: pub.get_subscription_count() >= 1, 60, "the recorder's subscription")
        time.sleep(0.5)
        n = 3000
        for i in range(n):
            if i == 1000:
                rec.send_signal(signal.SIGSTOP)
            if i == 2000:
                time.sleep(3.0)
                rec.send_signal(signal.SIGCONT)
            info = T.StepInfo(0.0, 1.0, i == 0, False, False, 0, i)
            pub.publish(T.fill_step_info(JointState(), info, stamp(i)))
            if i < 1000 or i >= 2000:
                time.sleep(0.001)
        time.sleep(2.0)
        out = interrupt(rec)
    assert rec.returncode == 0, out
    recorded = BagReader(bag).report.counts[T.topic_name(NS, T.STEP_INFO)]
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    lost = json.loads(info["custom_data"]["protocad_lost_messages"])[T.topic_name(NS, T.STEP_INFO)]
    assert lost > 0 and recorded + lost == n, (recorded, lost, out)
    assert f"LOST before the recorder took them (sequence gaps): {lost}" in out
    ds_report = MCAPDataset([bag], seq_len=4, cache_dir=tmp_path / "cache").report.summary()
    assert "the recorder reported lost messages" in ds_report and str(lost) in ds_report


@pytest.mark.ros
@pytest.mark.process
def test_a_stall_past_the_lease_is_reported_though_no_later_sample_shows_a_gap(ros, tmp_path):
    """Frozen (SIGSTOP) past its lease (--lease-duration 3) with nothing published after it,
    no sequence gap can show a loss: the stall itself is reported, in the log, the summary,
    metadata.yaml and the dataset report. A freeze shorter than the lease is not."""
    import yaml
    from sensor_msgs.msg import JointState

    from sim_bridge.contract import qos
    from trainer.data.dataset import MCAPDataset

    pub = ros.create_publisher(JointState, T.STEP_INFO, qos.observation_qos())
    bag = tmp_path / "stalled"
    with frozen_recorder("-o", str(bag), "--lease-duration", "3", T.topic_name(NS, T.STEP_INFO), "-p", "100") as rec:
        wait_until(lambda: pub.get_subscription_count() >= 1, 60, "the recorder's subscription")
        for i in range(20):
            pub.publish(T.fill_step_info(JointState(), T.StepInfo(0.0, 1.0, i == 0, False, False, 0, i), stamp(i)))
        for frozen in (0.5, 6.0):
            rec.send_signal(signal.SIGSTOP)
            time.sleep(frozen)
            rec.send_signal(signal.SIGCONT)
            time.sleep(1.0)
        out = interrupt(rec)
    assert rec.returncode == 0, out
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    marked = json.loads(info["custom_data"]["protocad_stalls_past_lease"])
    assert marked["lease_s"] == 3 and len(marked["stalls_s"]) == 1 and 6 <= marked["stalls_s"][0] < 20, marked
    assert "longer than its DDS lease (3 s)" in out and "STALLED past the DDS lease (3 s)" in out, out
    assert "protocad_lost_messages" not in info["custom_data"]     # no later sample, no gap to count
    ds_report = MCAPDataset([bag], seq_len=4, cache_dir=tmp_path / "cache").report.summary()
    assert "the recorder reported stalls past lease" in ds_report, ds_report


class ImportSpy:
    """A meta path finder that records every module name looked up while installed."""

    def __init__(self):
        self.names: list[str] = []

    def find_spec(self, name, path=None, target=None):
        self.names.append(name)
        return None

    def __enter__(self):
        sys.meta_path.insert(0, self)
        return self

    def __exit__(self, *exc):
        sys.meta_path.remove(self)


@pytest.mark.parametrize("type_name", ["idlelib/idle/X", "os/msg/X", "os.path/msg/X", "sensor_msgs/msg/Image.X",
                                       "sensor_msgs/idle/Image", "trainer/loop/X", "a/b/c/d", "../msg/X", ""])
def test_graph_type_names_are_checked_before_anything_is_imported(type_name):
    """Any participant can advertise any type string on a recorded topic (or one `ros2 topic echo`
    reads): only pkg/msg/Type names of ament packages, identifiers without dots, are imported."""
    from trainer.nodes.recorder_topics import _import_message
    from trainer.ros2cli.msgyaml import interface_class

    with ImportSpy() as spy:
        with pytest.raises(TypeSupportError):
            _import_message(type_name)
        with pytest.raises(ValueError):
            interface_class(type_name)
    assert spy.names == [], spy.names
    assert "idlelib.idle" not in sys.modules


def test_installed_message_types_still_import():
    from sensor_msgs.msg import Image
    from std_srvs.srv import Trigger

    from trainer.nodes.recorder_topics import _import_message
    from trainer.ros2cli.msgyaml import interface_class

    assert _import_message("sensor_msgs/msg/Image") is Image and _import_message("sensor_msgs/Image") is Image
    assert interface_class("std_srvs/srv/Trigger", kind="srv") is Trigger
    with pytest.raises(ValueError, match="unknown interface type"):
        interface_class("sensor_msgs/msg/Nope")     # an ament package, a type it lacks


@pytest.mark.ros
def test_the_parameters_are_its_table_and_list_ones_are_settable_as_string_arrays(tmp_path):
    """The node declares recorder_params.PARAMS, the command line's values as defaults; an empty
    list default is still a string array, so `-p topics:=[...]` works (a byte array refused it)."""
    import rclpy

    from trainer.nodes.recorder import RecorderNode
    from trainer.nodes.recorder_params import PARAMS

    ctx = rclpy.Context()
    rclpy.init(args=["recorder", "--ros-args", "-p", "topics:=[/a, /b]", "-p", "flush_interval:=2"], context=ctx)
    try:
        node = RecorderNode({"output": str(tmp_path / "bag"), "chunk_size": 4096, "no_discovery": True}, context=ctx)
        try:
            assert set(node.params) == {p.name for p in PARAMS}
            assert node.params["topics"] == ["/a", "/b"] and node.params["flush_interval"] == 2.0
            assert node.params["chunk_size"] == 4096 and node.params["exclude_topics"] == []
            kinds = {p.name: node.get_parameter(p.name).type_.name for p in PARAMS}
            assert kinds["topics"] == kinds["rate_limits"] == "STRING_ARRAY" and kinds["chunk_size"] == "INTEGER"
        finally:
            node.close()
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
