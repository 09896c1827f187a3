#!/usr/bin/env python3
"""Speed of the lock-step ROS loop against the same env stepped directly, and policy latency.

Measured in one run, on the same machine, with the same task and settings:

1. direct      ContextDMCEnv stepped in this process with zero actions (no ROS)
2. direct+pol  the same, with protocad_ros.policy.Policy.act in the loop (no ROS)
3. ros zero    sim-bridge node (own process, lock-step) + a trivial zero-action responder
               (an rclpy node in this process): the cost of the ROS round trip alone
4. ros policy  sim-bridge node + policy node (random agent), two processes

3 and 4 run twice: with the bridge's lossless lock-step (`lossless`, the default: KEEP_ALL
observation writers, nothing a reliable reader has not acknowledged is dropped) and without.
Observations this process's reader did not receive are reported as lost, never asserted.

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
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

# DDS on this machine only, in a domain of our own (before rclpy is imported).
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))

import numpy as np  # noqa: E402


def pct(values, q) -> float:
    return float(np.percentile(np.asarray(values), q)) if len(values) else float("nan")


def direct(args, with_policy: bool) -> tuple[float, list[float]]:
    """(agent steps/s, Policy.act latencies in s) with the env in this process."""
    import torch

    from sim_bridge.envs import ContextDMCEnv

    torch.set_num_threads(args.threads)
    policy = None
    if with_policy:
        from protocad_ros.agents import make_agent
        from protocad_ros.config import make_config
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


def spawn(name: str, *argv: str, logdir: Path) -> subprocess.Popen:
    log = open(logdir / f"{name}.log", "wb")
    cmd = [sys.executable, *argv]
    if PROFILE is not None:   # sampled where the CPU goes (idle threads left out), as collapsed stacks
        cmd = ["py-spy", "record", "--rate", "500", "--format", "raw", "--nonblocking",
               "--output", str(PROFILE / f"{name}.txt"), "--", *cmd]
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)


#: Frames of a node at work (stepping, spinning, answering): start-up (imports, model load) is left out.
STEADY = ("_run_lockstep", "_run_realtime", "spin_once", "_answer")


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
    import signal

    from sensor_msgs.msg import JointState

    from ros_helpers import Probe, Responder, wait_until
    from sim_bridge import qos, topics

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
            procs.append(spawn("policy" + ns.replace("/", "_"), "-m", "protocad_ros.policy_node", "--ros-args",
                               "-p", f"task:={args.task}", "-p", f"preset:={args.preset}",
                               "-p", f"num_threads:={args.threads}",
                               "-p", "diagnostics_period_s:=0.5", "-r", f"__ns:={ns}",
                               logdir=logdir))
            wait_until(lambda: probe.node.count_publishers(probe.topic(topics.ACTION)) > 0, 180,
                       "the policy node")
        else:
            from sim_bridge.contexts import task_actuators

            zero = np.zeros(len(task_actuators(args.task)))
            Responder(probe, lambda info: zero, ns=ns)
        bridge = spawn("bridge" + ns.replace("/", "_"), "-m", "sim_bridge.node", "--ros-args",
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
    args = ap.parse_args()
    logdir = Path(args.logdir)
    logdir.mkdir(parents=True, exist_ok=True)
    if args.profile:
        global PROFILE
        PROFILE = logdir / "profile"
        PROFILE.mkdir(exist_ok=True)

    import torch

    d_env, _ = direct(args, with_policy=False)
    d_pol, act_lat = direct(args, with_policy=True)
    r_zero = ros_loop(args, with_policy=False, logdir=logdir, acks=True)
    r_pol = ros_loop(args, with_policy=True, logdir=logdir, acks=True)
    r_zero_off = ros_loop(args, with_policy=False, logdir=logdir, acks=False)
    r_pol_off = ros_loop(args, with_policy=True, logdir=logdir, acks=False)

    n = args.episodes * (args.length + 1)
    print(f"bench_ros_loop: {args.task}, {args.episodes} episodes x {args.length} steps "
          f"({n} observations), render {args.render_quality}, {args.preset} random agent, "
          f"torch threads {args.threads}")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"Python {platform.python_version()}, "
          f"RMW {os.environ.get('RMW_IMPLEMENTATION', 'default')}, "
          f"torch CPU capability {torch.backends.cpu.get_cpu_capability()}")
    rows = [
        ("env direct (zero actions)", d_env, None, None),
        ("env + Policy.act direct", d_pol, None, None),
        ("ROS lock-step, zero responder", r_zero["steps_per_s"], d_env, r_zero["lost"]),
        ("  same, lossless off", r_zero_off["steps_per_s"], d_env, r_zero_off["lost"]),
        ("ROS lock-step, policy node", r_pol["steps_per_s"], d_pol, r_pol["lost"]),
        ("  same, lossless off", r_pol_off["steps_per_s"], d_pol, r_pol_off["lost"]),
    ]
    print(f"{'loop':34s} {'steps/s':>9s} {'ratio vs direct':>16s} {'lost':>6s}")
    for name, v, ref, lost in rows:
        ratio = f"{v / ref:16.2f}" if ref else f"{'':16s}"
        print(f"{name:34s} {v:9.1f} {ratio} {'' if lost is None else lost:>6}")
    print(f"{'ROS policy node vs env direct':34s} {'':9s} {r_pol['steps_per_s'] / d_env:16.2f}")
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
