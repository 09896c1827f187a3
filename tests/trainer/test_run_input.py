"""Crafted run directories handed to --resume are refused in one line with exit 2, before
anything uses them: run.json holding a list, JSON nested 100,000 deep (a RecursionError in
json), an unsafe YAML tag in config.yaml, `logs` pointing at /proc, settings of the wrong type.
The checks themselves (trainer/run_input.py) are tested on files too."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import ROOT

from trainer.data.records import DatasetError
from trainer.data.sources import find_sources
from trainer.run_input import MAX_DEPTH, check_logs, depth, load_json_object, load_yaml_mapping, matches

DEEP = "[" * 100_000 + "]" * 100_000
UNSAFE = "!!python/object/apply:os.system [\"echo PWNED\"]\n"


def run_dir(tmp_path: Path, run_json: str | None = "{}", config: str | None = None) -> Path:
    d = tmp_path / "run"
    (d / "checkpoints").mkdir(parents=True)
    (d / "checkpoints" / "latest.pt").write_bytes(b"not read before the run.json")
    if run_json is not None:
        (d / "run.json").write_text(run_json)
    if config is not None:
        (d / "config.yaml").write_text(config)
    return d


def cli(name: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(Path(sys.executable).parent / name), *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=240, env={**os.environ, "OMP_NUM_THREADS": "1"})


CASES = {
    "list": dict(run_json="[]", expect="run.json: holds a JSON list, not an object"),
    "deep": dict(run_json=DEEP, expect="run.json: nested too deeply to read"),
    "unsafe-yaml": dict(config=UNSAFE, expect="config.yaml: not YAML this tool reads"),
    "proc-logs": dict(run_json=json.dumps({"logs": ["/proc"]}),
                      expect="logs entry '/proc' lies outside the run directory"),
    "bad-setting": dict(run_json=json.dumps({"settings": {"SECTION": {"episode_length": "long"}}}),
                        expect="settings.SECTION.episode_length is 'long'"),
}
COMMANDS = {"protocad-train": "train", "protocad-loop": "loop", "protocad-online": "online"}


@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("case", sorted(CASES))
def test_a_crafted_run_dir_is_one_line_and_exit_2(tmp_path, command, case):
    c = CASES[case]
    if case == "proc-logs" and command != "protocad-train":
        pytest.skip("only protocad-train reads logs from run.json")
    if case == "bad-setting" and command == "protocad-train":
        c = dict(run_json=json.dumps({"updates": "many"}), expect="settings.train.updates is 'many'")
    d = run_dir(tmp_path, c.get("run_json", "{}"), c.get("config", "task: pendulum_swingup\n"))
    expect = c["expect"].replace("SECTION", COMMANDS[command])
    if case == "bad-setting" and command != "protocad-train":
        field = "episode_length" if command == "protocad-loop" else "eval_every"
        (d / "run.json").write_text(json.dumps({"settings": {COMMANDS[command]: {field: "long"}}}))
        expect = expect.replace("episode_length", field)
    r = cli(command, "--resume", "--run-dir", str(d), "--no-progress")
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert r.returncode == 2, r.stdout + r.stderr
    assert len(lines) == 1 and expect in lines[0], r.stderr
    assert "Traceback" not in r.stdout + r.stderr and "PWNED" not in r.stdout


def test_a_run_dir_whose_checkpoint_is_not_one_is_one_line_too(tmp_path):
    d = run_dir(tmp_path, "{}", "task: pendulum_swingup\n")
    r = cli("protocad-online", "--resume", "--run-dir", str(d), "--no-progress")
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "not a checkpoint" in lines[0], r.stderr


def test_json_checks(tmp_path):
    p = tmp_path / "x.json"
    for text, why in [("[]", "a JSON list"), ("3", "a JSON int"), (DEEP, "nested too deeply"),
                      ("{" * 5, "not valid JSON"),
                      (json.dumps({"a": [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[1]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]}),
                       f"nested more than {MAX_DEPTH} levels")]:
        p.write_text(text)
        with pytest.raises(ValueError, match=why):
            load_json_object(p)
    p.write_text('{"a": [1, {"b": 2}]}')
    assert load_json_object(p) == {"a": [1, {"b": 2}]} and depth(load_json_object(p)) == 3


def test_yaml_checks(tmp_path):
    p = tmp_path / "x.yaml"
    for text, why in [(UNSAFE, "could not determine a constructor"), ("- 1\n", "a YAML list"),
                      ("a: [" * 40 + "]" * 40, f"nested more than {MAX_DEPTH} levels"),
                      ("a: b: c\n", "not YAML this tool reads")]:
        p.write_text(text)
        with pytest.raises(ValueError, match=why):
            load_yaml_mapping(p)


def test_logs_must_lie_under_the_run(tmp_path):
    d = tmp_path / "run"
    (d / "bags").mkdir(parents=True)
    assert check_logs(d / "run.json", d, [str(d / "bags"), "bags"]) == [str(d / "bags"), "bags"]
    for bad in (["/proc"], ["../elsewhere"], [str(tmp_path)]):
        with pytest.raises(ValueError, match="outside the run directory"):
            check_logs(d / "run.json", d, bad)
    with pytest.raises(ValueError, match="not a list of paths"):
        check_logs(d / "run.json", d, "bags")


def test_a_log_path_that_cannot_be_searched_is_one_line(tmp_path):
    locked = tmp_path / "locked" / "inner"
    locked.mkdir(parents=True)
    deep = tmp_path / "deep"
    (deep.joinpath(*["d"] * 12)).mkdir(parents=True)
    with pytest.raises(DatasetError, match="nested more than 8 deep"):
        find_sources([deep])
    if os.geteuid() != 0:   # root lists anything
        locked.chmod(0)
        try:
            with pytest.raises(DatasetError, match="cannot search"):
                find_sources([tmp_path / "locked"])
        finally:
            locked.chmod(0o755)


def test_setting_types():
    assert matches(3, int) and not matches(True, int) and not matches("3", int)
    assert matches(None, int | None) and matches(["a"], list[str]) and not matches([1], list[str])
    assert matches(2, float) and not matches("x", float)
