"""protocad-train as a child process on a bag, and what its run directory holds."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from helpers import ROOT
from helpers.bags import TINY


def metrics(run_dir: Path) -> list[dict]:
    from trainer.metrics_log import read_metrics

    return [r for r in read_metrics(run_dir / "metrics.jsonl") if r.get("kind") == "train"]


def ckpt_counters(path: Path) -> dict:
    from protocad_ros.checkpoint.agent_file import read_checkpoint

    p = read_checkpoint(path)
    return {**p["counters"], "agent_updates": int(p["modules"]["updates"])}


def train_proc(tmp_path: Path, bag: Path, run_dir: Path, *extra: str) -> subprocess.Popen:
    args = [sys.executable, "-m", "trainer.learn.train", "--logs", str(bag), *TINY, "--run-dir", str(run_dir),
            "--cache-dir", str(tmp_path / "cache"), "--log-every", "1", "--seed", "5", *extra]
    return subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
