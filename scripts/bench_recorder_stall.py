#!/usr/bin/env python3
"""What a frozen recorder costs a lossless lock-step loop: time and memory, never a message.

Each run: sim-bridge node (own process, lock-step, lossless) + a zero-action responder (an rclpy
node in this process) + trainer.nodes.recorder (own process, default topics, KEEP_ALL readers), for
--steps agent steps. Without a stall, then with the recorder frozen (SIGSTOP) for --stall-s
seconds after --freeze-at steps, alternately (--runs pairs). Printed per run:

- steps/s over the whole run, while the recorder was frozen, and in the --window-s seconds
  after it was resumed (while it catches up on its backlog);
- the backlog: steps taken while it was frozen (each is 4 samples per writer: image, step_info,
  context, /clock, plus the action);
- catch-up: seconds from SIGCONT until the recorder's status line counts every message the
  bridge had published by then (its --status-interval log, 0.2 s);
- memory: the bridge's RSS growth over the stall (the KEEP_ALL histories hold the backlog),
  per backlogged step, and the recorder's peak RSS;
- the check: every message of every topic in the bag (the recorder reports no loss).

    python scripts/bench_recorder_stall.py                  # 4000 steps, 6 s stall, 2 pairs
    python scripts/bench_recorder_stall.py --stall-s 17     # towards Fast DDS's 5000-sample writer limit
    python scripts/bench_recorder_stall.py --queue-depth 1000   # the recorder's old KEEP_LAST(1000)
    python scripts/bench_recorder_stall.py --stall-s 25 --lease-duration 0   # past DDS's default lease
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

# Measure the working tree this script belongs to, not an installed copy; its tests' helpers too.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from helpers import wait_until

from sim_bridge.contract import topics as T
from trainer.bag.reader import BagReader

ROOT = Path(__file__).resolve().parents[1]
# DDS on this machine only, in a domain of our own (before rclpy is imported, in run).
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(ROOT / "sim_bridge" / "fastdds_discovery.xml"))
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))

TASK = "pendulum_swingup"


def rss_mb(pid: int, key: str = "VmRSS") -> float:
    """A process's resident (VmRSS) or peak resident (VmHWM) memory in MB; nan once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def spawn(name: str, logdir: Path, *argv: str) -> subprocess.Popen:
    log = open(logdir / f"{name}.log", "wb")
    return subprocess.Popen([sys.executable, *argv], stdout=log, stderr=subprocess.STDOUT, cwd=ROOT,
                            start_new_session=True)


def stop(proc: subprocess.Popen, timeout: float = 60.0) -> int:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGCONT)
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode


def recorded_counts(log: Path) -> list[tuple[float, int]]:
    """(log time in s, messages on the topic with fewest) from the recorder's --status-interval
    lines ('N messages (/a: n, /b: m, ...)')."""
    out = []
    for m in re.finditer(r"\[(\d+\.\d+)\] \[recorder\]: \d+ messages \(([^)]*)\)", log.read_text(errors="replace")):
        counts = [int(x.rsplit(":", 1)[1]) for x in m.group(2).split(", ") if ":" in x]
        out.append((float(m.group(1)), min(counts) if len(counts) == 5 else 0))
    return out


def steps_at(samples: list[tuple[float, int]], t: float) -> int:
    """Steps seen at wall time t (the last sample at or before it)."""
    n = samples[0][1] if samples else 0
    for ts, k in samples:
        if ts > t:
            break
        n = k
    return n


