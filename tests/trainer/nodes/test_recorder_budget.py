"""The recorder's disk is a budget: per-topic rate limits, byte-rate limits, message size limits
and byte budgets drop (and count) a flood's messages, bounded by default on the contract topics
and /diagnostics; the bag's byte budget and the free-disk floor end the recording with a closed,
valid bag and one line (exit 4), and a topic jumping far above its recent rate, or offered more
than its bounds let through, is flagged in the bag's metadata and on /diagnostics. The budget's
logic is tested on its own too."""
from __future__ import annotations

import base64
import json
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
from helpers import interrupt, wait_until

from sim_bridge.contract import topics as T
from trainer.bag.reader import BagReader
from trainer.nodes.record_budget import (
    BUDGET_KEY,
    DIAGNOSTICS_BYTE_BUDGET,
    DIAGNOSTICS_RATE_LIMIT_HZ,
    DROPPED_KEY,
    FLOOD_KEY,
    IMAGE_MESSAGE_BYTES,
    STEP_TOPIC_RATE_HZ,
    BudgetLimits,
    DiskFloor,
    RecordBudget,
    contract_bounds,
    parse_topic_values,
)

NS = T.DEFAULT_NAMESPACE


def test_a_rate_limit_keeps_its_rate_after_a_burst():
    b = RecordBudget(BudgetLimits(max_topic_rate=10.0, flood_factor=0))
    kept = sum(b.admit("/t", 10, i / 1000.0) is None for i in range(5000))   # 5 s at 1 kHz
    assert 20 + 50 - 2 <= kept <= 20 + 50 + 2          # 2 s of burst, then 10 Hz
    assert b.dropped == {"/t": {"rate": 5000 - kept}}


def test_byte_budgets_per_topic_and_for_the_bag():
    b = RecordBudget(BudgetLimits(topic_bytes={"/diagnostics": 1000}, max_total_bytes=5000, flood_factor=0))
    assert [b.admit("/diagnostics", 400, 0.0) for _ in range(4)] == [None, None, "topic_bytes", "topic_bytes"]
    assert [b.admit("/image", 1000, 0.0) for _ in range(5)] == [None, None, None, None, "total_bytes"]
    assert b.stopped and "budget of 5000 bytes" in b.stopped
    assert b.admit("/image", 1, 0.0) == "total_bytes"    # stays stopped
    meta = b.metadata()
    assert json.loads(meta[DROPPED_KEY]) == {"/diagnostics": {"topic_bytes": 2}, "/image": {"total_bytes": 2}}
    assert meta[BUDGET_KEY] == b.stopped


def test_a_jump_far_above_the_recent_rate_is_a_flood_once():
    b = RecordBudget(BudgetLimits())
    t = 0.0
    for _ in range(50):            # 5 s at 10 Hz: the recent figure
        b.admit("/diagnostics", 200, t)
        t += 0.1
    assert b.take_new_floods() == [] and not b.floods
    for _ in range(3000):          # 3 s at 1 kHz
        b.admit("/diagnostics", 200, t)
        t += 0.001
    assert b.take_new_floods() == ["/diagnostics"] and b.take_new_floods() == []
    f = b.floods["/diagnostics"]
    assert f["rate_hz"] >= 100 and 8 < f["recent_hz"] < 12   # flagged in the first second it shows
    assert "/diagnostics" in json.loads(b.metadata()[FLOOD_KEY])


def test_a_steady_fast_topic_is_no_flood():
    b = RecordBudget(BudgetLimits())
    for i in range(10_000):        # 10 s at 1 kHz from the start
        b.admit("/image", 12_000, i / 1000.0)
    assert not b.floods


def test_disk_floor_and_topic_values(tmp_path):
    assert DiskFloor(tmp_path, 0).below(1, 0.0) is None
    floor = DiskFloor(tmp_path / "bag", 1 << 62)           # more than any disk: below at once
    assert "below the floor of" in floor.below(1, 0.0)
    assert parse_topic_values(["/diagnostics=5", "/a=b=2"], "x") == {"/diagnostics": 5.0, "/a=b": 2.0}
    with pytest.raises(ValueError, match="TOPIC=NUMBER"):
        parse_topic_values(["/diagnostics"], "--rate-limit")


