#!/usr/bin/env python3
"""How long a new participant (a `ros2` verb, a node starting) takes to see a running one,
with Fast DDS's default participant announcements (every 3 s) and with the environment's
profile (sim_bridge/fastdds_discovery.xml: every 0.5 s). A publisher node runs in its own
process; each try is a fresh process that creates a node and waits until the publisher's
topic has a publisher in its graph (at most 10 s). Times are printed, never asserted.

    python scripts/bench_discovery.py              # 10 tries each
    python scripts/bench_discovery.py --tries 20
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
PROFILE = ROOT / "sim_bridge" / "fastdds_discovery.xml"
TOPIC = "/bench_discovery"

PUBLISHER = f"""
import rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node("bench_discovery_publisher")
node.create_publisher(String, "{TOPIC}", 10)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
"""

TRY = f"""
import time, rclpy
rclpy.init()
node = rclpy.create_node("bench_discovery_try")
t0 = time.perf_counter()
while node.count_publishers("{TOPIC}") == 0 and time.perf_counter() - t0 < 10.0:
    time.sleep(0.005)
print(f"{{time.perf_counter() - t0:.3f}}" if node.count_publishers("{TOPIC}") else "none")
"""


def tries(env: dict, n: int) -> list[str]:
    pub = subprocess.Popen([sys.executable, "-c", PUBLISHER], env=env, stdout=subprocess.DEVNULL,
                           stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(3.0)   # the publisher is up and past its own initial announcements
        if pub.poll() is not None:
            raise SystemExit(f"the publisher exited {pub.returncode}: {pub.stderr.read().strip()}")
        out = []
        for _ in range(n):
            r = subprocess.run([sys.executable, "-c", TRY], env=env, capture_output=True, text=True, timeout=60)
            out.append(r.stdout.strip() or f"error: {r.stderr.strip().splitlines()[-1:]}")
        return out
    finally:
        pub.terminate()
        pub.wait(10)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--tries", type=int, default=10, help="fresh participants per setting (default 10)")
    a = ap.parse_args()
    if a.tries < 1:
        ap.error("--tries must be at least 1")
    base = {k: v for k, v in os.environ.items() if k != "FASTRTPS_DEFAULT_PROFILES_FILE"}
    base["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"   # never off this machine
    base.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    print(f"bench_discovery: {a.tries} tries each; {platform.machine()}, {os.cpu_count()} CPUs, "
          f"RMW {os.environ.get('RMW_IMPLEMENTATION', 'default')}, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    for label, env in (("Fast DDS defaults (announcements every 3 s)", base),
                       (f"{PROFILE.relative_to(ROOT)} (every 0.5 s)",
                        {**base, "FASTRTPS_DEFAULT_PROFILES_FILE": str(PROFILE)})):
        times = tries(env, a.tries)
        print(f"{label}: seconds to see the running publisher: {' '.join(times)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