def run(args, logdir: Path, stall: bool, index: int) -> dict:
    from helpers.ros import Probe, Responder  # rclpy, after the DDS environment above

    ns = f"/stall{index}"
    bag = logdir / f"bag{index}"
    probe = Probe("stall_bench", namespace=ns)
    resp = Responder(probe, lambda info: [0.0], names=["torque"], ns=ns)
    # Each run in its own namespace, with its own clock (a bridge left over must not count).
    clock = f"{ns}/clock"
    topics = [T.topic_name(ns, rel) for rel in (T.IMAGE, T.STEP_INFO, T.CONTEXT, T.ACTION)] + [clock]
    rec = spawn(f"recorder{index}", logdir, "-m", "trainer.nodes.recorder", "-o", str(bag), *topics,
                "--status-interval", "0.2", "--queue-depth", str(args.queue_depth),
                "--lease-duration", str(args.lease_duration))
    bridge = None
    samples: list[tuple[float, float]] = []
    try:
        wait_until(lambda: "recording to" in (logdir / f"recorder{index}.log").read_text(), 120, "the recorder")
        bridge = spawn(f"bridge{index}", logdir, "-m", "sim_bridge.bridge.node", "--ros-args", "-p", f"task:={TASK}",
                       "-p", "seed:=1", "-p", "min_subscribers:=2", "-p", f"episode_length:={args.steps + 10}",
                       "-r", f"__ns:={ns}", "-r", f"/clock:={clock}")
        wait_until(lambda: len(resp.steps) >= 1, 180, "the first step")
        t_start = time.monotonic()
        wait_until(lambda: len(resp.steps) >= args.freeze_at, 300, f"{args.freeze_at} steps")
        rss0 = rss_mb(bridge.pid)
        t_freeze = t_cont = n_freeze = n_cont = peak = cont_wall = None
        if stall:
            os.killpg(rec.pid, signal.SIGSTOP)
            t_freeze, n_freeze = time.monotonic(), len(resp.steps)
            while time.monotonic() - t_freeze < args.stall_s:
                samples.append((time.monotonic(), rss_mb(bridge.pid)))
                time.sleep(0.1)
            n_cont = len(resp.steps)
            peak = max(r for _, r in samples)
            t_cont = time.monotonic()
            os.killpg(rec.pid, signal.SIGCONT)
            cont_wall = time.time()
        published_at: list[tuple[float, int]] = []   # (wall time, steps the responder has seen)
        deadline = time.monotonic() + 600
        n_window = None
        while (len(resp.steps) < args.steps or (stall and n_window is None)) and time.monotonic() < deadline:
            published_at.append((time.time(), len(resp.steps)))
            if stall and n_window is None and time.monotonic() - t_cont >= args.window_s:
                n_window = len(resp.steps)
            time.sleep(0.02)
        t_end, n_end = time.monotonic(), len(resp.steps)
        assert stop(bridge) == 0, "the bridge failed"
        rec_peak = rss_mb(rec.pid, "VmHWM")
        stop(rec)
        reader = BagReader(bag)
        counts = reader.report.counts
        published = int(re.search(r"observations_published=(\d+)",
                                  (logdir / f"bridge{index}.log").read_text()).group(1))
        ok = all(counts.get(t, 0) == published for t in topics if t != T.topic_name(ns, T.ACTION))
        out = {"stall": stall, "steps_per_s": (n_end - 1) / (t_end - t_start), "wall_s": t_end - t_start,
               "steps": n_end, "published": published, "bag_complete": ok, "recorder_peak_rss_mb": rec_peak}
        text = (logdir / f"recorder{index}.log").read_text(errors="replace")
        out["recorder_lost"] = "LOST" in text
        out["recorder_stalled"] = "STALLED past the DDS lease" in text   # said even where no gap shows
        if stall:
            backlog = n_cont - n_freeze
            out.update(backlog_steps=backlog, frozen_steps_per_s=backlog / (t_cont - t_freeze),
                       window_steps_per_s=(n_window - n_cont) / (args.window_s),
                       bridge_rss_growth_mb=peak - rss0,
                       kb_per_backlog_step=(peak - rss0) * 1024 / max(backlog, 1))
            # catch-up: the first status line after SIGCONT where every topic has what had been
            # published by then (within 2 steps: the status and the sample are not simultaneous)
            lines = recorded_counts(logdir / f"recorder{index}.log")
            done = [t for t, n in lines if t >= cont_wall and n >= steps_at(published_at, t) - 2]
            out["catch_up_s"] = (done[0] - cont_wall) if done else float("nan")
        return out
    finally:
        if bridge is not None:
            stop(bridge)
        stop(rec)
        probe.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=4000, help="agent steps per run")
    ap.add_argument("--freeze-at", type=int, default=100, help="step at which the recorder is frozen")
    ap.add_argument("--stall-s", type=float, default=6.0, help="seconds the recorder stays frozen")
    ap.add_argument("--window-s", type=float, default=2.0, help="seconds measured after SIGCONT")
    ap.add_argument("--runs", type=int, default=2, help="pairs (no stall, stall)")
    ap.add_argument("--queue-depth", type=int, default=0,
                    help="the recorder's --queue-depth (0: KEEP_ALL, the default; 1000: the old KEEP_LAST(1000))")
    ap.add_argument("--lease-duration", type=float, default=120.0,
                    help="the recorder's --lease-duration (s; 0: Fast DDS's 20 s, which a longer stall outlasts)")
    ap.add_argument("--logdir", default="/tmp/bench_recorder_stall")
    args = ap.parse_args()
    logdir = Path(args.logdir)
    logdir.mkdir(parents=True, exist_ok=True)
    for old in logdir.glob("bag*"):
        shutil.rmtree(old, ignore_errors=True)
    rows = []
    for i in range(args.runs):
        for stall in (False, True):
            r = run(args, logdir, stall, len(rows))
            rows.append(r)
            print({k: (round(v, 2) if isinstance(v, float) else v) for k, v in r.items()}, flush=True)
    for stall in (False, True):
        rs = [r for r in rows if r["stall"] == stall]
        print(f"{'stall ' + str(args.stall_s) + ' s' if stall else 'no stall':>12}: wall "
              + ", ".join(f"{r['wall_s']:.1f}" for r in rs) + " s; steps/s "
              + ", ".join(f"{r['steps_per_s']:.0f}" for r in rs)
              + (("; frozen " + ", ".join(f"{r['frozen_steps_per_s']:.0f}" for r in rs)
                  + "; first " + f"{args.window_s:g} s after SIGCONT " + ", ".join(f"{r['window_steps_per_s']:.0f}" for r in rs)
                  + "; backlog " + ", ".join(str(r["backlog_steps"]) for r in rs) + " steps"
                  + "; catch-up " + ", ".join(f"{r['catch_up_s']:.1f}" for r in rs) + " s"
                  + "; bridge RSS +" + ", ".join(f"{r['bridge_rss_growth_mb']:.0f}" for r in rs) + " MB ("
                  + ", ".join(f"{r['kb_per_backlog_step']:.1f}" for r in rs) + " KB/step)") if stall else "")
              + "; recorder peak RSS " + ", ".join(f"{r['recorder_peak_rss_mb']:.0f}" for r in rs) + " MB"
              + "; bag complete " + ", ".join(str(r["bag_complete"] and not r["recorder_lost"]) for r in rs)
              + "; recorder reported LOST " + ", ".join(str(r["recorder_lost"]) for r in rs)
              + ", STALLED past its lease " + ", ".join(str(r["recorder_stalled"]) for r in rs), flush=True)


if __name__ == "__main__":
    main()
