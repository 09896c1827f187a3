#!/usr/bin/env python3
"""Speed of the lock-step ROS loop against the same env stepped directly, and policy latency.

Measured in one run, on the same machine, with the same task and settings:

1. direct      ContextDMCEnv stepped in this process with zero actions (no ROS)
2. direct+pol  the same, with protocad_ros.policy.Policy.act in the loop (no ROS)
3. ros zero    sim-bridge node (own process, lock-step) + a trivial zero-action responder
               (an rclpy node in this process): the cost of the ROS round trip alone
4. ros policy  sim-bridge node + policy node (random agent), two processes

5. floor       a bare rclpy round trip of the same messages between two processes: this process
               publishes a 64x64 image and a step_info (the bridge's QoS), a 40-line echo node
               answers each pair with an action; no env, no validation, no counters. It bounds
               what any rclpy bridge/policy pair can reach here: the ceiling ratios printed
               are direct / (direct + round trip) with this floor's mean round trip. Once
               more with the image alone, to show what one message per step would give.

3 and 4 run with the bridge's lossless lock-step (`lossless`, the default: KEEP_ALL observation
writers, nothing a reliable reader has not acknowledged is dropped) and without, in the order
on, off, off, on (the first ROS run of a process is slower; each row is the mean of its two
runs, both shown). Observations this process's reader did not receive are reported as lost,
never asserted.

For 3 and 4 the steps/s are agent steps between the first and the last observation seen
(resets included, as in 1 and 2). Latencies: the policy node's own per-step latency
(observation complete -> action published) and model time, the bridge's round trip
(observation published -> valid action received), and Policy.act in-process, all p50/p99.

    python scripts/bench_ros_loop.py                      # pendulum_swingup, small preset
    python scripts/bench_ros_loop.py --task walker_walk --episodes 3 --length 200
"""
from __future__ import annotations

import argparse
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

# Measure the working tree this script belongs to, not an installed copy; its tests' helpers too.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from helpers import wait_until

from sim_bridge.contract import topics
from sim_bridge.contract.contexts import task_actuators
from sim_bridge.sim.envs import ContextDMCEnv

ROOT = Path(__file__).resolve().parents[1]
# DDS on this machine only, in a domain of our own (before rclpy is imported, in the functions
# that use it). torch and the model load in `direct` and main, never in the --echo child.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))


def pct(values, q) -> float:
    return float(np.percentile(np.asarray(values), q)) if len(values) else float("nan")


def mean_run(results: list[dict[str, float]]) -> dict:
    """One row from repeated runs: steps/s and latencies averaged, losses summed, and each
    run's steps/s under "runs"."""
    out: dict = {k: float(np.mean([r[k] for r in results])) for k in results[0] if k != "lost"}
    out["lost"] = sum(r["lost"] for r in results)
    out["runs"] = [r["steps_per_s"] for r in results]
    return out


def direct(args, with_policy: bool) -> tuple[float, list[float]]:
    """(agent steps/s, Policy.act latencies in s) with the env in this process."""
    import torch

    torch.set_num_threads(args.threads)
    policy = None
    if with_policy:
        from protocad_ros.model.agent import make_agent
        from protocad_ros.model.config import make_config
        from protocad_ros.policy import Policy

        env0 = ContextDMCEnv(args.task, seed=args.seed)
        adim = env0.action_dim
        env0.close()
        policy = Policy(make_agent(make_config(args.task, args.preset), adim))
    lat: list[float] = []
    with ContextDMCEnv(args.task, seed=args.seed, render_quality=args.render_quality,
                       time_limit=args.length * 2) as env:
        obs = env.reset()
        zero = np.zeros(env.action_dim, np.float32)
        prev = zero
        for _ in range(3):   # warm-up (shader compilation, first torch call)
            if policy is not None:
                policy.act(obs.image, prev, obs.is_first)
            env.step(zero)
        obs = env.reset()
        steps = 0
        start = time.perf_counter()
        for _ in range(args.episodes):
            while True:
                if policy is not None:
                    t = time.perf_counter()
                    a, _ = policy.act(obs.image, prev, obs.is_first)
                    lat.append(time.perf_counter() - t)
                    prev = np.zeros_like(a) if obs.is_last else a
                else:
                    a = zero
                steps += 1
                if obs.is_last:
                    obs = env.reset()
                    break
                obs = env.step(a)
        return steps / (time.perf_counter() - start), lat


PROFILE: Path | None = None   # --profile DIR: every node process runs under py-spy


