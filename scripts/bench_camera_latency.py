#!/usr/bin/env python3
"""Observation-to-action latency of the policy node for a camera's frames (issue 53).

A real policy node process serves the shipped walker policy (deterministic); this process
publishes frames to it one at a time over DDS (localhost, a domain of its own) and times each
from the image's publish to the arrival of the action stamped like it. Three cases, one node
process each, in turn, on the same frames (walker renders at 480x640, encoded before timing:
the camera's own encoding is not counted):

1. native   64x64 rgb8 (the frame as the sim bridge renders it: center crop, area resize) with
            step_info, paired by stamp: the sim bridge's contract
2. bgr8     480x640 bgr8 with step_info (the node crops, resizes and reorders the channels)
3. jpeg     480x640 JPEG (quality 90) as sensor_msgs/CompressedImage on image/compressed
            (image_transport:=compressed) with step_info (the node decodes it first)

Each row: the round trip p50/p99 seen here, and the node's own latency (its callback for the
completing message -> action published: decode, resize, model) and model time (Policy.act) from
its /diagnostics, p50/p99.

With --best-effort the images go out as a camera driver sends them (sensor data QoS: best
effort) and the node takes them so (its qos_overrides parameter), one every --period-s; a frame
whose answer has not come within a second counts as lost, and the figures are over those
answered.

    python scripts/bench_camera_latency.py                 # 300 frames per case
    python scripts/bench_camera_latency.py --frames 100 --num-threads 2
    python scripts/bench_camera_latency.py --best-effort --frames 50
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# Measure the working tree this script belongs to, not an installed copy; its tests' helpers too.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from helpers import Proc, wait_until
from helpers.camera_frames import CameraFeeder, compressed_msg, raw_msg, walker_frames
from helpers.ros import Probe
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image

from protocad_ros.model.precision import cpu_capability
from protocad_ros.policy import shipped_policy
from sim_bridge.contract import camera, topics
from trainer.launch.rosprocs import ros_env

CASES = ("native", "bgr8", "jpeg")


def parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n".join(__doc__.split("\n")[2:]))
    ap.add_argument("--frames", type=int, default=300, help="timed frames per case (default 300)")
    ap.add_argument("--warmup", type=int, default=20, help="frames sent first, not timed (default 20)")
    ap.add_argument("--distinct", type=int, default=50, help="distinct walker frames rendered and "
                    "cycled through (default 50)")
    ap.add_argument("--num-threads", type=int, default=1, help="the node's torch threads (default 1)")
    ap.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    ap.add_argument("--best-effort", action="store_true", help="images best effort, as camera drivers "
                    "publish them (lost frames counted)")
    ap.add_argument("--period-s", type=float, default=0.1, help="with --best-effort: seconds between "
                    "frames (default 0.1)")
    return ap.parse_args()


def messages(case: str, frames: list[np.ndarray], stamps: list[int]) -> list:
    out = []
    for i, stamp in enumerate(stamps):
        frame = frames[i % len(frames)]
        if case == "native":
            out.append(topics.fill_image(Image(), camera.resize(frame, 64), stamp))
        elif case == "bgr8":
            out.append(raw_msg(frame, "bgr8", stamp))
        else:
            out.append(compressed_msg(frame, "jpeg", stamp, quality=90))
    return out


def run_case(case: str, args, frames: list[np.ndarray], logs: Path) -> dict:
    ns = f"/bench_{case}"
    image_topic = f"{ns}/image" + ("/compressed" if case == "jpeg" else "")
    qos_args = ["-p", f"qos_overrides.{image_topic}.subscription.reliability:=best_effort"] if args.best_effort else []
    node = Proc([sys.executable, "-m", "protocad_ros.node.policy_node", "--ros-args",
                 "-p", f"checkpoint:={shipped_policy('walker_walk')}", "-p", "mode:=deterministic",
                 "-p", f"num_threads:={args.num_threads}", "-p", "diagnostics_period_s:=0.2",
                 "-p", f"image_transport:={'compressed' if case == 'jpeg' else 'raw'}", *qos_args,
                 "-r", f"__ns:={ns}"], logs / f"{case}.log")
    probe = Probe(f"bench_camera_{case}", namespace=ns)
    try:
        feeder = CameraFeeder(probe, ns, compressed=case == "jpeg")
        if args.best_effort:
            feeder.pub_image = probe.publisher(image_topic, type(messages(case, frames[:1], [0])[0]),
                                               qos_profile_sensor_data)
        wait_until(feeder.ready, 300, f"the {case} policy node to match")
        n = args.warmup + args.frames
        stamps = [1_000_000_000 + 20_000_000 * i for i in range(n)]
        msgs = messages(case, frames, stamps)
        sent: dict[int, float] = {}
        for i, (stamp, msg) in enumerate(zip(stamps, msgs)):
            sent[stamp] = feeder.send(msg, step=i)
            if args.best_effort:
                deadline = sent[stamp] + 1.0
                while stamp not in feeder.arrived and time.monotonic() < deadline:
                    time.sleep(0.0005)
                time.sleep(max(0.0, sent[stamp] + args.period_s - time.monotonic()))
            else:
                wait_until(lambda s=stamp: s in feeder.arrived, 60, f"the answer to frame {i}", 0.0005)
        timed = [s for s in stamps[args.warmup:] if s in feeder.arrived]
        if not timed:
            raise SystemExit(f"{case}: none of the timed frames was answered")
        rtt = np.array([feeder.arrived[s] - sent[s] for s in timed]) * 1e3
        name = f"{ns}/policy"
        answered = str(len(feeder.arrived))
        wait_until(lambda: probe.node_diag(name).get("observations_answered") == answered, 30, "its diagnostics")
        d = probe.node_diag(name)
        if not node.alive() or d.get("images_rejected") != "0":
            raise SystemExit(f"{case}: the node died or rejected images; see {node.log_path}")
        size = sum(len(m.data) for m in msgs) / len(msgs)
        return {"case": case, "bytes": size, "answered": f"{len(timed)}/{args.frames}", "p50": float(np.percentile(rtt, 50)),
                "p99": float(np.percentile(rtt, 99)),
                "node": (float(d["latency_ms_p50"]), float(d["latency_ms_p99"])),
                "act": (float(d["act_ms_p50"]), float(d["act_ms_p99"]))}
    finally:
        probe.close()
        node.stop()


def main() -> None:
    args = parse()
    if shipped_policy("walker_walk") is None:
        raise SystemExit("the package ships no walker_walk policy")
    # DDS on this machine only, in a free domain of our own (before the probe's rclpy.init): the
    # launchers' node environment, which the node process inherits.
    os.environ.update(ros_env(int(os.environ["ROS_DOMAIN_ID"]) if "ROS_DOMAIN_ID" in os.environ else None))
    frames = walker_frames(args.distinct)
    t0 = time.perf_counter()
    for f in frames:
        camera.encode_compressed(f, "jpeg", 90)
    encode_ms = (time.perf_counter() - t0) / len(frames) * 1e3
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.machine())
    pace = (f"images best effort, one every {args.period_s:g} s" if args.best_effort else
            "lock-step (the next frame once the last one is answered)")
    print(f"machine: {cpu}, {os.cpu_count()} cores, CPU capability {cpu_capability()}; node torch "
          f"threads {args.num_threads}; {args.frames} timed frames per case after {args.warmup}; {pace}")
    print(f"(camera side, not in the figures: JPEG q90 encoding of a 480x640 frame {encode_ms:.1f} ms)")
    print(f"{'case':8} {'bytes':>8} {'answered':>9} {'obs->action p50':>16} {'p99':>8} {'node p50':>9} {'p99':>8} "
          f"{'model p50':>10} {'p99':>8}   (ms)")
    with tempfile.TemporaryDirectory() as tmp:
        for case in args.cases:
            r = run_case(case, args, frames, Path(tmp))
            print(f"{r['case']:8} {r['bytes']:8.0f} {r['answered']:>9} {r['p50']:16.2f} {r['p99']:8.2f} {r['node'][0]:9.2f} "
                  f"{r['node'][1]:8.2f} {r['act'][0]:10.2f} {r['act'][1]:8.2f}", flush=True)


if __name__ == "__main__":
    main()
