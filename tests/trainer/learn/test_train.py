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
import yaml
from helpers import ROOT, wait_until
from helpers.bags import TINY, make_steps, run_cli, write_bag, write_rosbags_bag
from helpers.training import ckpt_counters, metrics, train_proc

ROBOT = {"image": "/robot/camera", "step_info": "/robot/step", "action": "/robot/cmd", "context": "/robot/ctx"}


@pytest.mark.process
def test_log_from_another_tool_trains_and_evaluates(tmp_path):
    bag = write_rosbags_bag(tmp_path / "robot_bag", make_steps(2, 16, context={"m": 1.0}), ROBOT)
    assert (bag / "metadata.yaml").exists()
    run_dir = tmp_path / "run"
    topic_args = [x for k, t in ROBOT.items() for x in ("--topic", f"{k}={t}")]
    r = run_cli("trainer.learn.train", "--logs", bag, *topic_args, "--task", "pendulum_swingup", *TINY,
                "--updates", "3", "--run-dir", run_dir, "--cache-dir", tmp_path / "cache", "--log-every", "1")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "2 episodes" in r.stdout and "/robot/camera as image x32" in r.stdout
    assert "finished at update 3" in r.stdout
    ck = run_dir / "checkpoints" / "latest.pt"
    assert ckpt_counters(ck)["agent_updates"] == 3
    assert [m["update"] for m in metrics(run_dir)] == [1, 2, 3]
    # no terminal here: a line of losses instead of a progress bar, and TensorBoard event files
    assert "[train] update 1" in r.stdout and "wm_loss" in r.stdout
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    events = EventAccumulator(str(run_dir / "tensorboard"))
    events.Reload()
    assert [e.step for e in events.Scalars("train/wm_loss")] == [1, 2, 3]
    saved = yaml.safe_load((run_dir / "config.yaml").read_text())   # TINY's generated options and --set
    assert (saved["world_model"]["deter"], saved["behavior"]["critic_units"], saved["context"]["proto_dim"]) == (32, 32, 8)
    # evaluate that checkpoint: one short episode of one test context
    out = tmp_path / "eval.json"
    r = run_cli("trainer.learn.evaluate", ck, "--episodes", "1", "--context", "m=0.4", "--time-limit", "20",
                "--json", out, "--workers", "0")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "m=0.4" in r.stdout and "mean over contexts" in r.stdout
    res = json.loads(out.read_text())["results"][0]
    assert res["task"] == "pendulum_swingup" and res["per_context"][0]["episodes"] == 1
    # without the topic mapping the same log is rejected with the reason, exit code 2
    r = run_cli("trainer.learn.train", "--logs", bag, *TINY, "--updates", "1", "--run-dir", tmp_path / "r2",
                "--cache-dir", tmp_path / "cache")
    assert r.returncode == 2 and "--topic KEY=/name" in r.stdout + r.stderr


@pytest.mark.process
def test_resume_after_kill_continues_from_last_checkpoint(tmp_path):
    bag = write_bag(tmp_path / "bag", make_steps(3, 20))
    N = 8
    # reference: an uninterrupted run
    ref_dir = tmp_path / "ref"
    p = train_proc(tmp_path, bag, ref_dir, "--updates", str(N), "--checkpoint-every", "2")
    assert p.wait(240) == 0, p.stdout.read()
    ref = {m["update"]: m for m in metrics(ref_dir)}
    # the same run, SIGKILLed after its first checkpoint
    run_dir = tmp_path / "killed"
    p = train_proc(tmp_path, bag, run_dir, "--updates", "1000", "--checkpoint-every", "2")
    ck = run_dir / "checkpoints" / "latest.pt"
    wait_until(ck.exists, 240, "the first checkpoint")
    os.killpg(p.pid, signal.SIGKILL)
    p.wait(30)
    saved = ckpt_counters(ck)
    k = saved["agent_updates"]
    assert k >= 2 and k % 2 == 0 and saved["updates"] == k
    # resume: continues at k with the same counters and draws the same batches as `ref` (the
    # bags again on the command line: run.json's logs are read only inside the run directory)
    r = run_cli("trainer.learn.train", "--run-dir", run_dir, "--resume", "--updates", str(N), "--logs", bag)
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"resuming {run_dir} at update {k}" in r.stdout
    got = {m["update"]: m for m in metrics(run_dir)}
    assert sorted(got) == list(range(1, N + 1))          # no update lost or logged twice
    for u in range(k + 1, N + 1):
        assert got[u]["batch_crc"] == ref[u]["batch_crc"], f"update {u} drew another batch"
        assert got[u]["wm_loss"] == pytest.approx(ref[u]["wm_loss"], rel=1e-4)
    final = ckpt_counters(ck)
    assert final["agent_updates"] == N and final["updates"] == N