def echo_node(ns: str, image_only: bool) -> None:
    """`--echo NS`: answer each (image, step_info) pair (each image with `--image-only`) with a
    zero action, nothing else."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from sensor_msgs.msg import Image, JointState

    from sim_bridge.contract import qos

    rclpy.init()
    node = Node("bench_echo", namespace=ns)
    pub = node.create_publisher(JointState, topics.ACTION, qos.action_qos())
    halves: dict[int, int] = {}

    def on(msg) -> None:
        stamp = topics.stamp_to_ns(msg.header.stamp)
        if not image_only and halves.pop(stamp, None) is None:
            halves[stamp] = 1
            return
        pub.publish(topics.fill_action(JointState(), [0.0], ["a0"], stamp))

    node.create_subscription(Image, topics.IMAGE, on, qos.observation_qos(lossless=True))
    if not image_only:
        node.create_subscription(JointState, topics.STEP_INFO, on, qos.observation_qos(lossless=True))
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


def floor(args, logdir: Path, image_only: bool = False) -> dict[str, float]:
    """Round trips/s and latency of the bare rclpy pair (see the module docstring, 5); with
    `image_only` the observation is the image alone (one message per step, not two)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import Image, JointState

    from sim_bridge.contract import qos

    ns = "/bench_floor"
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node("bench_floor", namespace=ns, context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    pub_img = node.create_publisher(Image, topics.IMAGE, qos.observation_qos(lossless=True))
    pub_info = node.create_publisher(JointState, topics.STEP_INFO, qos.observation_qos(lossless=True))
    answers: list[int] = []
    node.create_subscription(JointState, topics.ACTION,
                             lambda m: answers.append(topics.stamp_to_ns(m.header.stamp)),
                             qos.action_qos())
    echo = spawn("echo", __file__, "--echo", ns, *(["--image-only"] if image_only else []), logdir=logdir)
    try:
        def matched() -> bool:
            ex.spin_once(timeout_sec=0.01)
            return (pub_img.get_subscription_count() > 0
                    and (image_only or pub_info.get_subscription_count() > 0) and node.count_publishers(f"{ns}/{topics.ACTION}") > 0)

        wait_until(matched, 60, "the echo node")
        image = np.zeros((64, 64, 3), np.uint8)
        img, info = Image(), JointState()
        lat: list[float] = []
        n = args.episodes * (args.length + 1)
        warm = 50
        start = 0.0
        for i in range(warm + n):
            if i == warm:
                start = time.perf_counter()
            t = time.perf_counter()
            stamp = (i + 1) * 1_000_000
            pub_img.publish(topics.fill_image(img, image, stamp))
            if not image_only:
                pub_info.publish(topics.fill_step_info(info, topics.StepInfo(
                    0.0, 1.0, False, False, False, 0, i), stamp))
            while not answers or answers[-1] != stamp:
                ex.spin_once(timeout_sec=1.0)
            if i >= warm:
                lat.append(time.perf_counter() - t)
        total = time.perf_counter() - start
        return {"rt_per_s": n / total, "rt_mean_ms": 1e3 * total / n,
                "rt_p50_ms": pct(lat, 50) * 1e3, "rt_p99_ms": pct(lat, 99) * 1e3}
    finally:
        os.killpg(echo.pid, signal.SIGKILL)
        echo.wait()
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def spawn(name: str, *argv: str, logdir: Path) -> subprocess.Popen:
    log = open(logdir / f"{name}.log", "wb")
    cmd = [sys.executable, *argv]
    if PROFILE is not None:   # sampled where the CPU goes (idle threads left out), as collapsed stacks
        cmd = ["py-spy", "record", "--rate", "500", "--format", "raw", "--nonblocking",
               "--output", str(PROFILE / f"{name}.txt"), "--", *cmd]
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)


#: Frames of a node at work (stepping, spinning, answering): start-up (imports, model load) is left out.
STEADY = ("_run_lockstep", "_run_realtime", "spin_once", "answer_paired")


def profile_top(path: Path, n: int = 12) -> list[tuple[float, float, str]]:
    """(self %, inclusive %, function) of a py-spy raw profile, by self time, over the samples
    of the node at work (a STEADY frame in the stack)."""
    own: dict[str, int] = {}
    incl: dict[str, int] = {}
    total = 0
    for line in path.read_text(errors="replace").splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        k = int(count)
        if not any(m in stack for m in STEADY):
            continue
        total += k
        frames = [f.split(" (")[0] + " (" + f.rsplit("/", 1)[-1] if "(" in f else f for f in stack.split(";")]
        own[frames[-1]] = own.get(frames[-1], 0) + k
        for f in set(frames):
            incl[f] = incl.get(f, 0) + k
    top = sorted(own.items(), key=lambda kv: -kv[1])[:n]
    return [(100 * c / total, 100 * incl[f] / total, f) for f, c in top] if total else []


