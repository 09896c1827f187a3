"""Helpers of the trainer tests: step sequences with known content, written as rosbag2 MCAP bags
by this project's writer (trainer.bag.writer.BagWriter) or by another tool (the rosbags library).

Every step carries its identity in its data, so tests can check what the dataset made of it:
image[..., 0] = step id % 256, image[..., 1] = episode id, image[..., 2] = 7;
the action answering step s of episode e is [s / 100 + e] (for every action dimension).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from helpers import ROOT
from sim_bridge.contract import topics as T

DT_NS = 40_000_000  # pendulum: control_dt 0.02 s x action repeat 2

# A model small enough for CPU tests (seconds per run, not minutes): config fields set both ways,
# as generated options and as --set overrides.
TINY = ["--world_model.deter", "32", "--world_model.hidden", "32", "--world_model.stoch", "8",
        "--world_model.cnn_depth", "8", "--world_model.mlp_units", "32",
        "--behavior.actor_units", "32", "--behavior.critic_units", "32",
        "--set", "context.num_prototypes=8", "--set", "context.proto_dim=8",
        "--set", "behavior.horizon=5", "--batch-size", "4", "--seq-len", "8", "--threads", "1"]


def answer(step: int, episode: int, dim: int = 1) -> np.ndarray:
    return np.full(dim, step / 100.0 + episode, np.float64)


def make_steps(episodes: int, length: int, *, first_episode: int = 0, t0_ns: int = 0,
               context: dict | None = None, split: str = "train") -> list[dict]:
    """`episodes` episodes of `length` observations each (is_first ... is_last), consecutive
    sim-time stamps, rewards = step id / 10."""
    steps, tick = [], t0_ns // DT_NS
    for e in range(first_episode, first_episode + episodes):
        for s in range(length):
            img = np.zeros((64, 64, 3), np.uint8)
            img[..., 0], img[..., 1], img[..., 2] = s % 256, e % 256, 7
            steps.append(dict(stamp=tick * DT_NS, episode=e, step=s, is_first=s == 0,
                              is_last=s == length - 1, reward=0.0 if s == 0 else s / 10.0,
                              image=img, action=answer(s, e), context=dict(context or {"m": 1.0}),
                              split=split))
            tick += 1
    return steps


COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"


def fill_jpeg(msg, image: np.ndarray, stamp: int, quality: int = 90):
    """A camera's compressed transport: a sensor_msgs/CompressedImage of `image` as JPEG."""
    from sim_bridge.contract import camera

    T.set_stamp(msg.header.stamp, stamp)
    msg.header.frame_id = T.IMAGE_FRAME_ID
    msg.format = "jpeg"
    data = camera.encode_compressed(image, "jpeg", quality)
    msg.data = np.frombuffer(data, np.uint8) if isinstance(msg.data, np.ndarray) else data
    return msg


def write_bag(bag_dir: Path, steps: list[dict], *, namespace: str = "/protocad", chunk_size: int = 1 << 20,
              extra_topics: dict[str, int] | None = None, duplicate_stamps: set[int] | None = None,
              compression: str = "zstd", image_type: str = T.TYPES[T.IMAGE], fill_image=T.fill_image,
              image_topic: str = T.IMAGE) -> Path:
    """The ROS path's layout with trainer.bag.writer.BagWriter. A step without 'action' (None) is
    left unanswered; stamps in duplicate_stamps are written twice (image + step_info);
    extra_topics {topic: count} adds std_msgs/String messages on foreign topics. A camera's
    frames: image_type COMPRESSED_IMAGE with fill_image=fill_jpeg, on image_topic
    (e.g. image/compressed)."""
    from trainer.bag.rosmsg import new_message
    from trainer.bag.writer import BagWriter

    names = {k: T.topic_name(namespace, k) for k in (T.IMAGE, T.STEP_INFO, T.CONTEXT, T.ACTION)}
    names[T.IMAGE] = T.topic_name(namespace, image_topic)
    types = {**T.TYPES, T.IMAGE: image_type}
    with BagWriter(bag_dir, chunk_size=chunk_size, compression=compression) as w:
        for rel, topic in names.items():
            w.add_topic(topic, types[rel])
        for t in extra_topics or {}:
            w.add_topic(t, "std_msgs/msg/String")
        new = new_message
        for st in steps:
            s = st["stamp"]
            reps = 2 if duplicate_stamps and s in duplicate_stamps else 1
            for _ in range(reps):
                w.write_message(names[T.CONTEXT], T.fill_context(new(T.TYPES[T.CONTEXT]), st["context"],
                                                                 st["split"], s), s + 1)
                w.write_message(names[T.STEP_INFO], T.fill_step_info(new(T.TYPES[T.STEP_INFO]), T.StepInfo(
                    st["reward"], 1.0, st["is_first"], st["is_last"], False, st["episode"], st["step"]), s), s + 2)
                w.write_message(names[T.IMAGE], fill_image(new(image_type), st["image"], s), s + 3)
            if st.get("action") is not None:
                w.write_message(names[T.ACTION], T.fill_action(new(T.TYPES[T.ACTION]), st["action"],
                                                               [f"a{i}" for i in range(len(st["action"]))], s), s + 4)
        for t, n in (extra_topics or {}).items():
            for i in range(n):
                msg = new("std_msgs/msg/String")
                msg.data = f"foreign {i}"
                w.write_message(t, msg, 10 + i)
    return bag_dir