@pytest.mark.process
def test_ctrl_c_saves_a_checkpoint_and_exits_0(tmp_path):
    bag = write_bag(tmp_path / "bag", make_steps(2, 20))
    run_dir = tmp_path / "run"
    p = train_proc(tmp_path, bag, run_dir, "--updates", "100000", "--checkpoint-every", "1000")
    wait_until(lambda: (run_dir / "metrics.jsonl").exists() and metrics(run_dir), 240, "training to start")
    os.killpg(p.pid, signal.SIGINT)
    out, _ = p.communicate(timeout=120)
    assert p.returncode == 0, out
    assert "interrupted at update" in out and "--resume" in out
    c = ckpt_counters(run_dir / "checkpoints" / "latest.pt")
    assert c["agent_updates"] >= 1 and c["agent_updates"] == metrics(run_dir)[-1]["update"]


@pytest.mark.process
def test_cli_help_and_errors(tmp_path):
    r = run_cli("trainer.learn.train", "--help")
    assert r.returncode == 0
    for opt in ("--logs", "--task", "--variant", "--preset", "--config", "--set", "--updates", "--batch-size",
                "--seq-len", "--seed", "--device", "--run-dir", "--checkpoint-every", "--resume", "--topic"):
        assert opt in r.stdout
    r = run_cli("trainer.learn.train", "--logs", tmp_path / "missing", "--run-dir", tmp_path / "x")
    assert r.returncode == 2 and "does not exist" in r.stderr
    bag = write_bag(tmp_path / "bag", make_steps(1, 4))
    r = run_cli("trainer.learn.train", "--logs", bag, *TINY, "--set", "world_model.nope=1", "--run-dir", tmp_path / "y")
    assert r.returncode == 2 and "nope" in r.stderr
    r = run_cli("trainer.learn.train", "--logs", bag, *TINY, "--run-dir", tmp_path / "z", "--cache-dir", tmp_path / "c")
    assert r.returncode == 2 and "no window of 8 steps" in r.stderr


@pytest.mark.process
def test_resume_and_new_run_dirs_are_checked_by_every_command(tmp_path):
    (tmp_path / "ckpt_only" / "checkpoints").mkdir(parents=True)
    (tmp_path / "ckpt_only" / "checkpoints" / "latest.pt").write_bytes(b"")
    for module in ("trainer.learn.train", "trainer.research.online", "trainer.launch.loop"):
        r = run_cli(module, "--resume")
        assert r.returncode == 2 and "--resume needs --run-dir" in r.stderr, (module, r.stderr)
        r = run_cli(module, "--resume", "--run-dir", tmp_path / "nowhere")
        assert r.returncode == 2 and "is not a directory" in r.stderr, (module, r.stderr)
        assert "Traceback" not in r.stderr
    # online and loop need their run.json (the protocol); train can do without it.
    for module in ("trainer.research.online", "trainer.launch.loop"):
        r = run_cli(module, "--resume", "--run-dir", tmp_path / "ckpt_only")
        assert r.returncode == 2 and "run.json is missing" in r.stderr, (module, r.stderr)
    # A fresh run never overwrites one that is there.
    r = run_cli("trainer.research.online", "--run-dir", tmp_path / "ckpt_only", *TINY)
    assert r.returncode == 2 and "already holds a run" in r.stderr, r.stderr


def _help_entry(text: str, option: str) -> str:
    """The help text of one option in tyro's boxed listing (its lines up to the next option)."""
    lines = [ln.strip("│ ").strip() for ln in text.splitlines()]
    start = next(i for i, ln in enumerate(lines) if ln.startswith(option + " ") or ln == option
                 or ln.startswith(option + ","))
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("--")), len(lines))
    return " ".join(lines[start:end])


