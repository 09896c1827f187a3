"""protocad-train as a process: logs written by another tool, --resume after SIGKILL (same
counters, same next batches), Ctrl-C, and the CLI's errors."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT, wait_for
from trainer_bags import TINY, make_steps, run_cli, write_bag, write_rosbags_bag

ROBOT = {"image": "/robot/camera", "step_info": "/robot/step", "action": "/robot/cmd", "context": "/robot/ctx"}


def metrics(run_dir: Path) -> list[dict]:
    from trainer.runs import read_metrics

    return [r for r in read_metrics(run_dir / "metrics.jsonl") if r.get("kind") == "train"]


def ckpt_counters(path: Path) -> dict:
    from protocad_ros.checkpoint import read_checkpoint

    p = read_checkpoint(path)
    return {**p["counters"], "agent_updates": int(p["modules"]["updates"])}


def test_log_from_another_tool_trains_and_evaluates(tmp_path):
    bag = write_rosbags_bag(tmp_path / "robot_bag", make_steps(2, 16, context={"m": 1.0}), ROBOT)
    assert (bag / "metadata.yaml").exists()
    run_dir = tmp_path / "run"
    topic_args = [x for k, t in ROBOT.items() for x in ("--topic", f"{k}={t}")]
    r = run_cli("trainer.train", "--logs", bag, *topic_args, "--task", "pendulum_swingup", *TINY,
                "--updates", "3", "--run-dir", run_dir, "--cache-dir", tmp_path / "cache", "--log-every", "1")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "2 episodes" in r.stdout and "/robot/camera as image x32" in r.stdout
    assert "finished at update 3" in r.stdout
    ck = run_dir / "checkpoints" / "latest.pt"
    assert ckpt_counters(ck)["agent_updates"] == 3
    assert [m["update"] for m in metrics(run_dir)] == [1, 2, 3]
    assert (run_dir / "config.yaml").exists()
    # evaluate that checkpoint: one short episode of one test context
    out = tmp_path / "eval.json"
    r = run_cli("trainer.evaluate", ck, "--episodes", "1", "--context", "m=0.4", "--time-limit", "20",
                "--json", out, "--workers", "0")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "m=0.4" in r.stdout and "mean over contexts" in r.stdout
    res = json.loads(out.read_text())["results"][0]
    assert res["task"] == "pendulum_swingup" and res["per_context"][0]["episodes"] == 1
    # without the topic mapping the same log is rejected with the reason, exit code 2
    r = run_cli("trainer.train", "--logs", bag, *TINY, "--updates", "1", "--run-dir", tmp_path / "r2",
                "--cache-dir", tmp_path / "cache")
    assert r.returncode == 2 and "--topic KEY=/name" in r.stdout + r.stderr


def _train_proc(tmp_path: Path, bag: Path, run_dir: Path, *extra: str) -> subprocess.Popen:
    args = [sys.executable, "-m", "trainer.train", "--logs", str(bag), *TINY, "--run-dir", str(run_dir),
            "--cache-dir", str(tmp_path / "cache"), "--log-every", "1", "--seed", "5", *extra]
    return subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def test_resume_after_kill_continues_from_last_checkpoint(tmp_path):
    bag = write_bag(tmp_path / "bag", make_steps(3, 20))
    N = 8
    # reference: an uninterrupted run
    ref_dir = tmp_path / "ref"
    p = _train_proc(tmp_path, bag, ref_dir, "--updates", str(N), "--checkpoint-every", "2")
    assert p.wait(240) == 0, p.stdout.read()
    ref = {m["update"]: m for m in metrics(ref_dir)}
    # the same run, SIGKILLed after its first checkpoint
    run_dir = tmp_path / "killed"
    p = _train_proc(tmp_path, bag, run_dir, "--updates", "1000", "--checkpoint-every", "2")
    ck = run_dir / "checkpoints" / "latest.pt"
    wait_for(ck.exists, 240, "the first checkpoint")
    os.killpg(p.pid, signal.SIGKILL)
    p.wait(30)
    saved = ckpt_counters(ck)
    k = saved["agent_updates"]
    assert k >= 2 and k % 2 == 0 and saved["updates"] == k
    # resume: continues at k with the same counters and draws the same batches as `ref`
    r = run_cli("trainer.train", "--run-dir", run_dir, "--resume", "--updates", str(N))
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"resuming {run_dir} at update {k}" in r.stdout
    got = {m["update"]: m for m in metrics(run_dir)}
    assert sorted(got) == list(range(1, N + 1))          # no update lost or logged twice
    for u in range(k + 1, N + 1):
        assert got[u]["batch_crc"] == ref[u]["batch_crc"], f"update {u} drew another batch"
        assert got[u]["wm_loss"] == pytest.approx(ref[u]["wm_loss"], rel=1e-4)
    final = ckpt_counters(ck)
    assert final["agent_updates"] == N and final["updates"] == N


def test_ctrl_c_saves_a_checkpoint_and_exits_0(tmp_path):
    bag = write_bag(tmp_path / "bag", make_steps(2, 20))
    run_dir = tmp_path / "run"
    p = _train_proc(tmp_path, bag, run_dir, "--updates", "100000", "--checkpoint-every", "1000")
    wait_for(lambda: (run_dir / "metrics.jsonl").exists() and metrics(run_dir), 240, "training to start")
    os.killpg(p.pid, signal.SIGINT)
    out, _ = p.communicate(timeout=120)
    assert p.returncode == 0, out
    assert "interrupted at update" in out and "--resume" in out
    c = ckpt_counters(run_dir / "checkpoints" / "latest.pt")
    assert c["agent_updates"] >= 1 and c["agent_updates"] == metrics(run_dir)[-1]["update"]


def test_cli_help_and_errors(tmp_path):
    r = run_cli("trainer.train", "--help")
    assert r.returncode == 0
    for opt in ("--logs", "--task", "--variant", "--preset", "--config", "--set", "--updates", "--batch-size",
                "--seq-len", "--seed", "--device", "--run-dir", "--checkpoint-every", "--resume", "--topic"):
        assert opt in r.stdout
    r = run_cli("trainer.train", "--logs", tmp_path / "missing", "--run-dir", tmp_path / "x")
    assert r.returncode == 2 and "does not exist" in r.stderr
    bag = write_bag(tmp_path / "bag", make_steps(1, 4))
    r = run_cli("trainer.train", "--logs", bag, *TINY, "--set", "world_model.nope=1", "--run-dir", tmp_path / "y")
    assert r.returncode == 2 and "nope" in r.stderr
    r = run_cli("trainer.train", "--logs", bag, *TINY, "--run-dir", tmp_path / "z", "--cache-dir", tmp_path / "c")
    assert r.returncode == 2 and "no window of 8 steps" in r.stderr


def test_resume_and_new_run_dirs_are_checked_by_every_command(tmp_path):
    (tmp_path / "ckpt_only" / "checkpoints").mkdir(parents=True)
    (tmp_path / "ckpt_only" / "checkpoints" / "latest.pt").write_bytes(b"")
    for module in ("trainer.train", "trainer.online", "trainer.loop"):
        r = run_cli(module, "--resume")
        assert r.returncode == 2 and "--resume needs --run-dir" in r.stderr, (module, r.stderr)
        r = run_cli(module, "--resume", "--run-dir", tmp_path / "nowhere")
        assert r.returncode == 2 and "is not a directory" in r.stderr, (module, r.stderr)
        assert "Traceback" not in r.stderr
    # online and loop need their run.json (the protocol); train can do without it.
    for module in ("trainer.online", "trainer.loop"):
        r = run_cli(module, "--resume", "--run-dir", tmp_path / "ckpt_only")
        assert r.returncode == 2 and "run.json is missing" in r.stderr, (module, r.stderr)
    # A fresh run never overwrites one that is there.
    r = run_cli("trainer.online", "--run-dir", tmp_path / "ckpt_only", *TINY)
    assert r.returncode == 2 and "already holds a run" in r.stderr, r.stderr
