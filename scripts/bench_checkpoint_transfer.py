#!/usr/bin/env python3
"""How long a new checkpoint version takes to cross ROS: learner file -> policy side.

The checkpoint publisher node runs in its own process on a learner file; this process holds an
rclpy node with the policy's receiver (protocad_ros.node.checkpoint_receiver). For each preset and
chunk size, the learner file is rewritten (save_checkpoint, a new version each time) and timed:

  announce   file in place -> announcement received here (the publisher's poll, read, format
             check and publish included; poll_s 0.02)
  complete   file in place -> every chunk received here
  verify     size + sha256 of the received bytes
  install    written beside the local file, loaded (load_checkpoint), moved into place

    python scripts/bench_checkpoint_transfer.py                 # shared memory (one machine)
    python scripts/bench_checkpoint_transfer.py --udp           # UDP over loopback (no SHM)
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch

# Measure the working tree this script belongs to, not an installed copy of the packages.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocad_ros.atomic import atomic_open
from protocad_ros.checkpoint.agent_file import load_checkpoint, save_checkpoint
from protocad_ros.model.agent import Agent
from protocad_ros.model.config import make_config
from protocad_ros.model.precision import cpu_capability
from sim_bridge.contract.contexts import task_actuators

ROOT = Path(__file__).resolve().parents[1]


def parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["small", "paper"])
    ap.add_argument("--task", default="pendulum_swingup")
    ap.add_argument("--chunk-sizes", nargs="+", type=int, default=[256 << 10, 1 << 20, 4 << 20])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--udp", action="store_true",
                    help="Fast DDS with UDPv4 only (FASTDDS_BUILTIN_TRANSPORTS), as between machines")
    return ap.parse_args()


ARGS = parse()
# DDS on this machine only, in a domain of our own (before rclpy is imported, in main).
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
if ARGS.udp:
    os.environ["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"


def main() -> None:
    # rclpy, and the receiver that loads it, after the DDS environment above
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from protocad_ros.node.checkpoint_receiver import CheckpointReceiver, install

    torch.set_num_threads(1)
    rclpy.init()
    node = Node("bench_checkpoint_receiver", namespace="/protocad")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    times: dict[str, float] = {}
    done = threading.Event()

    class Timed(CheckpointReceiver):
        def _on_announcement(self, msg):
            times.setdefault("announce", time.monotonic())
            super()._on_announcement(msg)

    def wake():
        times["complete"] = time.monotonic()
        done.set()

    rejects: list[str] = []
    def count(key: str, why: str | None = None) -> None:
        if key == CheckpointReceiver.REJECTED:   # not the chunks a late start drops and re-reads
            rejects.append(why)

    receiver = Timed(node, "checkpoint", timeout_s=120.0, wake=wake, next_sha=lambda: None,
                     serving=lambda: "", count=count)
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.machine())
    print(f"machine: {cpu}, {os.cpu_count()} cores, CPU capability {cpu_capability()}; "
          f"transport: {'UDPv4 over loopback' if ARGS.udp else 'Fast DDS default (shared memory)'}")
    print(f"{'preset':7} {'MB':>6} {'chunk':>7} {'n':>4} {'announce ms':>12} {'complete ms':>12} "
          f"{'MB/s':>7} {'verify ms':>10} {'install ms':>11}")
    with tempfile.TemporaryDirectory() as tmp:
        for preset in ARGS.presets:
            adim = len(task_actuators(ARGS.task))
            agent = Agent(make_config(ARGS.task, preset, **{"train.batch_size": 2, "train.seq_len": 8}), adim)
            # One update first, so the file carries the Adam states a trainer's checkpoint has
            # (a fresh agent's file is a third of that size).
            rng = np.random.default_rng(0)
            agent.train_step({"image": rng.integers(0, 256, (2, 8, 64, 64, 3), dtype=np.uint8),
                              "action": np.zeros((2, 8, adim), np.float32),
                              "reward": np.zeros((2, 8), np.float32), "is_first": np.zeros((2, 8), bool)})
            learner = Path(tmp) / preset / "agent.pt"
            save_checkpoint(learner, agent)
            for chunk in ARGS.chunk_sizes:
                pub = subprocess.Popen([sys.executable, "-m", "trainer.nodes.checkpoint_publisher", "--ros-args",
                                        "-p", f"checkpoint:={learner}", "-p", f"chunk_size:={chunk}",
                                        "-p", "poll_s:=0.02"], stdout=subprocess.DEVNULL,
                                       stderr=subprocess.STDOUT, cwd=ROOT)
                try:
                    done.wait(120)   # its first version: start-up, not measured
                    rows = []
                    for i in range(ARGS.repeats):
                        done.clear()
                        times.clear()
                        agent.updates.fill_(i + 1)   # new bytes: a new version
                        scratch = save_checkpoint(Path(tmp) / "scratch" / "agent.pt", agent).read_bytes()
                        t0 = time.monotonic()         # the trainer's write, as save_checkpoint's
                        with atomic_open(learner, "wb") as f:
                            f.write(scratch)
                        if not done.wait(120):
                            raise SystemExit(f"no transfer within 120 s (rejected: {rejects})")
                        with receiver._lock:
                            transfer, receiver._received = receiver._received, None
                        t1 = time.monotonic()
                        data = transfer.verify()
                        t2 = time.monotonic()
                        install(data, Path(tmp) / "robot" / "agent.pt",   # as a policy node loads it
                                lambda name, raw: load_checkpoint(name, restore_rng=False, optimizer_states=False, data=raw))
                        t3 = time.monotonic()
                        rows.append((times["announce"] - t0, times["complete"] - t0, t2 - t1, t3 - t2))
                finally:
                    pub.terminate()
                    pub.wait(30)
                a, c, v, ins = (float(np.median([r[k] for r in rows])) for k in range(4))
                size = len(data) / 1e6
                print(f"{preset:7} {size:6.1f} {chunk >> 10:6d}K {transfer.announcement.n_chunks:4d} "
                      f"{a * 1e3:12.0f} {c * 1e3:12.0f} {size / c:7.0f} {v * 1e3:10.0f} "
                      f"{ins * 1e3:11.0f}")
    print(f"medians of {ARGS.repeats} versions each; rejected transfers: {len(rejects)}")
    receiver.destroy()
    executor.shutdown()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