def test_the_contract_topics_and_diagnostics_are_bounded_by_default():
    """Declared once (record_budget.contract_bounds): /diagnostics as the launchers bounded it,
    and every contract topic in the namespace or a robot's namespace below it."""
    lim = BudgetLimits()
    assert lim.rate(T.DIAGNOSTICS) == DIAGNOSTICS_RATE_LIMIT_HZ == 20
    assert lim.bytes_for(T.DIAGNOSTICS) == DIAGNOSTICS_BYTE_BUDGET == 64 << 20
    for topic in ("/protocad/image", "/protocad/robot3/image", "/protocad/robot3/clock", "/clock"):
        assert lim.rate(topic) == STEP_TOPIC_RATE_HZ and lim.message_limit(topic) > 0, topic
    assert lim.message_limit("/protocad/image") == IMAGE_MESSAGE_BYTES == 64 * 64 * 3 + 4096
    assert contract_bounds("/elsewhere/image") is None and lim.rate("/camera/image") == 0
    assert BudgetLimits(namespace="/lab").rate("/lab/step_info") == STEP_TOPIC_RATE_HZ
    # the stricter of the default and --max-topic-rate; a topic's own value wins, 0 turns it off
    assert BudgetLimits(max_topic_rate=10).rate("/protocad/image") == 10
    off = BudgetLimits(rates={T.DIAGNOSTICS: 0}, message_bytes={"/protocad/image": 0})
    assert off.rate(T.DIAGNOSTICS) == 0 and off.message_limit("/protocad/image") == 0
    assert off.turned_off() == ["/diagnostics: rate limit", "/protocad/image: message size limit"]


def test_message_size_and_byte_rate_limits_drop_and_count():
    b = RecordBudget(BudgetLimits(byte_rates={"/t": 1000}, message_bytes={"/t": 600}, flood_factor=0))
    assert b.admit("/t", 601, 0.0) == "message_bytes"
    kept = sum(b.admit("/t", 100, i / 100.0) is None for i in range(500))   # 5 s of 10 kB/s
    assert 20 + 50 - 2 <= kept <= 20 + 50 + 2          # 2 s of burst (2000 B), then 1000 B/s
    assert b.dropped["/t"] == {"message_bytes": 1, "byte_rate": 500 - kept}


def test_a_flood_on_a_topic_without_history_is_flagged_from_its_first_second():
    b = RecordBudget(BudgetLimits())
    for i in range(40):            # 2 s of 2 MB /diagnostics at 20 Hz: at its rate limit, far over its bytes
        b.admit(T.DIAGNOSTICS, 2 << 20, i / 20.0)
    assert b.take_new_floods() == [T.DIAGNOSTICS]
    assert b.dropped[T.DIAGNOSTICS] == {"message_bytes": 40}
    for i in range(12_000):        # an unbounded topic: 6,000 msg/s is over the absolute floor
        b.admit("/t", 10, i / 6000.0)
    assert "/t" in b.floods
    quiet = RecordBudget(BudgetLimits())
    for i in range(3000):          # a lock-step stream at 1,000 steps/s is no flood
        quiet.admit("/protocad/image", 12_400, i / 1000.0)
    assert not quiet.floods and not quiet.dropped


@pytest.fixture
def ros():
    from helpers.ros import publisher_node

    yield from publisher_node("budget_test_publisher")


