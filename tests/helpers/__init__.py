"""What the tests share: the repository root, one polling helper, a child process with its
output in a log file. Submodules: bags (steps with known content as MCAP bags, the CLIs),
ros (a test-side rclpy probe), agents (tiny agents, batches and checkpoints), policy (feeding
a policy node process), camera_frames (a camera's frames and messages, from walker renders);
scripts run as child processes: graph_watch.py, ddp_grad_worker.py, and import_blocker/ (put
first on a child's PYTHONPATH).

Test modules import from here, never from each other or from conftest.py (which only sets up
the environment and holds the fixtures).
"""
from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HELPERS = Path(__file__).resolve().parent


def wait_until(predicate, timeout: float, what: str, interval: float = 0.02):
    """Poll until predicate() is truthy (returns it) or fail naming what was awaited. The
    default interval is short: DDS events arrive within milliseconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout}s waiting for {what}")


class Proc:
    """A node or CLI in its own process, output captured to a log file."""

    def __init__(self, args: list[str], log: Path, env: dict | None = None, cwd: Path = ROOT):
        self.args, self.log_path = args, log
        self._log = open(log, "wb")
        self.p = subprocess.Popen(args, stdout=self._log, stderr=subprocess.STDOUT, cwd=cwd,
                                  env={**os.environ, **(env or {})}, start_new_session=True)

    def output(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def alive(self) -> bool:
        return self.p.poll() is None

    def stop(self, sig=signal.SIGINT, timeout: float = 20.0) -> int:
        if self.alive():
            os.killpg(self.p.pid, sig)
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.p.pid, signal.SIGKILL)
                self.p.wait()
        self._log.close()
        return self.p.returncode


def wait_exit(proc: Proc, timeout: float) -> int:
    """The exit status of `proc` once it has ended by itself."""
    wait_until(lambda: not proc.alive(), timeout, f"{proc.args} to exit", 0.05)
    return proc.p.returncode


def interrupt(proc: subprocess.Popen, timeout: float = 60) -> str:
    """Ctrl-C a child started with text pipes: its output once it has exited (killed when it
    has not within `timeout`)."""
    proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out