@pytest.mark.process
def test_every_config_field_is_an_option_with_the_configs_help_and_the_presets_default():
    import dataclasses

    from protocad_ros.model.config import make_config
    from trainer import run_config

    small, paper = run_cli("trainer.learn.train", "--help"), run_cli("trainer.learn.train", "--preset", "paper", "--help")
    assert small.returncode == paper.returncode == 0, small.stderr + paper.stderr
    cfg = make_config(preset="small")
    for section in (f for f in dataclasses.fields(cfg) if f.name not in run_config.OWN_FLAG_FIELDS):
        value = getattr(cfg, section.name)
        keys = [f"{section.name}.{f.name}" for f in dataclasses.fields(value)] if dataclasses.is_dataclass(value) \
            else [section.name]
        for key in keys:
            assert f"--{key}" in small.stdout, key
    # The default shown is the chosen preset's; the help is the field's comment in hyperparameters.py.
    assert "(default: 128)" in _help_entry(small.stdout, "--world_model.deter")
    assert "(default: 200)" in _help_entry(paper.stdout, "--world_model.deter")
    assert "paper B" in _help_entry(paper.stdout, "--train.batch_size")
    assert "(default: 16)" in _help_entry(paper.stdout, "--train.batch_size")


def test_config_options_set_what_set_and_the_file_set(tmp_path):
    from trainer import settings
    from trainer.learn.train import build_parser

    def config(*argv):
        parsed = settings.parse(build_parser(), [str(x) for x in argv])
        return parsed.get(settings.ModelChoice).to_config(parsed.config_args, parsed.prog)

    (tmp_path / "c.yaml").write_text("world_model: {deter: 40, hidden: 48}\n")
    cfg = config("--config", tmp_path / "c.yaml", "--set", "world_model.hidden=56", "--world_model.deter", "24",
                 "--world_model.no_gru_norm", "--behavior.horizon", "7", "--logs", "somewhere")
    assert (cfg.world_model.deter, cfg.world_model.hidden, cfg.world_model.gru_norm, cfg.behavior.horizon) == \
        (24, 56, False, 7)
    assert cfg.preset == "small" and config("--preset", "paper").world_model.deter == 200
    for bad in (["--world_model.nope", "1"], ["--world_model.deter", "many"]):
        with pytest.raises(SystemExit) as exit_:
            config(*bad)
        assert exit_.value.code == 2
    with pytest.raises(ValueError, match="train.precision"):
        config("--train.precision", "float8")


