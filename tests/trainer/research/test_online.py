"""protocad-online end to end on the CPU (tiny model, short episodes): it runs, writes MCAP bags
that another reader accepts and that the dataset reads like the ROS path's, a checkpoint and
evaluation JSON, and resumes. Whether it learns is shown by the documented experiment
(README), not here."""
from __future__ import annotations

import json

import pytest
from helpers.bags import TINY, run_cli

ARGS = ["--task", "pendulum_swingup", *TINY, "--time-limit", "40", "--prefill-episodes", "2",
        "--updates-per-episode", "2", "--eval-every", "80", "--eval-episodes", "1", "--final-episodes", "1",
        "--eval-max-contexts", "2", "--eval-workers", "0", "--log-every", "1", "--no-progress"]


@pytest.mark.process
def test_online_runs_end_to_end_and_resumes(tmp_path):
    run = tmp_path / "run"
    r = run_cli("trainer.research.online", *ARGS, "--env-steps", "160", "--num-envs", "2", "--run-dir", run,
                "--random-baseline", "--final-train-contexts", timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "finished: 160 env steps, 4 episodes" in r.stdout
    # the freeze is a tenth of the planned updates (6, below), recorded where results read it
    info = json.loads((run / "run.json").read_text())
    assert info["result"]["prototype_freeze"] == 1 and "prototypes frozen for the first 1 updates" in r.stdout
    from trainer.research.results_json import gather_run

    row = gather_run("pendulum_swingup", "protocad", "protocad", 0, run)
    assert (row["prototype_freeze"], row["collect_interval"]) == (1, 2)
    assert len(row["final_train"]["per_context"]) == 11 and row["final_train"]["episodes"] == 11
    bags = sorted(p for p in (run / "bags").iterdir())
    assert len(bags) == 4                                # one bag per episode per env
    # the bags are real MCAP: the mcap library's own reader with the ros2 decoder reads them
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(next(bags[0].glob("*.mcap")), "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        seen = {}
        for _s, ch, _m, msg in reader.iter_decoded_messages():
            seen.setdefault(ch.topic, msg)
    assert seen["/protocad/image"].encoding == "rgb8" and seen["/protocad/image"].height == 64
    assert list(seen["/protocad/step_info"].name)[:2] == ["reward", "discount"]
    assert "/protocad/action" in seen and "/protocad/context" in seen and "/clock" in seen
    # ... and the dataset rebuilds complete episodes from them, with no problem reported
    from trainer.data.dataset import MCAPDataset

    ds = MCAPDataset([run / "bags"], seq_len=8, cache_dir=tmp_path / "cache")
    assert ds.num_episodes == 4 and not ds.report.problems()
    assert all(e["has_first"] and e["has_last"] and e["length"] == 21 and e["split"] == "train"
               for e in ds.episodes())
    # checkpoint + evaluation JSON (periodic, final, random baseline)
    from protocad_ros.checkpoint.agent_file import read_checkpoint

    c = read_checkpoint(run / "checkpoints" / "latest.pt")["counters"]
    assert c["env_steps"] == 160 and c["episodes"] == 4
    # C updates after the prefill, then C per collected episode: 2 + 2 * 2
    assert int(read_checkpoint(run / "checkpoints" / "latest.pt")["modules"]["updates"]) == 6
    evals = [json.loads(line) for line in (run / "eval.jsonl").read_text().splitlines()]
    assert [e["tag"] for e in evals] == ["eval_00000080", "final"]   # at the budget: only the final one
    final = json.loads((run / "eval" / "final.json").read_text())
    assert final["split"] == "test" and len(final["per_context"]) == 8     # final: every test context
    assert len(json.loads((run / "eval" / "random.json").read_text())["per_context"]) == 8
    # resume with a larger budget: continues the counters, appends bags
    r = run_cli("trainer.research.online", "--run-dir", run, "--resume", "--env-steps", "200", "--no-progress",
                "--eval-workers", "0", timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "resuming" in r.stdout and "finished: 200 env steps" in r.stdout
    # run.json keeps the original command and appends the resume's
    info = json.loads((run / "run.json").read_text())
    assert "--random-baseline" in info["args"] and "--num-envs" in info["args"]
    assert len(info["resumes_argv"]) == 1 and "--resume" in info["resumes_argv"][0]
    # two more bags, one per env, each a partial episode (the budget ends mid-episode): kept,
    # and read as episodes without is_last
    ds = MCAPDataset([run / "bags"], seq_len=8, cache_dir=tmp_path / "cache")
    assert len(ds.stores) == 6 and not ds.report.problems()
    assert sorted(e["has_last"] for e in ds.episodes()) == [False, False, True, True, True, True]


def test_resume_keeps_the_original_options_unless_given_again(tmp_path):
    from trainer.research.online import parse_args

    run = tmp_path / "run"
    run.mkdir()
    # a run.json from before settings were saved: its command line
    (run / "run.json").write_text(json.dumps({"args": ["--eval-max-contexts", "1", "--log-every", "1",
                                                       "--task", "walker_walk", "--run-dir", str(run)]}))
    s, model, _ = parse_args(["--run-dir", str(run), "--resume", "--log-every", "5"])
    assert (s.eval_max_contexts, s.log_every, model.task, s.resume) == (1, 5, "walker_walk", True)
    # one with its settings saved (what runs write now): the same rule
    (run / "run.json").write_text(json.dumps({"settings": {
        "online": {"eval_max_contexts": 3, "log_every": 1, "wall_budget": 60.0, "run_dir": str(run)},
        "model": {"task": "cheetah_run", "threads": 1}}}))
    s, model, _ = parse_args(["--run-dir", str(run), "--resume", "--threads", "2"])
    assert (s.eval_max_contexts, s.log_every, s.wall_budget, s.resume) == (3, 1, 60.0, True)
    assert (model.task, model.threads) == ("cheetah_run", 2)
    # a run.json edited out of shape: one line, exit 2, nothing touched
    from trainer.research.online import main

    (run / "run.json").write_text(json.dumps({"settings": ["not", "a", "mapping"]}))
    assert main(["--run-dir", str(run), "--resume"]) == 2
    assert json.loads((run / "run.json").read_text()) == {"settings": ["not", "a", "mapping"]}


def test_defaults_quoted_in_help_are_the_configs():
    """'(default train.X = V)' in a command's --help is what the config tree holds."""
    import re

    from protocad_ros.model.config import make_config
    from protocad_ros.model.hyperparameters import DEFAULT_CLI_PRESET
    from trainer.launch.loop import DEMO
    from trainer.launch.loop import build_parser as loop_parser
    from trainer.research.online import build_parser as online_parser

    cfg = make_config("pendulum_swingup", DEFAULT_CLI_PRESET, "protocad")
    quoted = 0
    for ap in (loop_parser(), online_parser()):
        text = " ".join(ap.format_help().split())
        for key, value in re.findall(r"default train\.(\w+) = (\d+)", text):
            assert getattr(cfg.train, key) == int(value), (ap.prog, key, value)
            quoted += 1
    assert quoted >= 4
    loop_help = " ".join(loop_parser().format_help().split())
    assert f"demo {DEMO['updates_per_episode']}" in loop_help
    online_help = " ".join(online_parser().format_help().split())
    assert "(default: auto)" in online_help and "float32 (default" not in online_help


def _bag_count(run) -> int:
    bags = run / "bags"
    return sum(1 for p in bags.iterdir() if p.is_dir()) if bags.is_dir() else 0


@pytest.mark.process
def test_sigkill_at_any_point_then_resume_completes_with_counters_from_the_data(tmp_path, spawn):
    """Five SIGKILLs in a row (before the first checkpoint, right after a resume, after a
    checkpoint, mid-collection), then a resume to completion: the counters are the bags' steps,
    no metrics row is repeated, no temporary or reserve file is left."""
    import re
    import signal

    from helpers import wait_until

    from protocad_ros.checkpoint.agent_file import read_checkpoint
    from trainer.data.dataset import MCAPDataset
    from trainer.research.online_rundir import data_counts

    run = tmp_path / "run"
    args = ["-m", "trainer.research.online", "--task", "pendulum_swingup", *TINY, "--time-limit", "40",
            "--prefill-episodes", "2", "--updates-per-episode", "2", "--eval-every", "0",
            "--final-episodes", "1", "--final-max-contexts", "1", "--eval-workers", "0",
            "--log-every", "1", "--no-progress", "--env-steps", "1600", "--run-dir", str(run)]
    resume = ["-m", "trainer.research.online", "--run-dir", str(run), "--resume", "--no-progress"]
    ckpt = run / "checkpoints" / "latest.pt"

    def kill_when(proc, ready, what):
        wait_until(lambda: ready() or not proc.alive(), 240, what)
        assert proc.alive(), proc.output()[-3000:]
        proc.stop(signal.SIGKILL)

    # 1: before the first checkpoint (prefill bags only, none checkpointed)
    p = spawn("a1", *args, "--checkpoint-every", "1000")
    kill_when(p, lambda: _bag_count(run) >= 2, "two bags of the first attempt")
    assert not ckpt.exists()
    # 2: right after a resume (from the bags alone), 3: again at once
    for name in ("a2", "a3"):
        p = spawn(name, *resume)
        kill_when(p, lambda: "resuming" in p.output(), "the resume to start")
    # 4: after a checkpoint was written
    p = spawn("a4", *resume, "--checkpoint-every", "1")
    kill_when(p, lambda: ckpt.exists(), "a checkpoint")
    # 5: mid-collection, two more bags later
    n = _bag_count(run)
    p = spawn("a5", *resume)
    kill_when(p, lambda: _bag_count(run) >= n + 2, "two more bags")
    # then to completion
    p = spawn("a6", *resume)
    wait_until(lambda: not p.alive(), 400, "the final resume to finish")
    log = p.output()
    assert p.p.returncode == 0, log[-3000:]
    assert "finished: " in log

    counters = read_checkpoint(ckpt)["counters"]
    steps, episodes = data_counts(MCAPDataset([run / "bags"], seq_len=8, cache_dir=tmp_path / "cache"))
    assert counters["env_steps"] == 2 * steps >= 1600 and counters["episodes"] == episodes
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]
    train = [r["update"] for r in rows if r.get("kind") == "train"]
    assert len(train) == len(set(train)), "a train row logged twice"
    eps = [r["episodes"] for r in rows if r.get("kind") == "episode"]
    assert len(eps) == len(set(eps)), "an episode row logged twice"
    names = [q.name for q in run.rglob("*")]
    assert not [x for x in names if x.endswith(".tmp") or ".tmp-" in x or x == ".protocad-reserve"], names
    bag_names = sorted(q.name for q in (run / "bags").iterdir())
    assert len(bag_names) == len(set(bag_names)) and all(re.match(r"ep\d{6}_env0_a\d", b) for b in bag_names)


@pytest.mark.process
def test_ctrl_c_while_training_costs_the_run_neither_updates_nor_an_evaluation(tmp_path, spawn):
    """Ctrl-C in the updates that follow an episode (an evaluation due after them): the resume
    first makes the owed updates and the evaluation, at the step it was due, and only then
    collects the next episode, as if nothing had happened. Ctrl-C again in the updates after
    the last episode (the budget reached): the final evaluation is of all the updates."""
    import signal

    from helpers import wait_until

    from protocad_ros.checkpoint.agent_file import read_checkpoint

    run = tmp_path / "run"
    # 40 env steps per episode, prefill 2, C = 100: 100 updates after episode 2, 200 after
    # episode 3, whose 120 env steps make an evaluation due; the budget ends with episode 4.
    # (C is the window each Ctrl-C must land in: 100 tiny updates, a second or more.)
    args = ["-m", "trainer.research.online", "--task", "pendulum_swingup", *TINY, "--time-limit", "40",
            "--prefill-episodes", "2", "--updates-per-episode", "100", "--eval-every", "120",
            "--eval-episodes", "1", "--eval-max-contexts", "1", "--final-episodes", "1",
            "--final-max-contexts", "1", "--eval-workers", "0", "--log-every", "1", "--no-progress",
            "--env-steps", "160", "--run-dir", str(run)]

    def rows():
        text = (run / "metrics.jsonl").read_text() if (run / "metrics.jsonl").exists() else ""
        return [json.loads(x) for x in text.splitlines()[:-1]]   # the last line may be half written

    p = spawn("first", *args)
    wait_until(lambda: any(r.get("kind") == "train" and r.get("env_steps") == 120 for r in rows())
               or not p.alive(), 300, "the updates after episode 3")
    assert p.stop(signal.SIGINT, timeout=120) == 0, p.output()[-3000:]
    assert json.loads((run / "run.json").read_text())["result"]["status"] == "interrupted"
    cut = int(read_checkpoint(run / "checkpoints" / "latest.pt")["modules"]["updates"])
    logged = (run / "eval.jsonl").read_text() if (run / "eval.jsonl").exists() else ""
    assert cut < 200 or "eval_00000120" not in logged, "the interruption came too late to test anything"

    resume = ["-m", "trainer.research.online", "--run-dir", str(run), "--resume", "--no-progress"]
    p = spawn("second", *resume)
    wait_until(lambda: any(r.get("kind") == "train" and r.get("env_steps") == 160 for r in rows())
               or not p.alive(), 300, "the updates after episode 4")
    assert p.stop(signal.SIGINT, timeout=120) == 0, p.output()[-3000:]
    cut = int(read_checkpoint(run / "checkpoints" / "latest.pt")["modules"]["updates"])
    assert cut < 300 and not (run / "eval" / "final.json").exists(), "the interruption came too late"

    r = run_cli("trainer.research.online", *resume[2:], timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    evals = [json.loads(x) for x in (run / "eval.jsonl").read_text().splitlines()]
    assert [(e["tag"], e["env_steps"], e["updates"]) for e in evals] == [
        ("eval_00000120", 120, 200), ("final", 160, 300)]
    assert int(read_checkpoint(run / "checkpoints" / "latest.pt")["modules"]["updates"]) == 300
    episode4 = [r for r in rows() if r.get("kind") == "episode" and r["episodes"] == 4]
    assert [r["update"] for r in episode4] == [200]   # collected by the agent of all 200 updates


@pytest.mark.process
@pytest.mark.disk_size("1m")
@pytest.mark.parametrize("full", ["run_dir", "cache"])
def test_a_full_disk_is_one_line_with_the_cause_and_the_run_resumes_after_space_is_freed(tmp_path, small_disk, full):
    disk, grow = small_disk.path, small_disk.grow
    run = disk / "run" if full == "run_dir" else tmp_path / "run"
    cache = tmp_path / "cache" if full == "run_dir" else disk / "cache"
    args = ["--task", "pendulum_swingup", *TINY, "--time-limit", "40", "--prefill-episodes", "2",
            "--updates-per-episode", "2", "--eval-every", "0", "--final-episodes", "1",
            "--final-max-contexts", "1", "--eval-workers", "0", "--no-progress", "--env-steps", "240",
            "--run-dir", run, "--cache-dir", cache]
    r = run_cli("trainer.research.online", *args, timeout=300)
    assert r.returncode == 1, r.stdout + r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("protocad-online: error:")]
    assert len(errors) == 1 and "No space left on device" in errors[0], r.stderr
    assert "Traceback" not in r.stderr
    if full == "cache":
        assert str(cache) in errors[0]
    # what is said of the checkpoint is true
    ckpt = run / "checkpoints" / "latest.pt"
    if "no earlier checkpoint" in r.stderr:
        assert not ckpt.exists()
    if "the last good checkpoint there is intact" in r.stderr:
        assert ckpt.exists()
    grow()   # free space, then the same run to completion
    r = run_cli("trainer.research.online", "--run-dir", run, "--resume", "--no-progress", timeout=300)
    assert r.returncode == 0 and "finished: 240 env steps" in r.stdout, r.stdout + r.stderr


@pytest.mark.process
def test_a_run_whose_prototypes_would_stay_frozen_is_refused_before_it_starts(tmp_path):
    run = tmp_path / "run"
    # 6 planned updates (4 episodes of 40 env steps, N=2, C=2), a freeze of 100: never trained
    r = run_cli("trainer.research.online", *ARGS, "--env-steps", "160", "--num-envs", "2", "--run-dir", run,
                "--set", "context.freeze_prototypes_updates=100", timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "frozen for 6 of this run's 6 updates" in lines[0], r.stderr
    assert not run.exists()                  # nothing to clean up


@pytest.mark.process
def test_a_run_starts_from_a_policy_file_and_may_change_only_what_its_projector_reads(tmp_path):
    """--init-policy: the policy's networks and weights (fresh optimizers, updates counted from
    0), the run's options on top; context.projector_input may change (the projector alone starts
    fresh, said in one line); an option that changes any other network is refused before a run
    directory exists."""

    from protocad_ros.checkpoint.agent_file import read_checkpoint

    trained = tmp_path / "trained"
    short = [*ARGS, "--env-steps", "80", "--eval-every", "0", "--final-max-contexts", "1"]
    r = run_cli("trainer.research.online", *short, "--run-dir", trained, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    policy = read_checkpoint(trained / "checkpoints" / "latest.pt")
    assert policy["config"]["context"]["projector_input"] == "h"

    run = tmp_path / "from_policy"
    r = run_cli("trainer.research.online", "--init-policy", trained, "--set", "context.projector_input=s",
                "--seed", "3", "--time-limit", "40", "--prefill-episodes", "2", "--updates-per-episode", "2",
                "--env-steps", "80", "--eval-every", "0", "--final-max-contexts", "1", "--final-episodes", "1",
                "--eval-workers", "0", "--threads", "1", "--log-every", "1", "--no-progress", "--run-dir", run,
                timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "context.projector_input differs from the policy's" in r.stdout
    # the prototypes' drift is measured from the policy's, where this run started (a fresh
    # seeded draw would sit near cosine 0 to them)
    health = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [h["proto_init_cosine"] for h in health if "proto_init_cosine" in h][-1] > 0.9
    ck = read_checkpoint(run / "checkpoints" / "latest.pt")
    assert ck["config"]["world_model"] == policy["config"]["world_model"]
    assert ck["config"]["context"]["projector_input"] == "s" and ck["config"]["train"]["seed"] == 3
    assert int(ck["modules"]["updates"]) == 2           # its own count, from 0
    from protocad_ros.atomic import file_sha256

    started = json.loads((run / "run.json").read_text())["init_policy"]   # the file by its content
    assert started["sha256"] == file_sha256(trained / "checkpoints" / "latest.pt")
    # two Adam steps from the policy's weights (each moves a weight by about lr at most), not
    # seed 3's fresh initialisation; the projector reads s = (z, h) now: a wider, new layer
    before, after = policy["modules"], ck["modules"]
    moved = (after["wm.encoder.convs.0.weight"].float() - before["wm.encoder.convs.0.weight"].float()).abs().max()
    assert 0 < moved < 0.01
    assert after["wm.context.prototypes"].shape == before["wm.context.prototypes"].shape
    assert after["wm.context.projector.weight"].shape[1] > before["wm.context.projector.weight"].shape[1]

    # a resume whose --init-policy file was replaced since (a shipped policy is) goes on from
    # its own checkpoint and says the drift is no longer measured from that file
    import shutil

    shutil.copyfile(run / "checkpoints" / "latest.pt", trained / "checkpoints" / "latest.pt")
    r = run_cli("trainer.research.online", "--run-dir", run, "--resume", "--env-steps", "120", "--no-progress",
                timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "changed since the run started" in r.stdout and "finished: 120 env steps" in r.stdout

    refused = tmp_path / "refused"
    bad = run_cli("trainer.research.online", "--init-policy", trained, "--set", "world_model.deter=64",
                  "--env-steps", "80", "--run-dir", refused, "--no-progress", timeout=120)
    assert bad.returncode == 2 and "world_model.deter: 32 != 64" in bad.stderr, bad.stderr
    assert not refused.exists()
