"""The learner on torch.distributed: `torchrun --nproc_per_node 2` with gloo on CPU, as a user
runs it (real processes, the documented command), against a single process."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import HELPERS, ROOT, wait_until
from helpers.agents import render_batch
from helpers.bags import TINY, make_steps, write_bag

from protocad_ros.checkpoint.agent_file import load_checkpoint, read_checkpoint
from protocad_ros.model.agent import make_agent
from protocad_ros.model.config import make_config
from trainer.learn import distributed

pytestmark = [pytest.mark.process, pytest.mark.usefixtures("one_torch_thread"),
              pytest.mark.skipif(not (Path(sys.executable).parent / "protocad-train").exists(),
                                 reason="protocad-ros is not installed in this Python (run scripts/protocad setup)")]
BIN = Path(sys.executable).parent
# The documented command (msgs_docs/training.md) as written: torchrun and protocad-train are the
# environment's console scripts (protocad-train runs this tree's code: conftest puts it on PYTHONPATH).
TORCHRUN = [str(BIN / "torchrun"), "--standalone", "--nproc_per_node", "2"]
TRAIN = ["--no-python", str(BIN / "protocad-train")]
# gloo on the loopback interface only (it would otherwise pick the host's first interface).
ENV = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    d = tmp_path_factory.mktemp("ddp_bags")
    for i in range(3):
        write_bag(d / f"ep{i}", make_steps(1, 40, first_episode=i))
    return d


def torchrun(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([*TORCHRUN, *args], capture_output=True, text=True, timeout=timeout,
                          cwd=ROOT, env=ENV)


def train_args(bags: Path, run_dir: Path, updates: int, *extra: str) -> list[str]:
    # --bags, not --logs: torchrun would take --logs as its own --logs-specs.
    return ["--bags", str(bags), "--task", "pendulum_swingup", "--preset", "small",
            "--updates", str(updates), "--run-dir", str(run_dir), "--no-progress",
            "--cache-dir", str(run_dir.parent / "cache"), *TINY, "--batch-size", "4",
            "--set", "behavior.slow_critic_update=2", *extra]


def test_two_ranks_hold_identical_weights_after_several_updates(bags, tmp_path):
    run = tmp_path / "r2"
    out = torchrun(*TRAIN, *train_args(bags, run, 6, "--checkpoint-every", "3"))
    assert out.returncode == 0, out.stdout + out.stderr
    ckpt = read_checkpoint(run / "checkpoints" / "latest.pt")
    counters = ckpt["counters"]
    assert counters["world_size"] == 2 and counters["updates"] == 6
    ranks = json.loads(counters["rank_states"])
    assert len(ranks) == 2 and ranks[0]["dataset"] != ranks[1]["dataset"]   # own samplers
    assert ranks[0]["torch_rng"] != ranks[1]["torch_rng"]                    # own augmentation
    # Each rank fingerprinted its own weights; rank 0's are the checkpoint's.
    prints = ckpt["counters"]["rank_fingerprints"]
    prints = json.loads(prints)
    assert prints[0] == prints[1]
    for part in ("wm.encoder", "wm.rssm", "wm.context", "wm.decoder", "ac.actor", "ac.critic",
                 "ac.slow_critic"):
        assert part in prints[0]
    agent, _ = load_checkpoint(run / "checkpoints" / "latest.pt")
    assert distributed.fingerprints(agent) == prints[0]
    # ... and they are trained weights: a fresh agent of the same config differs in every part.
    fresh = distributed.fingerprints(make_agent(agent.cfg, 1))
    assert all(fresh[k] != prints[0][k] for k in ("wm.encoder", "wm.context", "ac.actor",
                                                  "ac.critic", "ac.slow_critic"))
    metrics = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [m["update"] for m in metrics if m.get("kind") == "train"][-1] == 6   # rank 0 only
    assert "2 ranks hold identical weights at update 6" in out.stdout


def test_first_update_gradients_are_the_single_process_average(tmp_path):
    """Rank r trains on half r of a batch with seed 100 + r; after the all-reduce both hold
    (g_0 + g_1) / 2, where g_r is the single-process gradient of that half with that seed.
    (The world model's learning rate is 0 so that the imagination the actor and critic learn
    from is the same with and without averaging; their gradients are compared too.)"""
    cfg = make_config("pendulum_swingup", "small", "protocad", **{
        "world_model.deter": 32, "world_model.hidden": 32, "world_model.stoch": 8,
        "world_model.cnn_depth": 8, "world_model.mlp_units": 32, "behavior.actor_units": 32,
        "behavior.critic_units": 32, "context.num_prototypes": 8, "behavior.horizon": 5,
        "train.batch_size": 4, "train.seq_len": 8, "world_model.lr": 0.0,
        "world_model.weight_decay": 0.0})
    cfg.save(tmp_path / "config.yaml")
    batch = render_batch("pendulum_swingup", batch=4, length=8, seed=3)
    np.savez(tmp_path / "batch.npz", **batch)
    out = torchrun(str(HELPERS / "ddp_grad_worker.py"), str(tmp_path))
    assert out.returncode == 0, out.stdout + out.stderr
    g0, g1 = (torch.load(tmp_path / f"grads_rank{r}.pt") for r in (0, 1))

    local = []
    for r in (0, 1):
        agent = make_agent(cfg, 1)
        names = {id(p): n for n, p in agent.named_parameters()}
        grads: dict[str, torch.Tensor] = {}
        agent.grad_sync = lambda ps, g=grads: g.update(
            {names[id(p)]: p.grad.detach().clone() for p in ps if p.grad is not None})
        torch.manual_seed(100 + r)
        agent.train_step({k: v[2 * r:2 * r + 2] for k, v in batch.items()})
        local.append(grads)
    assert set(g0) == set(g1) == set(local[0]) and len(g0) > 20
    assert any(n.startswith("ac.actor") for n in g0) and any("context" in n for n in g0)
    for name in g0:
        assert torch.equal(g0[name], g1[name]), name                     # identical on both ranks
        expected = (local[0][name] + local[1][name]) / 2
        torch.testing.assert_close(g0[name], expected, rtol=1e-4, atol=1e-6, msg=name)
    assert any(not torch.allclose(local[0][n], local[1][n]) for n in g0)  # the halves differ


@pytest.mark.parametrize("code", [0, 3])
def test_a_finished_rank_ends_with_its_code_and_its_output(code):
    # Ranks end by os._exit past the closing barrier (distributed.leave): what they printed
    # must still reach the pipe, and the body's exit code must be the process's. Buffered
    # stdout, as the console scripts have it: --no-python (torchrun runs a script with -u) and
    # no PYTHONUNBUFFERED (the suite's environment sets it).
    env = {k: v for k, v in ENV.items() if k != "PYTHONUNBUFFERED"}
    out = subprocess.run([*TORCHRUN, "--no-python", sys.executable, str(HELPERS / "ddp_leave_worker.py"), str(code)],
                         capture_output=True, text=True, timeout=240, cwd=ROOT, env=env)
    for rank in (0, 1):
        assert f"rank {rank} of 2 finished" in out.stdout, out.stdout + out.stderr
    if code == 0:
        assert out.returncode == 0, out.stdout + out.stderr
    else:
        assert out.returncode != 0 and f"exitcode  : {code}" in out.stderr, out.stderr


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def wait_gone(pids: list[int], timeout: float = 30) -> None:
    wait_until(lambda: not any(Path(f"/proc/{p}").exists() for p in pids), timeout, f"{pids} to exit", 0.1)


def _counters(path: Path) -> dict:
    try:
        return read_checkpoint(path)["counters"]
    except Exception:   # noqa: BLE001 - not written yet
        return {}


def test_a_killed_two_rank_run_resumes_with_two_ranks_and_with_one(bags, tmp_path):
    run = tmp_path / "killed"
    ckpt = run / "checkpoints" / "latest.pt"
    proc = subprocess.Popen([*TORCHRUN, *TRAIN, *train_args(bags, run, 400, "--checkpoint-every", "2")],
                            cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)
    try:
        wait_until(lambda: proc.poll() is not None or _counters(ckpt).get("updates", 0) >= 4, 180,
                   "a checkpoint at update 4", 0.2)
        assert proc.poll() is None, proc.stdout.read()
        ranks = _children(proc.pid)
        assert len(ranks) == 2, ranks
    finally:
        for pid in [proc.pid, *_children(proc.pid)]:   # the launcher and both ranks, at once
            os.kill(pid, signal.SIGKILL)
        proc.wait(30)
    wait_gone(ranks)
    at_kill = _counters(ckpt)["updates"]
    assert 4 <= at_kill < 400

    # The bags given again: a resume reads run.json's logs only inside the run directory.
    resumed = torchrun(*TRAIN, "--run-dir", str(run), "--resume", "--updates", str(at_kill + 4),
                       "--no-progress", "--threads", "1", "--bags", str(bags))
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    assert f"resuming {run} at update {at_kill}" in resumed.stdout
    c = _counters(ckpt)
    assert c["updates"] == at_kill + 4 and c["world_size"] == 2
    train_rows = [json.loads(x)["update"] for x in (run / "metrics.jsonl").read_text().splitlines()
                  if json.loads(x).get("kind") == "train"]
    assert train_rows == sorted(set(train_rows))     # nothing logged twice across the kill

    # The same run on one process (any N resumes): rank 0's weights, fresh draws.
    one = subprocess.run([sys.executable, "-m", "trainer.learn.train", "--run-dir", str(run), "--resume",
                          "--updates", str(at_kill + 6), "--no-progress", "--threads", "1", "--logs", str(bags)],
                         capture_output=True, text=True, timeout=240, cwd=ROOT, env=ENV)
    assert one.returncode == 0, one.stdout + one.stderr
    assert _counters(ckpt)["updates"] == at_kill + 6 and "world_size" not in _counters(ckpt)


def test_torchrun_takes_logs_as_its_own_option_so_the_docs_say_bags():
    """Why the documented command writes --bags: torchrun's parser matches --logs to its own
    --logs-specs even after the script. If a torch release stops doing that, this fails and
    --logs can be documented again."""
    out = torchrun("--no-python", "true", "--logs", "x", timeout=60)
    assert out.returncode != 0 and "ambiguous option: --logs" in out.stderr


def test_protocad_online_on_two_ranks_collects_on_each_and_resumes_on_one(tmp_path):
    run = tmp_path / "online"
    tiny = ["--set", "world_model.deter=32", "--set", "world_model.hidden=32", "--set",
            "world_model.cnn_depth=8", "--set", "context.num_prototypes=8", "--set",
            "train.batch_size=4", "--set", "train.seq_len=16", "--threads", "1"]
    args = ["--task", "pendulum_swingup", "--preset", "small", "--time-limit", "200",
            "--prefill-episodes", "2", "--updates-per-episode", "3", "--eval-every", "0",
            "--eval-episodes", "1", "--final-episodes", "1", "--final-max-contexts", "1", "--run-dir", str(run),
            "--no-progress", *tiny]
    out = torchrun("--no-python", str(BIN / "protocad-online"), "--env-steps", "1200", *args)
    assert out.returncode == 0, out.stdout + out.stderr
    bags = sorted(p.name for p in (run / "bags").iterdir())
    assert len(bags) == 6 and sum(b.endswith("_rank1") for b in bags) == 3   # 3 episodes each
    result = json.loads((run / "run.json").read_text())["result"]
    assert result["status"] == "finished" and result["env_steps"] == 1200
    assert result["updates"] == 3 + 3 * 4        # C after the 2 prefill episodes, C per episode
    prints = json.loads(read_checkpoint(run / "checkpoints" / "latest.pt")["counters"]["rank_fingerprints"])
    assert prints[0] == prints[1]
    assert (run / "eval" / "final.json").exists()
    one = subprocess.run([sys.executable, "-m", "trainer.research.online", "--run-dir", str(run), "--resume",
                          "--env-steps", "1600", "--no-progress", "--threads", "1"],
                         capture_output=True, text=True, timeout=240, cwd=ROOT, env=ENV)
    assert one.returncode == 0, one.stdout + one.stderr
    result = json.loads((run / "run.json").read_text())["result"]
    assert result["status"] == "finished" and result["env_steps"] == 1600
    assert "6 bags" in one.stdout                 # one process replays every rank's bags