@pytest.mark.process
@pytest.mark.parametrize("local_ranks", [None, "2"])
def test_auto_threads_are_the_cores_shared_among_the_local_ranks(local_ranks):
    """--threads 0: torch's one thread per core, divided among torchrun's ranks on the machine;
    an explicit number wins, and auto after it comes back to the same share."""
    code = ("import torch; from trainer import torch_setup; d = torch.get_num_threads(); "
            "print(d, torch_setup.setup_torch(0), torch_setup.setup_torch(3), torch_setup.setup_torch(None))")
    env = {k: v for k, v in os.environ.items() if k != "LOCAL_WORLD_SIZE"}
    if local_ranks:
        env["LOCAL_WORLD_SIZE"] = local_ranks
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    default, auto, given, auto_again = map(int, r.stdout.split())
    share = max(1, default // int(local_ranks or 1))
    assert (auto, given, auto_again) == (share, 3, share)


def record_with_a_second_image_publisher(tmp_path: Path, steps: list[dict]) -> Path:
    """A bag recorded by trainer.nodes.recorder (its own process) from publishers in this process: the
    contract topics, plus a second, silent writer on /protocad/image (an impostor)."""
    import rclpy
    from helpers import Proc
    from rclpy.duration import Duration
    from rclpy.node import Node
    from sensor_msgs.msg import Image, JointState

    from sim_bridge.contract import qos
    from sim_bridge.contract import topics as T

    bag = tmp_path / "impostor_bag"
    rec = Proc([sys.executable, "-m", "trainer.nodes.recorder", "-o", str(bag), "-p", "100"], tmp_path / "recorder.log")
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node("train_test_publisher", namespace="/protocad", context=ctx)
    try:
        pubs = {rel: node.create_publisher(Image if rel == T.IMAGE else JointState, rel, qos.observation_qos(True))
                for rel in (T.IMAGE, T.STEP_INFO, T.CONTEXT, T.ACTION)}
        impostor = node.create_publisher(Image, T.IMAGE, qos.observation_qos(True))
        wait_until(lambda: all(p.get_subscription_count() for p in [*pubs.values(), impostor]), 90,
                 "the recorder to subscribe to every topic")
        for st in steps:
            s = st["stamp"]
            pubs[T.CONTEXT].publish(T.fill_context(JointState(), st["context"], st["split"], s))
            pubs[T.STEP_INFO].publish(T.fill_step_info(JointState(), T.StepInfo(
                st["reward"], 1.0, st["is_first"], st["is_last"], False, st["episode"], st["step"]), s))
            pubs[T.IMAGE].publish(T.fill_image(Image(), st["image"], s))
            pubs[T.ACTION].publish(T.fill_action(JointState(), st["action"], ["torque"], s))
        for p in pubs.values():
            assert p.wait_for_all_acked(Duration(seconds=30))
        assert rec.stop() == 0, rec.output()
    finally:
        rec.stop()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    assert "SEVERAL PUBLISHERS" in rec.output() and "/protocad/image: 2" in rec.output(), rec.output()
    return bag


@pytest.mark.ros
@pytest.mark.process
def test_a_bag_with_two_image_publishers_is_refused_unless_accepted(tmp_path):
    bag = record_with_a_second_image_publisher(tmp_path, make_steps(2, 12))
    custom = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["custom_data"]
    assert json.loads(custom["protocad_multiple_publishers"]) == {"/protocad/image": 2}
    args = ["--logs", bag, "--task", "pendulum_swingup", *TINY, "--updates", "1", "--cache-dir", tmp_path / "cache"]
    r = run_cli("trainer.learn.train", *args, "--run-dir", tmp_path / "refused")
    assert r.returncode == 2, r.stdout + r.stderr
    line = [x for x in r.stderr.splitlines() if "error" in x]
    assert len(line) == 1 and str(bag) in line[0] and "/protocad/image had 2 publishers" in line[0] \
        and "--accept-multiple-publishers" in line[0], r.stderr
    r = run_cli("trainer.learn.train", *args, "--run-dir", tmp_path / "accepted", "--accept-multiple-publishers")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "finished at update 1" in r.stdout
    assert "the recorder reported multiple publishers" in r.stdout   # and the dataset report says why


@pytest.mark.process
def test_logs_with_test_split_episodes_are_refused_unless_accepted(tmp_path):
    bag = write_bag(tmp_path / "bag", make_steps(2, 12, split="test"))
    args = ["--logs", bag, "--task", "pendulum_swingup", *TINY, "--updates", "1", "--cache-dir", tmp_path / "cache"]
    r = run_cli("trainer.learn.train", *args, "--run-dir", tmp_path / "refused")
    assert r.returncode == 2, r.stdout + r.stderr
    line = [x for x in r.stderr.splitlines() if "error" in x]
    assert len(line) == 1 and "2 episode(s) of the test split" in line[0] and "--accept-test-split" in line[0]
    r = run_cli("trainer.learn.train", *args, "--run-dir", tmp_path / "accepted", "--accept-test-split")
    assert r.returncode == 0 and "WARNING: the logs hold 2 episode(s) of the test split" in r.stdout, r.stderr


def test_updates_that_end_on_a_checkpoint_multiple_are_saved_when_the_caller_saves_later(tmp_path):
    """protocad-online trains C updates per episode with save=False (it saves at evaluations):
    a checkpoint_every that divides C must still checkpoint each episode's updates, else a kill
    between evaluations loses them all (what C = 100 with --checkpoint-every 100 did)."""
    from protocad_ros.checkpoint.agent_file import read_checkpoint
    from protocad_ros.model.config import make_config
    from trainer.data.dataset import MCAPDataset
    from trainer.learn.trainer import Trainer

    write_bag(tmp_path / "bag", make_steps(2, 12))
    ds = MCAPDataset([tmp_path / "bag"], seq_len=8, cache_dir=tmp_path / "cache")
    cfg = make_config("pendulum_swingup", "small", "dreamer", **{
        "train.batch_size": 2, "train.seq_len": 8, "world_model.deter": 16, "world_model.hidden": 16,
        "world_model.cnn_depth": 4, "world_model.mlp_units": 16, "behavior.actor_units": 16,
        "behavior.critic_units": 16, "behavior.horizon": 3})
    tr = Trainer(cfg, tmp_path / "run", ds)

    def saved() -> int:
        return int(read_checkpoint(tr.checkpoint_path)["modules"]["updates"])

    assert tr.train(2, checkpoint_every=2, save=False) and saved() == 2
    assert tr.train(3, checkpoint_every=2, save=False) and saved() == 2    # 3 is no multiple: not saved
    assert tr.train(4, checkpoint_every=2) and saved() == 4
    tr.close()
