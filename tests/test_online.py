"""protocad-online end to end on the CPU (tiny model, short episodes): it runs, writes MCAP bags
that another reader accepts and that the dataset reads like the ROS path's, a checkpoint and
evaluation JSON, and resumes. Whether it learns is shown by the documented experiment
(README), not here."""
from __future__ import annotations

import json

from trainer_bags import TINY, run_cli

ARGS = ["--task", "pendulum_swingup", *TINY, "--time-limit", "40", "--prefill-episodes", "2",
        "--updates-per-episode", "2", "--eval-every", "80", "--eval-episodes", "1", "--final-episodes", "1",
        "--eval-max-contexts", "2", "--eval-workers", "0", "--log-every", "1", "--no-progress"]


def test_online_runs_end_to_end_and_resumes(tmp_path):
    run = tmp_path / "run"
    r = run_cli("trainer.online", *ARGS, "--env-steps", "160", "--num-envs", "2", "--run-dir", run,
                "--random-baseline", timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "finished: 160 env steps, 4 episodes" in r.stdout
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
    from trainer.dataset import MCAPDataset

    ds = MCAPDataset([run / "bags"], seq_len=8, cache_dir=tmp_path / "cache")
    assert ds.num_episodes == 4 and not ds.report.problems()
    assert all(e["has_first"] and e["has_last"] and e["length"] == 21 and e["split"] == "train"
               for e in ds.episodes())
    # checkpoint + evaluation JSON (periodic, final, random baseline)
    from protocad_ros.checkpoint import read_checkpoint

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
    r = run_cli("trainer.online", "--run-dir", run, "--resume", "--env-steps", "200", "--no-progress",
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
    from trainer import runs
    from trainer.online import build_parser

    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"args": ["--eval-max-contexts", "1", "--log-every", "1",
                                                       "--task", "walker_walk", "--run-dir", str(run)]}))
    a = runs.resumed_cli(build_parser, runs.parse_cli(build_parser(), [
        "--run-dir", str(run), "--resume", "--log-every", "5"]))
    assert (a.eval_max_contexts, a.log_every, a.task, a.resume) == (1, 5, "walker_walk", True)


def test_defaults_quoted_in_help_are_the_configs():
    """'(default train.X = V)' in a command's --help is what the config tree holds."""
    import re

    from protocad_ros.config import DEFAULT_CLI_PRESET, make_config
    from trainer.loop import DEMO
    from trainer.loop import build_parser as loop_parser
    from trainer.online import build_parser as online_parser

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
