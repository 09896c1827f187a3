"""The recorder's disk is a budget: per-topic rate limits and byte budgets drop (and count) a
flood's messages, the bag's byte budget and the free-disk floor end the recording with a closed,
valid bag and one line (exit 4), and a topic jumping far above its recent rate is flagged in the
bag's metadata and on /diagnostics. The budget's logic is tested on its own too."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
from helpers import wait_until

from sim_bridge.contract import topics as T
from trainer.bag import mcap_io as M
from trainer.launch.rosprocs import recorder_budget_args
from trainer.nodes.record_budget import (
    BUDGET_KEY,
    DROPPED_KEY,
    FLOOD_KEY,
    BudgetLimits,
    DiskFloor,
    RecordBudget,
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


def test_the_launchers_record_a_bounded_copy_of_diagnostics():
    args = recorder_budget_args(["/protocad/image", T.DIAGNOSTICS])
    assert args[:2] == ["--rate-limit", f"{T.DIAGNOSTICS}=20"] and args[2] == "--byte-budget"
    assert recorder_budget_args(["/protocad/image"]) == []


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
    r = M.BagReader(bag, strict=True)
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
    rec = recorder(bag, T.DIAGNOSTICS, *recorder_budget_args([T.DIAGNOSTICS]))
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
        rec.send_signal(signal.SIGINT)
        out, _ = rec.communicate(timeout=60)
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