def write_rosbags_bag(bag_dir: Path, steps: list[dict], topics: dict[str, str], *,
                      image_type: str = T.TYPES[T.IMAGE], fill_image=T.fill_image) -> Path:
    """The same content written by ANOTHER tool: the rosbags library (rosbag2 MCAP storage,
    its own CDR serializer and message definitions), under the topic names in `topics`
    {'image': '/robot/camera', 'step_info': ..., 'action': ..., 'context': ...}; a camera's
    JPEG frames with image_type COMPRESSED_IMAGE, fill_image=fill_jpeg."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    Image, JointState = ts.types[image_type], ts.types["sensor_msgs/msg/JointState"]
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]

    def header():
        return Header(stamp=Time(sec=0, nanosec=0), frame_id="")

    def js():
        e = np.zeros(0, np.float64)
        return JointState(header=header(), name=[], position=e, velocity=e, effort=e)

    with Writer(bag_dir, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {k: w.add_connection(t, image_type if k == "image" else "sensor_msgs/msg/JointState",
                                     typestore=ts) for k, t in topics.items()}
        for st in steps:
            s = st["stamp"]
            if "context" in conns:
                w.write(conns["context"], s + 1, ts.serialize_cdr(
                    T.fill_context(js(), st["context"], st["split"], s), "sensor_msgs/msg/JointState"))
            w.write(conns["step_info"], s + 2, ts.serialize_cdr(T.fill_step_info(js(), T.StepInfo(
                st["reward"], 1.0, st["is_first"], st["is_last"], False, st["episode"], st["step"]), s),
                "sensor_msgs/msg/JointState"))
            img = (Image(header=header(), format="", data=np.zeros(0, np.uint8)) if image_type == COMPRESSED_IMAGE
                   else Image(header=header(), height=0, width=0, encoding="", is_bigendian=0, step=0,
                              data=np.zeros(0, np.uint8)))
            w.write(conns["image"], s + 3, ts.serialize_cdr(fill_image(img, st["image"], s), image_type))
            if st.get("action") is not None:
                w.write(conns["action"], s + 4, ts.serialize_cdr(
                    T.fill_action(js(), st["action"], ["torque"], s), "sensor_msgs/msg/JointState"))
    return bag_dir


def run_cli(module: str, *args: str, timeout: float = 240, env: dict | None = None):
    """Run `python -m module args` to completion; returns the CompletedProcess (text)."""
    return subprocess.run([sys.executable, "-m", module, *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT,
                          env={**os.environ, **(env or {})})


def loop_failure(r, run: Path) -> str:
    """What to show when a protocad-loop run failed: its output and every node log's tail."""
    return r.stdout + r.stderr + "".join(
        f"\n--- {p.name}\n" + p.read_text()[-3000:] for p in sorted((run / "logs").glob("*.log")))


def check_robot_episodes(bag: Path, namespaces: list[str], episode_length: int) -> None:
    """One episode of each robot in `bag`, under the robot's namespace with its own clock, and
    nothing under the shared namespace."""
    from trainer.bag.reader import BagReader

    reader = BagReader(bag)
    topics = reader.report.counts
    for ns in namespaces:
        # one episode of L steps = L+1 observations; count distinct stamps, as a lock-step
        # timeout may republish one
        stamps = {reader.decode(m).header.stamp.nanosec + 10**9 * reader.decode(m).header.stamp.sec
                  for m in reader.messages([f"{ns}/step_info"])}
        assert len(stamps) == episode_length + 1 and topics.get(f"{ns}/action", 0) >= episode_length + 1, topics
        assert topics.get(f"{ns}/clock", 0) >= episode_length + 1, topics    # each robot's own sim clock
    assert "/protocad/step_info" not in topics


def check_robots_recorded_and_trained(run: Path, namespaces: list[str], *, episode_length: int,
                                      phases: list[tuple[str, int]], episodes: int, updates: int,
                                      cache_dir: Path) -> None:
    """A multi-robot protocad-loop run: every robot's episodes are in every bag under its own
    namespace (with its own clock), nothing under the shared one, each robot's episodes give
    training windows, and the checkpoint counted them all."""
    import json

    from trainer.data.dataset import MCAPDataset, TopicMap

    got = json.loads((run / "phases.json").read_text())
    assert [(p["bag"], p["episodes"]) for p in got] == phases
    for p in got:
        check_robot_episodes(run / "bags" / p["bag"], namespaces, episode_length)
    for ns in namespaces:
        ds = MCAPDataset([run / "bags"], topics=TopicMap.for_namespace(ns), seq_len=4, cache_dir=cache_dir)
        assert len(ds.report.sources) == len(phases) and ds.num_windows > 0, ns    # this robot's episodes train
    from protocad_ros.checkpoint.agent_file import read_checkpoint

    ck = read_checkpoint(run / "checkpoints" / "latest.pt")
    assert ck["counters"]["episodes"] == episodes and int(ck["modules"]["updates"]) == updates


RERUN = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")


def rerun_check(path: Path) -> subprocess.CompletedProcess:
    """`rerun mcap check` on one MCAP file: an independent reader's verdict."""
    assert RERUN, "rerun CLI (rerun-sdk) not found next to the Python interpreter"
    return subprocess.run([RERUN, "mcap", "check", str(path)], capture_output=True, text=True,
                          timeout=60)
