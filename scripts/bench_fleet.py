#!/usr/bin/env python3
"""Fleet throughput: total env steps/s over M lock-step actor groups (sim bridge + policy node
each, in /protocad/robotI, own clock), for M = 1 and 2, discovering without a server
(LOCALHOST) and through a Fast DDS Discovery Server on 127.0.0.1.

Each configuration runs in a fresh process (Fast DDS reads the discovery variables when a
participant is created): RosStack starts the groups (trainer/launch/rosprocs.py), and the launcher's
graph node subscribes to every robot's step_info and image (undecoded, like a recorder); each
bridge waits for its policy, that reader (and the recorder, with --record), so every step is
seen. The fleet's rate counts
the steps of all groups in the span where all of them step (from the last group's 5th
observation to the first group's last: they start seconds apart); a group's own rate is its
steps after its 5th observation over their time. "obs seen" above "expected" are lock-step
timeouts (an observation republished after lockstep_timeout_s without an answer).
Env steps = agent steps x action repeat. The policy nodes serve a random agent (no checkpoint).

    python scripts/bench_fleet.py                       # pendulum_swingup, 4 x 250 steps, M = 1, 2
    python scripts/bench_fleet.py --groups 1 2 4 --episodes 2 --length 200
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# Measure the working tree this script belongs to, not an installed copy of the packages.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocad_ros.model.precision import cpu_capability
from sim_bridge.contract import topics as T
from trainer.bag.reader import BagReader
from trainer.launch import discovery
from trainer.launch.rosprocs import RosStack, robot_namespaces

ROOT = Path(__file__).resolve().parents[1]
# DDS on this machine only (before rclpy is imported, in `one`); the nodes render headless.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))


WARMUP = 5   # observations of each group before its timing starts


def one(args) -> dict:
    """One configuration, in this process: M groups, measured; returns the figures."""
    # rclpy's messages and QoS profiles after the DDS environment set at the top
    from sensor_msgs.msg import Image, JointState

    from sim_bridge.contract import qos

    namespaces = robot_namespaces(T.DEFAULT_NAMESPACE, args.one, first=0)
    server = (discovery.LOCALHOST, discovery.free_port()) if args.server else None
    with (tempfile.TemporaryDirectory(prefix="bench_fleet_") if not os.environ.get("BENCH_FLEET_KEEP") else
          contextlib.nullcontext(tempfile.mkdtemp(prefix="bench_fleet_"))) as tmp:
        stack = RosStack(Path(tmp) / "logs", start_discovery_server=server)
        seen: dict[str, list[float]] = {ns: [] for ns in namespaces}
        try:
            graph = stack.graph
            for ns in namespaces:
                graph.node.create_subscription(JointState, T.topic_name(ns, T.STEP_INFO),
                                               lambda _m, ns=ns: seen[ns].append(time.monotonic()),
                                               qos.observation_qos(), raw=True)
                # images too (undecoded), so that each bridge counts this reader in min_subscribers
                graph.node.create_subscription(Image, T.topic_name(ns, T.IMAGE), lambda _m: None,
                                               qos.observation_qos(), raw=True)
            bag = Path(tmp) / "bag"
            if args.record:   # one recorder for the fleet, as machine A would run it
                stack.start_recorder(bag, namespaces=namespaces)
            for i, ns in enumerate(namespaces):
                stack.start_policy(checkpoint=None, task=args.task, preset=args.preset, num_threads=args.threads,
                                   seed=i, ns=ns)
            bridges = [stack.start_bridge(task=args.task, seed=i, max_episodes=args.episodes,
                                          episode_length=args.length, min_subscribers=2 + args.record,
                                          ns=ns)
                       for i, ns in enumerate(namespaces)]
            deadline = time.monotonic() + args.timeout
            while any(b.alive() for b in bridges) and time.monotonic() < deadline:
                graph.spin(0.01)
            # what is still queued for this reader (it lags behind on busy cores): until 0.5 s
            # pass without a new observation
            quiet_since, n = time.monotonic(), -1
            while time.monotonic() - quiet_since < 0.5 and time.monotonic() < deadline + 10:
                graph.spin(0.01)
                if sum(map(len, seen.values())) != n:
                    quiet_since, n = time.monotonic(), sum(map(len, seen.values()))
        finally:
            stack.stop_all()
            bag_bytes = sum(f.stat().st_size for f in bag.glob("*")) if args.record else None
            if args.record:   # did the recorder keep up: every step of every group in the bag?
                counts = BagReader(bag).report.counts
                recorded = sum(counts.get(T.topic_name(ns, T.STEP_INFO), 0) for ns in namespaces)
    if any(len(t) <= WARMUP + 1 for t in seen.values()):
        raise SystemExit(f"too few observations to time: {[len(t) for t in seen.values()]}")
    # The span in which every group steps: from the last group's WARMUP-th observation (groups
    # start a few seconds apart, and a first action may come late) to the first group's end.
    start = max(t[WARMUP] for t in seen.values())
    end = min(t[-1] for t in seen.values())
    steps = sum(sum(start <= x <= end for x in t) for t in seen.values())
    per_group = [(len(t) - 1 - WARMUP) / (t[-1] - t[WARMUP]) for t in seen.values()]
    return {"groups": args.one, "server": bool(args.server), "agent_steps": steps,
            "seconds": end - start,
            "observations_expected": len(namespaces) * args.episodes * (args.length + 1),
            "observations_seen": sum(len(t) for t in seen.values()),
            "fleet_agent_steps_per_s": steps / (end - start) if end > start else float("nan"),
            "fleet_env_steps_per_s": steps * args.action_repeat / (end - start) if end > start else float("nan"),
            "per_group_agent_steps_per_s": per_group,
            "bag_bytes_per_step": bag_bytes / sum(len(t) for t in seen.values()) if bag_bytes else None,
            "recorded_steps": recorded if args.record else None}


def machine_line() -> str:
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    return (f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
            f"torch CPU capability {cpu_capability()}, load average {load}, "
            f"RMW {os.environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--task", default="pendulum_swingup")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--groups", type=int, nargs="+", default=[1, 2], help="fleet sizes M to time")
    ap.add_argument("--episodes", type=int, default=4, help="episodes per group")
    ap.add_argument("--length", type=int, default=250, help="agent steps per episode")
    ap.add_argument("--action-repeat", type=int, default=2, help="the bridge's (env steps per agent step)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per policy node")
    ap.add_argument("--record", action="store_true",
                    help="a recorder for all groups in every configuration (prints bag bytes per step)")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds a configuration may run")
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)    # a child: one configuration
    ap.add_argument("--server", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one is not None:
        print(json.dumps(one(args)), flush=True)
        return
    print(machine_line(), flush=True)
    print(f"{args.task}, {args.episodes} x {args.length} agent steps per group, action repeat {args.action_repeat}, "
          f"lock-step, {args.preset} random agent, {args.threads} torch thread(s) per policy node"
          + (", one recorder for all groups" if args.record else ", no recorder"), flush=True)
    rows = []
    for m in args.groups:
        for server in (False, True):
            cmd = [sys.executable, __file__, "--one", str(m), "--task", args.task, "--preset", args.preset,
                   "--episodes", str(args.episodes), "--length", str(args.length), "--threads", str(args.threads),
                   "--action-repeat", str(args.action_repeat), "--timeout", str(args.timeout)] + \
                (["--record"] if args.record else [])
            # RosStack draws a fresh ROS_DOMAIN_ID for each configuration
            r = subprocess.run(cmd + (["--server"] if server else []), capture_output=True, text=True)
            lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
            if r.returncode or not lines:
                sys.exit(f"configuration M={m} server={server} failed:\n{r.stdout[-3000:]}{r.stderr[-3000:]}")
            rows.append(json.loads(lines[-1]))
    print(f"{'groups':>6s} {'discovery':>18s} {'env steps/s':>12s} {'agent steps/s':>14s} "
          f"{'per group (agent)':>20s} {'obs seen/expected':>18s}" + (f" {'bag B/step':>10s} {'recorded':>9s}" if args.record else ""))
    for r in rows:
        per = ", ".join(f"{v:.0f}" for v in r["per_group_agent_steps_per_s"])
        print(f"{r['groups']:6d} {'server 127.0.0.1' if r['server'] else 'no server':>18s} "
              f"{r['fleet_env_steps_per_s']:12.1f} {r['fleet_agent_steps_per_s']:14.1f} {per:>20s} "
              f"{r['observations_seen']:>8d}/{r['observations_expected']}"
              + (f" {r['bag_bytes_per_step']:10.0f} {r['recorded_steps']:9d}" if args.record else ""))
    print(machine_line().replace("machine:", "after:"), flush=True)


if __name__ == "__main__":
    main()
