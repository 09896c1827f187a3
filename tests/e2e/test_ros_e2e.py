"""End to end: sim bridge, policy and recorder as three separate processes over DDS.

Several lock-step episodes with randomized contexts; the MCAP bag must hold every published
step exactly once, answered by exactly one action, with equal counts and (episode, step) ids
on every topic; `rerun mcap check` accepts the file and the `mcap` library (mcap_ros2 decoder)
reads it back with the right types.
"""
from __future__ import annotations

import collections
import re
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import wait_exit, wait_until
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from sim_bridge.contract import topics

pytestmark = [pytest.mark.ros, pytest.mark.process]

TASK = "pendulum_swingup"
EPISODES, LENGTH = 4, 15
START = 120.0
NS = topics.DEFAULT_NAMESPACE
TYPES = {topics.topic_name(NS, rel): t for rel, t in topics.TYPES.items()
         if rel not in (topics.DIAGNOSTICS,)}


def final_counters(log: str) -> dict[str, int]:
    line = [ln for ln in log.splitlines() if "stopped:" in ln][-1]
    return {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", line)}


def test_three_nodes_lockstep_episodes_recorded_exactly_once(spawn, tmp_path):
    bag = tmp_path / "e2e_bag"
    rec = spawn("recorder", "-m", "trainer.nodes.recorder", "-o", str(bag))
    policy = spawn("policy", "-m", "protocad_ros.node.policy_node", "--ros-args",
                   "-p", f"task:={TASK}", "-p", "preset:=small", "-p", "num_threads:=1")
    # The recorder subscribes when it sees a publisher; wait until it follows the policy's
    # topics, then start the bridge, which waits for 2 readers (policy + recorder).
    for topic in ("action", "context_features"):
        wait_until(lambda: f"subscribed to {NS}/{topic}" in rec.output(), START,
                   f"the recorder to subscribe to {topic}", interval=0.1)
    bridge = spawn("bridge", "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}",
                   "-p", "seed:=11", "-p", f"episode_length:={LENGTH}",
                   "-p", f"max_episodes:={EPISODES}", "-p", "min_subscribers:=2",
                   "-p", "lockstep_timeout_s:=30.0")
    assert wait_exit(bridge, START) == 0, bridge.output()
    assert rec.stop() == 0
    assert policy.stop() == 0
    logs = {p: p.log_path.read_text() for p in (rec, policy, bridge)}
    assert not any("Traceback" in text for text in logs.values()), logs
    bc = final_counters(logs[bridge])
    pc = final_counters(logs[policy])
    n = (LENGTH + 1) * EPISODES
    assert bc["observations_published"] == bc["actions_accepted"] == n, bc
    assert bc.get("observations_republished", 0) == 0 and bc.get("actions_rejected", 0) == 0
    assert pc["observations_answered"] == n and pc["episodes"] == EPISODES, pc

    # ---- the bag, read with the mcap library and the mcap_ros2 decoder
    files = sorted(bag.glob("*.mcap"))
    assert files and (bag / "metadata.yaml").is_file()
    msgs: dict[str, list] = collections.defaultdict(list)
    schemas: dict[str, str] = {}
    for path in files:
        with open(path, "rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            assert reader.get_header().profile == "ros2"
            for schema, channel, message, decoded in reader.iter_decoded_messages():
                schemas[channel.topic] = schema.name
                assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
                msgs[channel.topic].append(decoded)
    for topic, msgtype in TYPES.items():
        assert schemas.get(topic) == msgtype, (topic, schemas)

    def stamps(topic: str) -> list[int]:
        return [topics.stamp_to_ns(m.header.stamp) for m in msgs[f"{NS}/{topic}"]]

    obs = stamps("image")
    assert len(obs) == n and len(set(obs)) == n                       # recorded exactly once
    for topic in ("step_info", "context", "action", "context_features"):
        assert sorted(stamps(topic)) == sorted(obs), topic             # same steps, no dupes
    infos = [topics.read_step_info(m) for m in msgs[f"{NS}/step_info"]]
    ids = [(i.episode, i.step) for i in infos]
    assert sorted(ids) == [(e, t) for e in range(EPISODES) for t in range(LENGTH + 1)]
    assert sum(i.is_first for i in infos) == sum(i.is_last for i in infos) == EPISODES
    for img in msgs[f"{NS}/image"]:
        assert (img.encoding, img.height, img.width, img.step, len(img.data)) == (
            "rgb8", 64, 64, 192, 64 * 64 * 3)
        assert img.header.frame_id == topics.IMAGE_FRAME_ID
    for act in msgs[f"{NS}/action"]:
        assert list(act.name) == ["torque"] and len(act.effort) == 1
        assert -1.0 <= act.effort[0] <= 1.0
    # Randomized contexts: one per episode (constant within it), not all the same.
    by_stamp = {topics.stamp_to_ns(m.header.stamp): topics.read_context(m)
                for m in msgs[f"{NS}/context"]}
    per_episode = collections.defaultdict(set)
    for stamp, info in zip(stamps("step_info"), infos):
        ctx, split = by_stamp[stamp]
        assert split == "train"
        per_episode[info.episode].add(tuple(sorted(ctx.items())))
    assert all(len(v) == 1 for v in per_episode.values())
    assert len({next(iter(v)) for v in per_episode.values()}) >= 2
    clock = {topics.stamp_to_ns(m.clock) for m in msgs["/clock"]}
    assert set(obs) <= clock

    # ---- rerun's own MCAP checker
    for path in files:
        res = subprocess.run([str(Path(sys.executable).parent / "rerun"), "mcap", "check", "--full",
                              str(path)], capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stdout + res.stderr