def recorder(bag, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "trainer.nodes.recorder", "-o", str(bag), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def flood_images(ros, rec: subprocess.Popen, limit: int = 3000) -> int:
    """Random 12 kB images as fast as they go until the recorder exits (or `limit`)."""
    from sensor_msgs.msg import Image

    from sim_bridge.contract import qos

    obs = qos.observation_qos()
    obs.depth = 1000
    pub = ros.create_publisher(Image, T.IMAGE, obs)
    wait_until(lambda: pub.get_subscription_count() >= 1, 60, "the recorder's subscription")
    rng = np.random.default_rng(0)
    sent = 0
    while rec.poll() is None and sent < limit:
        pub.publish(T.fill_image(Image(), rng.integers(0, 256, (64, 64, 3), dtype=np.uint8), sent))
        sent += 1
        time.sleep(0.001)
    return sent


def check_valid(bag) -> dict:
    """The bag reads whole (strict) and its metadata.yaml counts what is in it."""
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    r = BagReader(bag, strict=True)
    n = sum(1 for _ in r.messages())
    assert n == info["message_count"] > 0 and not r.report.truncated
    return info


@pytest.mark.ros
@pytest.mark.process
def test_a_flood_stops_at_the_bags_budget_with_a_valid_bag(ros, tmp_path):
    from trainer.nodes.recorder import EXIT_BUDGET

    bag = tmp_path / "bag"
    rec = recorder(bag, T.topic_name(NS, T.IMAGE), "--max-total-bytes", "600000", "--flood-factor", "0")
    try:
        sent = flood_images(ros, rec)
        out, _ = rec.communicate(timeout=60)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == EXIT_BUDGET, out
    assert sent < 3000
    errors = [x for x in out.splitlines() if "recording stopped:" in x]
    assert len(errors) == 1 and "budget of 600000 bytes (max_total_bytes)" in errors[0], out
    info = check_valid(bag)
    assert info["message_count"] * 12_000 <= 600_000 < (info["message_count"] + 1) * 12_400
    assert "budget of 600000 bytes" in info["custom_data"][BUDGET_KEY]


@pytest.mark.ros
@pytest.mark.process
@pytest.mark.disk_size("4m")
def test_below_the_free_disk_floor_recording_stops_with_a_valid_bag(ros, small_disk):
    from trainer.nodes.recorder import EXIT_BUDGET

    bag = small_disk.path / "bag"
    rec = recorder(bag, T.topic_name(NS, T.IMAGE), "--min-free-disk", str(3 << 20), "--flush-interval", "0.2")
    try:
        flood_images(ros, rec)
        out, _ = rec.communicate(timeout=60)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == EXIT_BUDGET, out
    assert "below the floor of 3145728 (min_free_disk)" in out and "No space left" not in out, out
    check_valid(bag)


@pytest.mark.ros
@pytest.mark.process
def test_a_diagnostics_flood_is_rate_limited_and_flagged_in_the_bag_and_on_diagnostics(ros, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.executors import SingleThreadedExecutor

    from sim_bridge.contract import qos

    executor = SingleThreadedExecutor(context=ros.context)
    executor.add_node(ros)
    heard: list[str] = []
    ros.create_subscription(DiagnosticArray, T.DIAGNOSTICS,   # the recorder's statuses only
                            lambda m: heard.extend(s.message for s in m.status if s.hardware_id == "recorder"),
                            qos.diagnostics_qos())
    pub = ros.create_publisher(DiagnosticArray, T.DIAGNOSTICS, qos.diagnostics_qos())
    bag = tmp_path / "bag"
    rec = recorder(bag, T.DIAGNOSTICS)   # bounded by default
    try:
        wait_until(lambda: pub.get_subscription_count() >= 2, 60, "the recorder's subscription")

        def send(n: int, pause: float) -> None:
            for i in range(n):
                arr = DiagnosticArray()
                arr.status = [DiagnosticStatus(name=f"stranger {i}", message="x" * 100)]
                pub.publish(arr)
                time.sleep(pause)
                executor.spin_once(timeout_sec=0)

        send(25, 0.2)       # 5 s at 5 Hz: its recent figure
        send(3000, 0.0005)  # then a flood
        deadline = time.monotonic() + 30
        while "flood on /diagnostics" not in heard and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        out = interrupt(rec)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert "flood on /diagnostics" in heard, out   # the recorder's WARN status
    assert rec.returncode == 0, out
    assert "FLOOD" in out, out
    info = check_valid(bag)
    floods = json.loads(info["custom_data"][FLOOD_KEY])
    assert floods[T.DIAGNOSTICS]["rate_hz"] > 100
    dropped = json.loads(info["custom_data"][DROPPED_KEY])[T.DIAGNOSTICS]["rate"]
    assert dropped > 1000 and info["message_count"] < 1000


#: What the default recorder's bag may grow by in the flood test below: its legitimate traffic
#: (about 1.5 MB: 12 kB images at 20 Hz for 6 s, step_info for 9 s) and room for MCAP framing; the
#: floods offer about 250 MB (120 messages of 2 MB), which the recorder wrote whole before
#: issue 54 (a 10 s flood of each grew a bag by about 5.1 GB).
FLOOD_BAG_BOUND = 8 << 20


@pytest.mark.ros
@pytest.mark.process
def test_the_default_recorder_bounds_large_diagnostics_and_image_floods_flags_both_and_keeps_recording(
        ros, tmp_path):
    """The recorder with its defaults only, on the contract's image and step_info and on
    /diagnostics. A stranger sends 2 MB /diagnostics for 3 s, then 2 MB images for 3 s (20 each
    per second, bounded in count), while the bridge's traffic goes on at 20 Hz: the bag grows
    by at most FLOOD_BAG_BOUND, both floods are flagged although neither topic had history, and
    every topic is still recorded after the floods (no flood ends the bag)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from sensor_msgs.msg import Image, JointState

    from sim_bridge.contract import qos

    image_t, info_t = T.topic_name(NS, T.IMAGE), T.topic_name(NS, T.STEP_INFO)
    bag = tmp_path / "bag"
    rec = recorder(bag, image_t, info_t, T.DIAGNOSTICS)
    pub_img = ros.create_publisher(Image, image_t, qos.observation_qos())
    pub_info = ros.create_publisher(JointState, info_t, qos.observation_qos())
    pub_diag = ros.create_publisher(DiagnosticArray, T.DIAGNOSTICS, qos.diagnostics_qos())
    rng = np.random.default_rng(0)   # random bytes: MCAP's zstd cannot shrink them

    def small() -> Image:
        return T.fill_image(Image(), rng.integers(0, 256, (64, 64, 3), dtype=np.uint8), 0)

    big_img = T.fill_image(Image(), rng.integers(0, 256, (836, 836, 3), dtype=np.uint8), 0)   # 2.1 MB
    noise = base64.b64encode(rng.integers(0, 256, 3 << 19, dtype=np.uint8).tobytes()).decode()  # 2 MB
    big_diag = DiagnosticArray(status=[DiagnosticStatus(name="stranger", message=noise)])
    sent = {"info": 0, "image": 0, "flood": 0}
    try:
        wait_until(lambda: min(pub_img.get_subscription_count(), pub_info.get_subscription_count(),
                               pub_diag.get_subscription_count()) >= 1 or rec.poll() is not None,
                   60, "the recorder's subscriptions")
        time.sleep(1.0)   # the recorder's graph poll has subscribed to every topic

        def phase(seconds: float, flood=None, images: bool = True) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                pub_info.publish(JointState(name=["reward"], position=[float(sent["info"])]))
                sent["info"] += 1
                if images:
                    pub_img.publish(small())
                    sent["image"] += 1
                if flood is not None:
                    flood[0].publish(flood[1])
                    sent["flood"] += 1
                time.sleep(0.05)

        phase(1.0)
        phase(3.0, (pub_diag, big_diag))
        phase(3.0, (pub_img, big_img), images=False)
        after = time.time_ns()
        phase(2.0)
        time.sleep(1.0)
        out = interrupt(rec)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == 0, out
    grown = sum(f.stat().st_size for f in bag.rglob("*") if f.is_file())
    print(f"bag grew by {grown} bytes against {sent['flood']} flood messages of 2 MB offered")
    assert grown <= FLOOD_BAG_BOUND, (grown, out[-3000:])
    info = check_valid(bag)
    floods = json.loads(info["custom_data"][FLOOD_KEY])
    assert set(floods) == {T.DIAGNOSTICS, image_t}, floods
    dropped = json.loads(info["custom_data"][DROPPED_KEY])
    assert dropped[T.DIAGNOSTICS]["message_bytes"] >= 40 and dropped[image_t]["message_bytes"] >= 40, dropped
    assert out.count("FLOOD") >= 2, out
    counts, late = {}, {}
    for rec_msg in BagReader(bag, strict=True).messages():
        counts[rec_msg.topic] = counts.get(rec_msg.topic, 0) + 1
        if rec_msg.log_time_ns > after:
            late[rec_msg.topic] = late.get(rec_msg.topic, 0) + 1
    assert counts[info_t] == sent["info"] and counts[image_t] == sent["image"], (counts, sent)
    assert late.get(info_t, 0) >= 20 and late.get(image_t, 0) >= 20, late   # recording went on


@pytest.mark.ros
@pytest.mark.process
def test_zero_turns_a_default_bound_off_with_a_warning(tmp_path):
    rec = recorder(tmp_path / "bag", T.DIAGNOSTICS, "--rate-limit", f"{T.DIAGNOSTICS}=0",
                   "--max-message-bytes", "/protocad/image=0")
    try:
        wait_until(lambda: (tmp_path / "bag").is_dir() or rec.poll() is not None, 60, "the recorder's bag")
        time.sleep(0.5)
        out = interrupt(rec)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == 0, out
    warnings = [x for x in out.splitlines() if "turned off (0): a flood on it is not bounded" in x]
    assert len(warnings) == 2 and "WARN" in warnings[0], out
    assert "/diagnostics: rate limit" in warnings[0] and "/protocad/image: message size limit" in warnings[1], out
