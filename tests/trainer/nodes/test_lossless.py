"""Collection under a stalled recorder (SIGSTOP), through real processes: the bridge, a
responder in this process standing in for the policy, and trainer.nodes.recorder.

Lock-step: the bridge's observation writers keep every sample a reliable reader has not
acknowledged (lossless, KEEP_ALL) and the recorder's readers refuse, rather than drop, what they
have no room for (KEEP_ALL), so a frozen recorder gets the backlog once it runs again and every
published message is in the bag. Real time: the bridge cannot wait (the clock runs), so steps are lost, and the
recorder counts exactly what the bag lacks, which the dataset report names.
"""
from __future__ import annotations

import json
import re
import signal
import time

import pytest
import yaml
from helpers import wait_until
from helpers.ros import Probe, Responder

from sim_bridge.bridge.params import LOSSLESS_FLUSH_TIMEOUT_S
from sim_bridge.contract import topics as T
from sim_bridge.nodekit.rosnode import SHUTDOWN_BUDGET_S, flush_publishers
from trainer.bag.reader import BagReader

pytestmark = [pytest.mark.ros, pytest.mark.process]

TASK, NS = "pendulum_swingup", T.DEFAULT_NAMESPACE
START = 90.0


def bag_stamps(bag, rel: str) -> list[int]:
    reader = BagReader(bag)
    return [T.stamp_to_ns(reader.decode(m).header.stamp) for m in reader.messages([T.topic_name(NS, rel)])]


def start(spawn, tmp_path, mode: list[str]):
    probe = Probe("lossless_probe")
    resp = Responder(probe, lambda info: [0.0], names=["torque"])
    bag = tmp_path / "bag"
    rec = spawn("recorder", "-m", "trainer.nodes.recorder", "-o", str(bag), T.topic_name(NS, T.STEP_INFO),
                T.topic_name(NS, T.IMAGE), T.topic_name(NS, T.ACTION))
    wait_until(lambda: "recording to" in rec.output(), START, "the recorder")
    bridge = spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}", "-p", "seed:=1",
                   "-p", "min_subscribers:=2", "-p", "diagnostics_period_s:=0.2", *mode)
    return probe, resp, bag, rec, bridge


def clock_stamps(bag) -> list[int]:
    reader = BagReader(bag)
    return [T.stamp_to_ns(reader.decode(m).clock) for m in reader.messages([T.CLOCK])]


#: Steps the bridge takes while the recorder is frozen: more than the 1000 samples per topic
#: that the recorder's old KEEP_LAST(1000) readers could hold (what they lost on waking).
FROZEN_STEPS = 1100
#: Longer than Fast DDS's default participant lease (20 s), after which the writers used to drop
#: the frozen recorder with its whole backlog (a loaded machine froze it that long when asked
#: for 6 s and 1,100 steps); the recorder now announces a longer lease (--lease-duration).
FROZEN_S = 25.0
#: The lossless bridge's own close budget (flush wait + shutdown), and slack for a loaded machine.
BRIDGE_CLOSE_S = LOSSLESS_FLUSH_TIMEOUT_S + SHUTDOWN_BUDGET_S + 10.0


def test_lockstep_recorder_frozen_25s_records_every_message_of_every_topic(spawn, tmp_path):
    """The recorder (default topics, KEEP_ALL readers) frozen for at least 25 s and 1,100 steps
    of a lock-step bridge (beyond DDS's default lease; at more than 200 steps/s also past the
    5,000 samples a writer holds, so the bridge waits for it): afterwards every image, step_info, context and /clock message the
    bridge published is in the bag exactly once, every action too, and nothing counted lost."""
    probe = Probe("frozen_probe")
    resp = Responder(probe, lambda info: [0.0], names=["torque"])
    bag = tmp_path / "bag"
    rec = spawn("recorder", "-m", "trainer.nodes.recorder", "-o", str(bag))
    wait_until(lambda: "recording to" in rec.output(), START, "the recorder")
    bridge = spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}", "-p", "seed:=2",
                   "-p", "min_subscribers:=2", "-p", "episode_length:=400")
    try:
        wait_until(lambda: len(resp.steps) >= 40, START, "40 lock-step steps")
        rec.p.send_signal(signal.SIGSTOP)
        frozen_at, t_frozen = len(resp.steps), time.monotonic()
        wait_until(lambda: len(resp.steps) >= frozen_at + FROZEN_STEPS and time.monotonic() - t_frozen >= FROZEN_S,
                 240, f"{FROZEN_STEPS} steps and {FROZEN_S} s while the recorder is frozen")
        rec.p.send_signal(signal.SIGCONT)
        resumed_at = len(resp.steps)
        # The woken recorder first drains thousands of samples per topic: with a full suite
        # beside other work on 2 cores that took over 120 s once (alone: 42 s for the test).
        wait_until(lambda: len(resp.steps) >= resumed_at + 100, 300, "100 more steps")
        # SIGINT: the bridge waits for every reader's acks (the woken recorder's whole backlog),
        # so it is given the close budget it grants itself, not a default stop timeout.
        assert bridge.stop(timeout=BRIDGE_CLOSE_S) == 0, bridge.output()[-2000:] + rec.output()[-2000:]
        assert flush_publishers([resp.pub], 30.0) == []
        assert rec.stop() == 0, rec.output()[-2000:]
    finally:
        rec.p.send_signal(signal.SIGCONT)                     # never leave it stopped
        probe.close()
    out = bridge.output()
    published = int(re.search(r"observations_published=(\d+)", out).group(1))
    repeats = re.search(r"observations_republished=(\d+)", out)
    repeats = int(repeats.group(1)) if repeats else 0
    dt = resp.steps[1][0] - resp.steps[0][0]
    expected = [i * dt for i in range(published)]
    for rel in (T.IMAGE, T.STEP_INFO, T.CONTEXT):
        stamps = bag_stamps(bag, rel)
        assert sorted(set(stamps)) == expected and len(stamps) == published + repeats, \
            (rel, len(stamps), published, repeats, rec.output()[-3000:], out[-3000:])
    clock = clock_stamps(bag)
    assert sorted(set(clock)) == expected and len(clock) == published + repeats, (len(clock), published)
    assert set(bag_stamps(bag, T.ACTION)) == set(resp.answered)
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    lost = json.loads((info.get("custom_data") or {}).get("protocad_lost_messages", "{}"))
    assert not any(lost.values()), lost
    assert "LOST" not in rec.output(), rec.output()[-2000:]