def ros_loop(args, with_policy: bool, logdir: Path, acks: bool) -> dict[str, float]:
    from helpers.ros import Probe, Responder
    from sensor_msgs.msg import JointState

    from sim_bridge.contract import qos

    ns = ("/bench_policy" if with_policy else "/bench_zero") + ("_acked" if acks else "")
    probe = Probe("bench_probe", namespace=ns)
    seen: list[tuple[float, int]] = []
    info_sub = probe.node.create_subscription(
        JointState, probe.topic(topics.STEP_INFO),
        lambda m: seen.append((time.perf_counter(), topics.stamp_to_ns(m.header.stamp))),
        qos.observation_qos())
    procs = []
    try:
        if with_policy:
            procs.append(spawn("policy" + ns.replace("/", "_"), "-m", "protocad_ros.node.policy_node", "--ros-args",
                               "-p", f"task:={args.task}", "-p", f"preset:={args.preset}",
                               "-p", f"num_threads:={args.threads}",
                               "-p", "diagnostics_period_s:=0.5", "-r", f"__ns:={ns}",
                               logdir=logdir))
            wait_until(lambda: probe.node.count_publishers(probe.topic(topics.ACTION)) > 0, 180,
                       "the policy node")
        else:
            zero = np.zeros(len(task_actuators(args.task)))
            Responder(probe, lambda info: zero, ns=ns)
        bridge = spawn("bridge" + ns.replace("/", "_"), "-m", "sim_bridge.bridge.node", "--ros-args",
                       "-p", f"task:={args.task}", "-p", f"seed:={args.seed}",
                       "-p", f"episode_length:={args.length}",
                       "-p", f"max_episodes:={args.episodes}",
                       "-p", f"render_quality:={args.render_quality}",
                       "-p", "min_subscribers:=1", "-p", "diagnostics_period_s:=0.5",
                       "-p", f"lossless:={str(acks).lower()}",
                       "-r", f"__ns:={ns}", logdir=logdir)
        procs.append(bridge)
        expected = args.episodes * (args.length + 1)
        wait_until(lambda: bridge.poll() is not None, 600, "the bridge to finish", interval=0.1)
        if bridge.returncode != 0:
            raise RuntimeError(f"bridge exited {bridge.returncode}: see {logdir}/bridge.log")
        wait_until(lambda: probe.node_diag(f"{ns}/sim_bridge").get("episodes")
                   == str(args.episodes), 10, "the bridge's last diagnostics")
        if with_policy:
            try:
                wait_until(lambda: probe.node_diag(f"{ns}/policy").get("observations_answered")
                           == str(expected), 10, "the policy's diagnostics")
            except AssertionError:
                pass   # reported below through the loss, not a failure of the benchmark
        # Like `direct`: from the first observation to one past the last (its answer).
        per_step = (seen[-1][0] - seen[0][0]) / (len(seen) - 1)
        out = {"steps_per_s": 1.0 / per_step, "lost": expected - len({s for _, s in seen})}
        b = probe.node_diag(f"{ns}/sim_bridge")
        out["rtt_p50_ms"], out["rtt_p99_ms"] = (float(b["action_latency_ms_p50"]),
                                                float(b["action_latency_ms_p99"]))
        if with_policy:
            p = probe.node_diag(f"{ns}/policy")
            for k in ("latency_ms_p50", "latency_ms_p99", "act_ms_p50", "act_ms_p99"):
                out[k] = float(p[k])
        return out
    finally:
        for proc in procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
                try:
                    proc.wait(20)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
        probe.node.destroy_subscription(info_sub)
        probe.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="pendulum_swingup")
    ap.add_argument("--preset", default="small", help="model preset of the random agent")
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--length", type=int, default=100, help="agent steps per episode")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--render-quality", default="fast", choices=("fast", "default"))
    ap.add_argument("--threads", type=int, default=1, help="torch threads (node and direct)")
    ap.add_argument("--logdir", default="/tmp/bench_ros_loop", help="node logs")
    ap.add_argument("--profile", action="store_true",
                    help="run the nodes under py-spy (pip install py-spy) and print the top functions of "
                         "the bridge and the policy node (profiled runs are slower; their figures are "
                         "not the benchmark's)")
    ap.add_argument("--echo", metavar="NS", help=argparse.SUPPRESS)   # the floor's echo node
    ap.add_argument("--image-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.echo:
        return echo_node(args.echo, args.image_only)
    logdir = Path(args.logdir)
    logdir.mkdir(parents=True, exist_ok=True)
    if args.profile:
        global PROFILE
        PROFILE = logdir / "profile"
        PROFILE.mkdir(exist_ok=True)

    import torch

    d_env, _ = direct(args, with_policy=False)
    d_pol, act_lat = direct(args, with_policy=True)
    floors = [floor(args, logdir)]
    runs: dict[tuple[bool, bool], list[dict[str, float]]] = {}
    for acks in (True, False, False, True):   # on, off, off, on: order effects cancel
        for with_policy in (False, True):
            runs.setdefault((with_policy, acks), []).append(
                ros_loop(args, with_policy=with_policy, logdir=logdir, acks=acks))
    floors.append(floor(args, logdir))
    one_message = floor(args, logdir, image_only=True)
    bare = {k: float(np.mean([f[k] for f in floors])) for k in floors[0]}
    r_zero, r_pol = mean_run(runs[False, True]), mean_run(runs[True, True])
    r_zero_off, r_pol_off = mean_run(runs[False, False]), mean_run(runs[True, False])

    n = args.episodes * (args.length + 1)
    print(f"bench_ros_loop: {args.task}, {args.episodes} episodes x {args.length} steps "
          f"({n} observations), render {args.render_quality}, {args.preset} random agent, "
          f"torch threads {args.threads}")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"Python {platform.python_version()}, "
          f"RMW {os.environ.get('RMW_IMPLEMENTATION', 'default')}, "
          f"torch CPU capability {torch.backends.cpu.get_cpu_capability()}")
    rows = [
        ("env direct (zero actions)", {"steps_per_s": d_env}, None),
        ("env + Policy.act direct", {"steps_per_s": d_pol}, None),
        ("ROS lock-step, zero responder", r_zero, d_env),
        ("  same, lossless off", r_zero_off, d_env),
        ("ROS lock-step, policy node", r_pol, d_pol),
        ("  same, lossless off", r_pol_off, d_pol),
    ]
    print(f"{'loop':34s} {'steps/s':>9s} {'ratio vs direct':>16s} {'lost':>6s}  runs (steps/s)")
    for name, row, ref in rows:
        v = row["steps_per_s"]
        ratio = f"{v / ref:16.2f}" if ref else f"{'':16s}"
        each = "  ".join(f"{x:.1f}" for x in row.get("runs", ()))
        print(f"{name:34s} {v:9.1f} {ratio} {row.get('lost', ''):>6}  {each}")
    print(f"{'ROS policy node vs env direct':34s} {'':9s} {r_pol['steps_per_s'] / d_env:16.2f}")
    rt = bare["rt_mean_ms"] / 1e3
    each_floor = " / ".join(f"{f['rt_mean_ms']:.3f}" for f in floors)
    print(f"floor: bare rclpy round trip (image + step_info -> action, two processes): "
          f"{bare['rt_per_s']:.0f} round trips/s, mean {bare['rt_mean_ms']:.3f} ms, "
          f"p50 {bare['rt_p50_ms']:.3f}, p99 {bare['rt_p99_ms']:.3f} (means of a run before and one "
          f"after the loops: {each_floor} ms)")
    print(f"  ceiling at that round trip: zero responder {1 / (1 + rt * d_env):.2f} of direct, "
          f"policy node {1 / (1 + rt * d_pol):.2f} of env + Policy.act")
    rt1 = one_message["rt_mean_ms"] / 1e3
    print(f"  the image alone (one message a step, not the contract's two): mean "
          f"{one_message['rt_mean_ms']:.3f} ms, p50 {one_message['rt_p50_ms']:.3f}; ceiling "
          f"{1 / (1 + rt1 * d_env):.2f} / {1 / (1 + rt1 * d_pol):.2f}")
    print("latency (ms)                          p50      p99")
    lat_rows = [
        ("Policy.act in-process", pct(act_lat, 50) * 1e3, pct(act_lat, 99) * 1e3),
        ("policy node, obs -> action", r_pol["latency_ms_p50"], r_pol["latency_ms_p99"]),
        ("policy node, model (act)", r_pol["act_ms_p50"], r_pol["act_ms_p99"]),
        ("bridge round trip, zero resp.", r_zero["rtt_p50_ms"], r_zero["rtt_p99_ms"]),
        ("bridge round trip, policy node", r_pol["rtt_p50_ms"], r_pol["rtt_p99_ms"]),
    ]
    for name, p50, p99 in lat_rows:
        print(f"  {name:32s} {p50:7.2f}  {p99:7.2f}")
    if PROFILE is not None:
        for f in sorted(PROFILE.glob("*.txt")):
            print(f"profile {f.stem} (py-spy, non-idle samples at work): self %  incl %  function")
            for own, incl, fn in profile_top(f):
                print(f"  {own:6.1f} {incl:7.1f}  {fn}")


if __name__ == "__main__":
    main()