def test_realtime_loss_is_counted_exactly_and_named_by_the_dataset(spawn, tmp_path):
    from trainer.data.dataset import MCAPDataset

    probe, resp, bag, rec, bridge = start(spawn, tmp_path, ["-p", "mode:=realtime", "-p", "control_rate_hz:=100.0"])
    try:
        wait_until(lambda: len(resp.steps) >= 100, START, "100 real-time steps")
        rec.p.send_signal(signal.SIGSTOP)
        n0 = len(resp.steps)
        wait_until(lambda: len(resp.steps) >= n0 + 300, 60, "300 steps while the recorder is frozen")
        rec.p.send_signal(signal.SIGCONT)
        n1 = len(resp.steps)
        wait_until(lambda: len(resp.steps) >= n1 + 100, 60, "100 more steps")
        assert bridge.stop() == 0
        time.sleep(1.0)                     # the last samples in flight reach the recorder
        out_code = rec.stop()
    finally:
        probe.close()
    assert out_code == 0, rec.output()[-2000:]
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    lost = json.loads(info["custom_data"]["protocad_lost_messages"])
    topic = T.topic_name(NS, T.STEP_INFO)
    recorded = bag_stamps(bag, T.STEP_INFO)
    # What the bridge published (its own count at exit: the responder may miss the very last
    # one, sent as the bridge stopped); real-time stamps advance by one control_dt per step.
    published = int(re.search(r"observations_published=(\d+)", bridge.output()).group(1))
    dt = resp.steps[1][0] - resp.steps[0][0]
    assert set(recorded) <= {i * dt for i in range(published)} and len(set(recorded)) == len(recorded)
    assert lost[topic] > 0 and len(recorded) + lost[topic] == published, \
        (len(recorded), lost, published, bridge.output()[-1500:])
    report = MCAPDataset([bag], seq_len=4, cache_dir=tmp_path / "cache").report.summary()
    assert "the recorder reported lost messages" in report and str(lost[topic]) in report


def test_a_lockstep_recording_stopped_by_a_full_disk_is_in_time_order_and_read_by_rosbags(spawn, small_disk):
    """The recorder's default topics from a lock-step bridge into a 1.5 MB tmpfs: the recorder
    stops by itself (disk full) and its cut file, without an index, is read by rosbags, whose
    streaming reader needs log times that never go back (reception times of different topics
    come from different DDS readers and used to interleave out of order)."""
    from mcap.records import Message
    from mcap.stream_reader import StreamReader
    from rosbags.rosbag2 import Reader

    from trainer.nodes.recorder import EXIT_WRITE_FAILED

    disk = small_disk.path
    probe = Probe("fulldisk_probe")
    Responder(probe, lambda info: [0.0], names=["torque"])
    bag = disk / "bag"
    rec = spawn("recorder", "-m", "trainer.nodes.recorder", "-o", str(bag), "--compression", "none",
                "--ros-args", "-p", "flush_interval:=0.2", "-p", "min_free_disk:=0")   # the write failure, not the floor
    wait_until(lambda: "recording to" in rec.output(), START, "the recorder")
    spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}", "-p", "seed:=1",
          "-p", "min_subscribers:=2")
    wait_until(lambda: not rec.alive(), 120, "the recorder to stop on the full disk")
    assert rec.p.returncode == EXIT_WRITE_FAILED, rec.output()[-2000:]
    (mcap,) = bag.glob("*.mcap")
    with open(mcap, "rb") as f:
        times = [r.log_time for r in StreamReader(f, emit_chunks=False).records if isinstance(r, Message)]
    assert len(times) > 100 and times == sorted(times)
    with Reader(bag) as reader:
        assert sum(1 for _ in reader.messages()) == reader.message_count == len(times)
    probe.close()
