"""protocad-compare: a real grid of protocad-online processes (tiny budgets), interrupted and
resumed; results.json against its schema; the statistics against hand-computed values; the
plot; the README section regenerated from the committed results.json."""
from __future__ import annotations

import copy
import itertools
import json
import re
import signal
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT, wait_until

from trainer.research.report import (
    BEGIN,
    aggregate_rows,
    combined,
    curves,
    format_report,
    labels_of,
    log_curves_rerun,
    markdown_section,
    paired_lines,
    plot_curves,
    readme_section,
    table_rows,
)
from trainer.research.results_json import ANCHOR_LABEL, gather, gather_run, load_results, validate
from trainer.research.statistics import (
    aggregate_iqm,
    aggregate_mean,
    aggregate_median,
    bootstrap_ci,
    iqm,
    paired_difference,
    summarize,
    unseen_train_ratio,
)

# Runs of 100-agent-step episodes; 2 test contexts, 1 episode each, so a run takes seconds.
TINY = ["--preset", "small", "--time-limit", "200", "--prefill-episodes", "1", "--updates-per-episode", "2",
        "--batch-size", "4", "--seq-len", "16", "--eval-every", "400", "--eval-episodes", "1", "--final-episodes", "1",
        "--eval-contexts", "m=0.2", "m=1.8", "--checkpoint-every", "1",
        "--set", "context.freeze_prototypes_updates=2"]


def grid_args(out: Path) -> list[str]:
    return ["-m", "trainer.research.compare", "--tasks", "pendulum_swingup", "--variants", "protocad", "dreamer",
            "--seeds", "0", "--env-steps", "800", "--jobs", "2", "--out", str(out),
            "--status-every", "5", "--", *TINY]


def read_counters(run_dir: Path) -> dict:
    from protocad_ros.checkpoint.agent_file import read_checkpoint

    return read_checkpoint(run_dir / "checkpoints" / "latest.pt")["counters"]


@pytest.mark.process
@pytest.mark.slow
def test_grid_runs_in_parallel_resumes_after_ctrl_c_and_reports(tmp_path, spawn):
    out = tmp_path / "grid"
    # Two variants, one seed: two runs (one curve each in the plot), side by side. Seeds are
    # planned like variants (test_the_variants_of_a_seed_are_planned_side_by_side).
    run_dirs = [out / "pendulum_swingup" / v / "seed0" for v in ("protocad", "dreamer")]
    first = spawn("compare1", *grid_args(out))
    # Both runs are alive at once (parallel workers) and each has written a checkpoint.
    wait_until(lambda: all((d / "checkpoints" / "latest.pt").exists() for d in run_dirs), 300,
             "a checkpoint in every run directory")
    pids = set(re.findall(r"started \S+ \(fresh\) pid (\d+)", first.output()))
    assert len(pids) == 2, first.output()

    def rows_now() -> list[dict]:
        try:
            return load_results(out / "results.json")["runs"]
        except (OSError, ValueError):
            return []
    # results.json is rewritten at each status line while the grid runs: every run shows as going
    wait_until(lambda: [r["status"] for r in rows_now()] == ["running"] * 2
               and all(r["env_steps"] > 0 for r in rows_now()), 60, "results.json showing both runs going")
    # what the grid has to do, said before it starts
    assert "2 of 2 runs to go, 1,600 env steps in all, 2 at once" in first.output()
    assert first.stop(signal.SIGINT, timeout=120) == 130, first.output()
    assert "interrupted" in first.output()
    saved = {d: read_counters(d) for d in run_dirs}
    for d in run_dirs:
        assert json.loads((d / "run.json").read_text())["result"]["status"] == "interrupted"
        assert not (d / "eval" / "final.json").exists()
    # cut short, the grid still says where each run stands
    cut = load_results(out / "results.json")
    assert [(r["status"], r["final"]) for r in cut["runs"]] == [("interrupted", None)] * 2
    # ... and the report says how far each got: env steps of the budget, updates, as in its checkpoint
    report = format_report(cut)
    assert f"not finished (2 of 2 runs; as of {cut['created']}):" in report, report
    for r in cut["runs"]:
        c = saved[Path(r["run_dir"])]
        assert re.search(rf"{r['label']}\s+{r['seed']}\s+interrupted\s+{c['env_steps']:,} of 800\s+"
                         rf"{c['updates']:,}\s", report), report
    assert "Not finished yet (2 of 2 runs; as of " in markdown_section([cut])

    second = spawn("compare2", *grid_args(out))
    wait_until(lambda: not second.alive(), 400, "the resumed grid to finish")
    log = second.output()
    assert second.p.returncode == 0, log
    # A status line says where each run stands, with the grid's wall-time estimate once the
    # runs have been timed for a while: how long that takes here depends on the machine's load
    # (a resumed run near its end can finish first), so the estimate's arithmetic is
    # test_the_wall_time_estimate_counts_updates_not_the_seconds_of_prefill's.
    assert re.search(r"\[compare\] protocad/seed0: \d+, dreamer/seed0: \d+; (about \S+ left \([\d.]+ "
                     r"updates/s per run\)|no estimate yet)", log), log
    for d in run_dirs:
        c = saved[d]
        run_log = (d / "online.log").read_text()
        # The resumed run starts from exactly the counters its checkpoint holds.
        line = next(x for x in run_log.replace(str(d.resolve()), str(d)).splitlines() if "resuming" in x)
        assert line.startswith(f"[online] resuming {d}: {c['env_steps']} env steps, {c['episodes']} episodes")
        assert line.endswith(f", {c['updates']} updates"), line
        res = json.loads((d / "run.json").read_text())["result"]
        assert res["status"] == "finished" and res["env_steps"] == 800 and res["resumes"] == 1

    doc = load_results(out / "results.json")         # validates against RESULTS_SCHEMA
    assert len(doc["runs"]) == 2 and {r["status"] for r in doc["runs"]} == {"finished"}
    for r in doc["runs"]:   # the code each run trained with, both invocations', in its row and the grid's
        assert r["code_versions"] == json.loads((Path(r["run_dir"]) / "run.json").read_text())["code_versions"]
        assert set(r["code_versions"]) <= set(doc["code_version"].split(", "))
    for r in doc["runs"]:
        assert r["final"] is not None and set(r["final"]["per_context"]) == {"m=0.2", "m=1.8"}
        assert r["curve"][-1]["tag"] == "final" and r["curve"][-1]["env_steps"] == 800
        assert [c["env_steps"] for c in r["curve"]] == sorted(c["env_steps"] for c in r["curve"])
    # A third run of the same command has nothing left to do.
    third = spawn("compare3", *grid_args(out))
    wait_until(lambda: not third.alive(), 120, "the finished grid to report")
    assert third.output().count(": done") == 2 and "started" not in third.output()

    # The plot: a valid PNG with one curve per variant (each variant's colour is in it).
    from PIL import Image

    png = out / "curves.png"
    with Image.open(png) as im:
        im.verify()
    with Image.open(png) as im:
        pixels = {tuple(p) for p in np.asarray(im.convert("RGB")).reshape(-1, 3)}
    import matplotlib

    for color in matplotlib.rcParams["axes.prop_cycle"].by_key()["color"][:2]:
        rgb = tuple(int(round(255 * x)) for x in matplotlib.colors.to_rgb(color))
        assert rgb in pixels, color
    assert (out / "curves.rrd").stat().st_size > 0


@pytest.mark.process
def test_results_that_cannot_be_written_do_not_stop_the_runs(tmp_path, capsys):
    """The grid's results.json is rewritten while it runs; a write that fails (a full disk,
    injected here: it cannot be made on demand) is said on stderr and the run still finishes."""
    from trainer.research import compare as C
    from trainer.settings import build

    out = tmp_path / "grid"
    a = build(C.GridSettings, vars(C.build_parser().parse_args(
        ["--tasks", "pendulum_swingup", "--variants", "dreamer", "--seeds", "0", "--env-steps", "400",
         "--jobs", "1", "--out", str(out), "--status-every", "1", "--", *TINY])))
    a.online_args = a.online_args[1:] if a.online_args[:1] == ["--"] else a.online_args
    calls = []

    def disk_full(running):
        calls.append(dict(running))
        raise OSError(28, "No space left on device (injected)")

    assert C.run_grid(C.plan(a), a, on_progress=disk_full) == 0
    assert json.loads((out / "pendulum_swingup" / "dreamer" / "seed0" / "run.json").read_text())["result"][
        "status"] == "finished"
    assert len(calls) >= 2 and calls[-1] == {}          # status lines, then the run's end
    assert any(out / "pendulum_swingup" / "dreamer" / "seed0" in c for c in calls[:-1])
    err = capsys.readouterr().err
    assert "could not write the grid's results" in err and "No space left on device" in err


def test_the_grid_names_the_code_each_run_trained_with_and_not_started_runs_none(tmp_path):
    """A grid spans sessions, machines and commits: each row keeps its run's `code_versions`
    (run.json, every invocation's) and the grid's code_version lists them all; a run not started
    yet ran no code and does not turn that into 'the gathering tree'. A started run that records
    none (written before runs did) still does, saying so."""
    from types import SimpleNamespace

    def spec(seed, run_json=None):
        run_dir = tmp_path / f"seed{seed}"
        if run_json is not None:
            run_dir.mkdir()
            (run_dir / "run.json").write_text(json.dumps(run_json))
        return SimpleNamespace(task="walker_walk", label="dreamer", variant="dreamer", seed=seed, run_dir=run_dir)

    done = {"code_versions": ["aaa1111", "bbb2222"], "preset": "small",
            "result": {"status": "finished", "env_steps": 100, "updates": 10}}
    args = dict(command=["protocad-compare"], env_steps=100, wall_budget=None, jobs=1, threads=1, wall_time=1.0)
    doc = gather([spec(0, done), spec(1, {**done, "code_versions": ["bbb2222", "ccc3333"]}), spec(2)], **args)
    validate(doc)
    assert [r.get("code_versions") for r in doc["runs"]] == [["aaa1111", "bbb2222"], ["bbb2222", "ccc3333"], None]
    assert doc["runs"][2]["status"] == "missing"
    assert doc["code_version"] == "aaa1111, bbb2222, ccc3333"
    older = {k: v for k, v in done.items() if k != "code_versions"}
    assert "the gathering tree" in gather([spec(3, older)], **args)["code_version"]
    crafted = {**done, "code_versions": ["ddd4444", {"a": 1}, "x" * 10_000, *[f"c{i}" for i in range(1000)]]}
    kept = gather([spec(4, crafted)], **args)["runs"][0]["code_versions"]   # bounded, strings only
    assert kept[:2] == ["ddd4444", "c0"] and len(kept) == 64


def test_results_schema_rejects_a_broken_document(tmp_path):
    doc = json.loads((ROOT / "msgs_docs" / "results" / "pendulum_cpu.json").read_text())
    validate(doc)
    del doc["runs"][0]["curve"]
    with pytest.raises(ValueError, match="runs/0"):
        validate(doc)


def test_results_and_run_files_read_as_input_are_bounded(tmp_path):
    """A results.json given to --report / --from-results and a run.json gathered into one are
    read as a stranger could have written them: one that is too large (a sparse file, nothing
    allocated), not an object or nested too deep is one error line naming it, or, for a run,
    a row that says what is known of it; none is read whole before its size is checked."""
    from trainer.run_input import MAX_RUN_FILE_BYTES

    huge = tmp_path / "huge.json"
    with huge.open("wb") as f:
        f.truncate(MAX_RUN_FILE_BYTES + 1)
    for path, says in ((huge, "more than the limit"), (tmp_path / "list.json", "not an object"),
                       (tmp_path / "deep.json", "nested")):
        if path.name == "list.json":
            path.write_text("[1, 2]")
        elif path.name == "deep.json":
            path.write_text("[" * 100_000 + "]" * 100_000)
        with pytest.raises(ValueError, match=says) as err:
            load_results(path)
        assert path.name in str(err.value)
    # not an object: as if absent; an object whose result is no mapping: started, ended unknown
    for crafted, status in (("[1, 2]", "missing"), (json.dumps({"result": "finished", "code_versions": ["a"]}), "failed")):
        run_dir = tmp_path / f"run{len(crafted)}"
        run_dir.mkdir()
        (run_dir / "run.json").write_text(crafted)
        row = gather_run("walker_walk", "dreamer", "dreamer", 0, run_dir)
        assert row["status"] == status and row["final"] is None
    huge_run = tmp_path / "huge_run"
    huge_run.mkdir()
    huge.rename(huge_run / "run.json")
    assert gather_run("walker_walk", "dreamer", "dreamer", 0, huge_run)["status"] == "missing"


def test_a_run_whose_files_are_out_of_shape_gathers_as_failed_and_keeps_what_is_sound(tmp_path, capsys):
    """run.json, eval.jsonl and eval/final.json are the run's own files, but a hand edit or a
    stranger can put any JSON in them: a value of the wrong kind gathers the run as failed with
    a line naming the file, a bad evaluation line or final.json counts as not written, and the
    grid's results.json still validates (before, a non-numeric count was a traceback, a status
    outside the schema a refused results.json)."""
    good = {"result": {"status": "finished", "env_steps": 1000, "updates": 50, "wall_time": 12.5},
            "protocol": {"eval_split": "test", "updates_per_episode": 5}, "preset": "small"}
    crafted = {"status": dict(good, result={**good["result"], "status": "done!"}),
               "steps": dict(good, result={**good["result"], "env_steps": "1000"}),
               "fraction": dict(good, result={**good["result"], "updates": 2.5}),
               "infinite": json.dumps(good).replace("1000", "Infinity"),
               "protocol": dict(good, protocol=["test"]),
               "split": dict(good, protocol={"eval_split": "everything"})}
    rows = []
    for name, doc in crafted.items():
        run_dir = tmp_path / name
        (run_dir / "eval").mkdir(parents=True)
        (run_dir / "run.json").write_text(doc if isinstance(doc, str) else json.dumps(doc))
        (run_dir / "eval.jsonl").write_text("\n".join([
            "[1, 2]", json.dumps({"env_steps": "many", "mean_return": 3.0}),
            json.dumps({"env_steps": 500, "mean_return": [1]}),
            json.dumps({"env_steps": 500, "mean_return": 40.25, "tag": ""}), "{torn"]) + "\n")
        (run_dir / "eval" / "final.json").write_text(json.dumps({"mean_return": "high", "per_context": []}))
        row = gather_run("walker_walk", "dreamer", "dreamer", 0, run_dir)
        assert row["status"] == "failed", (name, row)
        assert f"{run_dir / 'run.json'}" in capsys.readouterr().err
        assert row["curve"] == [{"env_steps": 500, "mean_return": 40.25, "tag": ""}]
        assert row["final"] is None
        rows.append(row)
    sound = tmp_path / "sound"
    sound.mkdir()
    (sound / "run.json").write_text(json.dumps(good))
    row = gather_run("walker_walk", "dreamer", "dreamer", 1, sound)
    assert (row["status"], row["env_steps"], row["updates"], row["collect_interval"], row["preset"]) == \
        ("finished", 1000, 50, 5, "small")
    doc = gather([], command=["protocad-compare"], env_steps=1000, wall_budget=None, jobs=1, threads=1,
                   wall_time=1.0)
    doc["runs"] = [*rows, row]
    validate(doc)


def test_bootstrap_interval_matches_the_exact_bootstrap_distribution():
    # Four seeds: the bootstrap distribution of the mean is the 4**4 = 256 equally likely
    # resamples, enumerated here; a 95% percentile interval must sit at its 2.5% and 97.5%
    # points (checked between the exact 2% and 3% / 97% and 98% points: Monte Carlo error at
    # 40k replicates is ~0.08%).
    scores = np.array([1.0, 2.0, 6.0, 10.0])
    exact = np.sort([np.mean(c) for c in itertools.product(scores, repeat=4)])
    q = lambda p: exact[int(np.ceil(p * exact.size)) - 1]   # noqa: E731  inverse CDF
    lo, hi = bootstrap_ci([scores], aggregate_mean, reps=40_000, seed=1)
    assert q(0.02) <= lo <= q(0.03) and q(0.97) <= hi <= q(0.98), (lo, hi, q(0.025), q(0.975))
    assert q(0.025) == pytest.approx(1.5) and q(0.975) == pytest.approx(8.0)   # by hand: 1,1,2,2 / 10,10,6,6
    assert bootstrap_ci([scores], aggregate_mean, reps=500, seed=3) == \
        bootstrap_ci([scores], aggregate_mean, reps=500, seed=3)


def _paired_doc(a: list[float], b: list[float]) -> dict:
    """A results document of two labels on walker_walk with these final returns per seed."""
    doc = json.loads((ROOT / "msgs_docs" / "results" / "pendulum_cpu.json").read_text())
    template = doc["runs"][0]
    doc["runs"] = [{**template, "task": "walker_walk", "label": label, "variant": label, "seed": seed,
                    "final": {"mean_return": v, "episodes": 320, "per_context": {}},
                    "final_train": {"mean_return": 2 * v, "episodes": 125, "per_context": {}}}
                   for label, values in (("protocad", a), ("dreamer", b)) for seed, v in enumerate(values)]
    validate(doc)
    return doc


def test_the_paired_difference_is_the_mean_of_per_seed_differences_with_a_t_interval():
    doc = _paired_doc([10, 20, 30, 40, 50], [5, 25, 20, 30, 45])
    d = paired_difference(doc, "walker_walk")
    # differences 5, -5, 10, 10, 5: mean 5, sd sqrt(150 / 4), t(0.975, 4) = 2.7764
    half = 2.7764451 * np.sqrt(150 / 4) / np.sqrt(5)
    assert d["diffs"] == [5, -5, 10, 10, 5] and d["mean"] == pytest.approx(5)
    assert d["ci"] == pytest.approx((5 - half, 5 + half), abs=1e-4)
    assert unseen_train_ratio(doc, "walker_walk", "protocad")["mean"] == pytest.approx(0.5)
    assert "no difference shown" in paired_lines(doc)[0]
    # a superseded row and a seed only one label finished are not pairs
    doc["runs"][0]["superseded"] = "its prototypes never trained"
    doc["runs"] = [r for r in doc["runs"] if not (r["label"] == "dreamer" and r["seed"] == 4)]
    assert paired_difference(doc, "walker_walk")["seeds"] == [1, 2, 3]
    # below 5 seeds a table shows the range, and calls it one
    head, rows = table_rows(doc, summarize(doc, reps=100))
    assert "(range 20.0-50.0)" in rows[1][5] and "range below 5 seeds" in head[5]


def test_over_tasks_a_variant_with_too_few_seeds_on_a_task_shows_no_interval():
    doc = _paired_doc([10, 20, 30, 40, 50], [5, 25, 20, 30, 45])
    doc["runs"] += [{**r, "task": "cheetah_run"} for r in doc["runs"] if r["seed"] < 2 or r["label"] == "dreamer"]
    head, rows = aggregate_rows(summarize(doc, reps=100))
    by_label = {r[0]: r for r in rows}
    assert head[2] == "fewest seeds per task" and by_label["protocad"][2] == "2" and by_label["dreamer"][2] == "5"
    assert by_label["protocad"][3].endswith("(no interval below 5 seeds)") and "[" not in by_label["protocad"][3]
    assert "[" in by_label["dreamer"][3]
    # one task: the over-tasks table would repeat the per-task row, so neither report shows it
    assert "over tasks" not in format_report(_paired_doc([10, 20], [5, 25])).lower()


def test_iqm_and_aggregates_match_hand_computed_values():
    # 8 scores: IQM drops the 2 lowest and the 2 highest and averages the middle 4.
    assert iqm(np.array([0, 1, 2, 3, 4, 5, 6, 100.0])) == pytest.approx((2 + 3 + 4 + 5) / 4)
    per_task = [np.array([10.0, 20.0]), np.array([0.0, 100.0]), np.array([5.0, 5.0])]
    assert aggregate_mean(per_task) == pytest.approx(140 / 6)
    assert aggregate_median(per_task) == pytest.approx(15.0)   # task means 15, 50, 5
    # all 6 scores sorted 0 5 5 10 20 100: trim 25% (1.5 each side) -> scipy trims 1 each side
    assert aggregate_iqm(per_task) == pytest.approx(np.mean([5, 5, 10, 20]))
    # Stratified: a task whose seeds agree contributes no spread.
    lo, hi = bootstrap_ci([np.array([5.0, 5.0])], aggregate_mean, reps=200)
    assert lo == hi == 5.0


def test_a_superseded_grid_reports_beside_the_grid_that_replaced_it():
    """The first walker comparison's rows are superseded by the paired grid, which reran their
    seeds: both files report together, the superseded rows plotting nothing and counting nowhere."""
    old = load_results(ROOT / "msgs_docs" / "results" / "walker_compare_small.json")
    new = load_results(ROOT / "msgs_docs" / "results" / "walker_paired_small.json")
    assert all(r.get("superseded") for r in old["runs"])
    both = combined([old, new], ["old.json", "new.json"])
    assert len(both["runs"]) == len(new["runs"])
    assert labels_of(both, "walker_walk") == ["dreamer", "protocad"]
    other_look = copy.deepcopy(old)   # a superseded row's setup does not relabel the rows that count
    for r in other_look["runs"]:
        r["render_quality"] = "default"
    assert labels_of(combined([other_look, new]), "walker_walk") == ["dreamer", "protocad"]
    _, mean, _, _ = curves(both, "walker_walk", "protocad")
    _, mean_new, _, _ = curves(new, "walker_walk", "protocad")
    assert np.array_equal(mean, mean_new)
    unsuperseded = copy.deepcopy(old)
    for r in unsuperseded["runs"]:
        del r["superseded"]
    with pytest.raises(ValueError, match="walker_walk/protocad/seed0 is in both old.json and new.json"):
        combined([unsuperseded, new], ["old.json", "new.json"])


def test_the_generated_results_section_regenerates_byte_identically_from_the_committed_json():
    # the files and plot it names in its own first line, regenerated: the page says what they hold
    target = "msgs_docs/results.md"
    section = readme_section(ROOT / target)
    named = re.search(rf"by `protocad-compare --report (.+?) --image (\S+) --update-readme {target}`", section)
    sources, image = named.group(1).split(), named.group(2)
    assert "msgs_docs/results/walker_anchor_cpu.json" in sources
    docs = [load_results(ROOT / s) for s in sources]
    assert section == markdown_section(docs, image=image, sources=sources, target=target)
    assert "![test-context return vs env steps](results/walker_cpu.png)" in section   # relative to the page
    assert (ROOT / image).exists()
    # the anchor's verdicts, from the committed curves and DreamerV2's committed points
    assert "| walker_walk | 30,000 | 133.3 (n=2) | 130 (83-239) | yes |" in section


@pytest.mark.process
def test_compare_help_and_bad_report_are_clear(tmp_path):
    import subprocess

    h = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--help"], capture_output=True, text=True,
                       cwd=ROOT, timeout=120)
    assert h.returncode == 0 and "--wall-budget" in h.stdout and "--anchor-seeds" in h.stdout
    bad = tmp_path / "results.json"
    bad.write_text(json.dumps({"schema": "protocad-compare/1"}))
    r = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--report", str(bad)], capture_output=True,
                       text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "does not match protocad-compare/1" in r.stderr


def test_durations_print_as_they_parse():
    from trainer.cli_values import format_duration, parse_duration
    for seconds in (0, 45, 600, 3600, 11400, 90061):
        text = format_duration(seconds)
        assert abs(parse_duration(text) - seconds) < 60, text
    assert (format_duration(45), format_duration(11400)) == ("45s", "3h10m")


@pytest.mark.process
def test_a_report_writes_only_where_it_is_told(tmp_path):
    import shutil
    import subprocess

    src = tmp_path / "results"
    src.mkdir()
    shutil.copyfile(ROOT / "msgs_docs" / "results" / "pendulum_cpu.json", src / "results.json")
    r = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--report", str(src / "results.json")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in src.iterdir()) == ["results.json"]     # nothing beside the json
    assert "plot: not written (--image PNG)" in r.stdout
    r = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--report", str(src / "results.json"),
                        "--image", str(tmp_path / "c.png")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and (tmp_path / "c.png").stat().st_size > 0


def test_an_anchor_at_two_presets_reports_as_two_curves(tmp_path):
    """The small-preset anchor beside the same grid at DreamerV2's sizes (same task, label and
    seeds, another preset): one curve per preset in the plot and the rerun recording; the same
    preset in two files is still refused (its curve would count twice)."""
    from trainer.viz.rerun_log import read_recording

    small = load_results(ROOT / "msgs_docs" / "results" / "walker_anchor_cpu.json")
    paper = copy.deepcopy(small)
    for r in paper["runs"]:
        r["preset"] = "paper"
        for c in r["curve"]:
            c["mean_return"] += 50.0
    both = combined([small, paper], ["small.json", "paper.json"])
    names = ["dreamer_standard (paper preset)", "dreamer_standard (small preset)"]
    assert labels_of(both, "walker_walk") == names
    assert {r["base_label"] for r in both["runs"]} == {ANCHOR_LABEL}
    _, m_small, _, _ = curves(small, "walker_walk", ANCHOR_LABEL)
    _, m_paper, _, _ = curves(both, "walker_walk", names[0])
    assert np.allclose(m_paper, m_small + 50.0)
    assert plot_curves(both, tmp_path / "both.png").stat().st_size > 0
    held = read_recording(log_curves_rerun(both, tmp_path / "both.rrd"))
    for name in names:
        part = name.replace(" ", "\\ ").replace("(", "\\(").replace(")", "\\)")
        assert f"/curves/walker_walk/{part}/mean" in held, sorted(held)
    with pytest.raises(ValueError, match="walker_walk/dreamer_standard/seed0 is in both small.json and again.json"):
        combined([small, copy.deepcopy(small)], ["small.json", "again.json"])


def test_an_anchor_rendered_two_ways_reports_as_two_curves(tmp_path):
    """The same anchor rendered with dm_control's default look beside the committed one (same
    preset, a file that predates the field: it rendered 'fast'): one curve per look; a grid
    gathered from run directories records the look its config.yaml names."""
    from protocad_ros.model.config import make_config

    fast = load_results(ROOT / "msgs_docs" / "results" / "walker_anchor_cpu.json")
    assert all("render_quality" not in r for r in fast["runs"])
    looks = copy.deepcopy(fast)
    looks["runs"] = [{**r, "render_quality": "default"} for r in looks["runs"][:1]]
    validate(looks)
    both = combined([fast, looks], ["fast.json", "default.json"])
    names = ["dreamer_standard (default render)", "dreamer_standard (fast render)"]
    assert labels_of(both, "walker_walk") == names
    assert [r["seed"] for r in both["runs"] if r["label"] == names[0]] == [0]
    assert plot_curves(both, tmp_path / "looks.png").stat().st_size > 0
    paper = copy.deepcopy(looks)
    paper["runs"][0]["preset"] = "paper"
    assert labels_of(combined([fast, paper]), "walker_walk") == [
        "dreamer_standard (paper preset, default render)", "dreamer_standard (small preset, fast render)"]

    run_dir = tmp_path / "walker_walk" / "dreamer_standard" / "seed0"
    run_dir.mkdir(parents=True)
    cfg = make_config("walker_walk", preset="small", variant="dreamer")
    cfg.train.render_quality = "default"
    cfg.save(run_dir / "config.yaml")
    row = gather_run("walker_walk", ANCHOR_LABEL, "dreamer", 0, run_dir)
    assert row["render_quality"] == "default"
    assert "render_quality" not in gather_run("walker_walk", ANCHOR_LABEL, "dreamer", 1, tmp_path / "none")


@pytest.mark.process
def test_a_report_of_two_grids_shows_each_and_plots_both(tmp_path):
    """The README section from the anchor's grid and another grid's results.json (budgets,
    machines and commands of their own): each file's command and table, one plot of both; the
    same run in two files, or --ship over two, is one error line before anything is written."""
    import subprocess

    anchor, other = "msgs_docs/results/walker_anchor_cpu.json", "msgs_docs/results/pendulum_cpu.json"
    png = tmp_path / "both.png"
    r = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--report", anchor, other,
                        "--markdown", "--image", str(png)], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    section = r.stdout[r.stdout.index(BEGIN):]
    assert f"*Generated from `{anchor}` and `{other}` by `protocad-compare --report {anchor} {other} " \
           f"--image {png} --update-readme README.md`" in section
    docs = [load_results(ROOT / anchor), load_results(ROOT / other)]
    for doc, name in zip(docs, (anchor, other)):
        part = section[section.index(f"**`{name}`**"):]
        assert " ".join(doc["command"]) in part and f"Budget {doc['budgets']['env_steps']:,} env steps" in part
    assert "| walker_walk | 30,000 | 133.3 (n=2) | 130 (83-239) | yes |" in section      # the anchor's verdict
    assert "| pendulum_swingup | protocad | 3 |" in section                              # the other grid's row
    import matplotlib.image

    assert matplotlib.image.imread(png).shape[1] > 1.8 * matplotlib.image.imread(png).shape[0]   # two panels

    for argv, says in (([anchor, anchor], "walker_walk/dreamer_standard/seed0 is in both"),
                       ([anchor, other, "--ship", str(tmp_path / "p.pt")], "--ship takes the best run of one")):
        r = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--report", *argv,
                            "--image", str(tmp_path / "x.png")], capture_output=True, text=True, cwd=ROOT, timeout=120)
        assert r.returncode == 2 and says in r.stderr, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["both.png"]


@pytest.mark.process
def test_a_grid_whose_parent_is_killed_twice_resumes_to_completion(tmp_path, spawn):
    """SIGKILL of protocad-compare (its runs die with it) twice in a row, once before any
    checkpoint: the same command then finishes every run, counters equal to their bags."""
    from trainer.data.dataset import MCAPDataset
    from trainer.research.online_rundir import data_counts

    out = tmp_path / "grid"
    args = ["-m", "trainer.research.compare", "--tasks", "pendulum_swingup", "--variants", "dreamer", "--seeds", "0", "1",
            "--env-steps", "400", "--jobs", "2", "--out", str(out), "--status-every", "5", "--",
            *TINY, "--checkpoint-every", "1000", "--time-limit", "100"]
    run_dirs = [out / "pendulum_swingup" / "dreamer" / f"seed{s}" for s in (0, 1)]

    def bags(d):
        return len(list((d / "bags").glob("*"))) if (d / "bags").is_dir() else 0

    first = spawn("kill1", *args)
    wait_until(lambda: all(bags(d) >= 2 for d in run_dirs), 300, "bags in both runs")
    assert not any((d / "checkpoints" / "latest.pt").exists() for d in run_dirs)   # none yet
    first.stop(signal.SIGKILL)
    second = spawn("kill2", *args)
    wait_until(lambda: second.output().count("(resume)") == 2, 120, "both runs resumed from their bags")
    wait_until(lambda: all(bags(d) >= 3 for d in run_dirs), 300, "more bags")
    second.stop(signal.SIGKILL)
    third = spawn("finish", *args)
    wait_until(lambda: not third.alive(), 400, "the grid to finish")
    assert third.p.returncode == 0, third.output()[-3000:]
    for d in run_dirs:
        assert json.loads((d / "run.json").read_text())["result"]["status"] == "finished"
        steps, episodes = data_counts(MCAPDataset([d / "bags"], seq_len=4, cache_dir=tmp_path / "c" / d.name))
        assert read_counters(d)["env_steps"] == 2 * steps >= 400

    ship_the_best_policy(out, tmp_path)
    continue_the_grid_on_another_machine(out, args, tmp_path, spawn)


def continue_the_grid_on_another_machine(out: Path, args: list[str], tmp_path: Path, spawn) -> None:
    """Only results.json travels (the run directories stay behind): `--from-results` takes its
    finished runs as done, runs only the new seed, and the report says where the others came
    from. A results.json of other run arguments is refused before anything runs."""
    import subprocess

    committed = tmp_path / "committed.json"
    committed.write_bytes((out / "results.json").read_bytes())
    out.rename(tmp_path / "first-machine")
    elsewhere = tmp_path / "elsewhere"
    more = [x if x != str(out) else str(elsewhere) for x in args]
    more[more.index("--seeds") + 1:more.index("--seeds") + 3] = ["0", "1", "2"]
    grid = spawn("carried", *more[:more.index("--")], "--from-results", str(committed), *more[more.index("--"):])
    wait_until(lambda: not grid.alive(), 400, "the continued grid to finish")
    log = grid.output()
    assert grid.p.returncode == 0, log[-3000:]
    assert "2 finished run(s) carried" in log and log.count("(fresh)") == 1 and "seed2 (fresh)" in log
    before = {r["seed"]: r for r in load_results(committed)["runs"]}
    doc = load_results(elsewhere / "results.json")
    assert [r["seed"] for r in doc["runs"]] == [0, 1, 2]
    for r in doc["runs"][:2]:
        assert {k: v for k, v in r.items() if k != "carried_from"} == before[r["seed"]]
        assert r["carried_from"]["results"] == str(committed)
    assert "carried_from" not in doc["runs"][2] and doc["runs"][2]["status"] == "finished"
    assert doc["runs"][2]["code_versions"] and "gathering tree" not in doc["code_version"]
    assert not (elsewhere / "pendulum_swingup" / "dreamer" / "seed0").exists()
    assert f"dreamer/seed0, dreamer/seed1 finished elsewhere and came from {committed}" in \
        markdown_section([doc])

    other = [*more[:more.index("--")], "--from-results", str(committed), *more[more.index("--"):],
             "--updates-per-episode", "3"]
    r = subprocess.run([sys.executable, *other], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 2 and "--from-results" in r.stderr and "run arguments" in r.stderr, r.stderr
    missing = tmp_path / "not-committed.json"
    gone = tmp_path / "never-made"
    r = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--tasks", "pendulum_swingup", "--seeds",
                        "0", "--env-steps", "500", "--out", str(gone), "--from-results", str(missing)],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 2 and f"--from-results {missing}: cannot read" in r.stderr, r.stderr
    assert not gone.exists()


def ship_the_best_policy(out: Path, tmp_path: Path) -> None:
    """`--ship`: the run with the best final return on unseen contexts becomes a policy file
    (bfloat16 weights, no optimizer states, provenance inside and beside it) that loads, acts
    and can be trained on from fresh optimizers."""
    import subprocess

    import torch

    from protocad_ros.checkpoint.agent_file import load_checkpoint, read_checkpoint, read_provenance

    policy = tmp_path / "policies" / "pendulum.pt"
    r = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--report", str(out / "results.json"),
                        "--ship", str(policy)], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    doc = load_results(out / "results.json")
    best = max(doc["runs"], key=lambda row: row["final"]["mean_return"])
    prov = read_provenance(policy)
    assert prov["results_entry"]["seed"] == best["seed"] and prov["results_entry"]["final"] == best["final"]
    assert prov["run_command"] and prov["code_versions"]
    assert prov["results_entry"]["prototype_freeze"] == best["prototype_freeze"]   # what decided the run
    assert f"among the {len(doc['runs'])} finished runs of results.json" in prov["what"], prov["what"]
    assert json.loads(policy.with_suffix(".json").read_text())["provenance"] == prov
    assert f"seed {best['seed']}" in r.stdout and str(policy) in r.stdout

    source = Path(best["run_dir"]) / "checkpoints" / "latest.pt"
    assert "optimizers" not in read_checkpoint(policy)
    assert policy.stat().st_size < source.stat().st_size / 2
    shipped, _ = load_checkpoint(policy, restore_rng=False)
    trained, _ = load_checkpoint(source, restore_rng=False)
    for (k, a), b in zip(shipped.state_dict().items(), trained.state_dict().values()):
        assert a.dtype == b.dtype, k                  # back in float32 once loaded
        if b.is_floating_point():
            assert torch.equal(a, b.to(torch.bfloat16).to(b.dtype)), k
    assert all(not st for opt in shipped.optimizers().values() for st in opt.state.values())

    # With the run's own unseen-context evaluation in the provenance; another checkpoint's is refused.
    evaluation = tmp_path / "unseen.json"
    e = subprocess.run([sys.executable, "-m", "trainer.learn.evaluate", str(source), "--random", "--context", "m=0.2",
                        "--episodes", "1", "--time-limit", "100", "--no-progress", "--json", str(evaluation)],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert e.returncode == 0, e.stderr
    r = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--report", str(out / "results.json"),
                        "--ship", str(policy), "--ship-evaluation", str(evaluation)],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    unseen = read_provenance(policy)["unseen_evaluation"]
    measured = json.loads(evaluation.read_text())
    assert unseen["mean_return"] == measured["results"][0]["mean_return"] and unseen["split"] == "test"
    assert unseen["random_mean_return"] == measured["random"][0]["mean_return"]
    other = next(row for row in doc["runs"] if row["seed"] != best["seed"])
    another_version = dict(measured["results"][0], sha256="0" * 64)   # the same path, since overwritten
    crafted = dict(measured["results"][0], sha256=[1] * 10**5)          # no digest at all
    measured["results"][0]["policy"] = str(Path(other["run_dir"]) / "checkpoints" / "latest.pt")
    for results, refusal in (([measured["results"][0]], "does not evaluate"), ([another_version], "another version"),
                             ([crafted], "another version")):
        evaluation.write_text(json.dumps(dict(measured, results=results)))
        r = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--report", str(out / "results.json"),
                            "--ship", str(tmp_path / "mismatch.pt"), "--ship-evaluation", str(evaluation)],
                           capture_output=True, text=True, cwd=ROOT, timeout=300)
        assert r.returncode == 2 and refusal in r.stderr and not (tmp_path / "mismatch.pt").exists(), r.stderr

    # Only unseen-context finals count: asked for a label without any, a clear error, no file.
    r = subprocess.run([sys.executable, "-m", "trainer.research.compare", "--report", str(out / "results.json"),
                        "--ship", str(tmp_path / "none.pt"), "--ship-label", "protocad"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 2 and "no finished run" in r.stderr and not (tmp_path / "none.pt").exists()


def test_the_variants_of_a_seed_are_planned_side_by_side():
    """A grid cut short has compared seeds: protocad and dreamer of seed 0 come first."""
    from trainer.research.compare import GridSettings, plan

    specs = plan(GridSettings(tasks=["walker_walk"], variants=["protocad", "dreamer"], seeds=[0, 1, 2],
                              anchor_seeds=[0], out="grid"))
    assert [(s.label, s.seed) for s in specs] == [
        ("protocad", 0), ("dreamer", 0), ("protocad", 1), ("dreamer", 1), ("protocad", 2), ("dreamer", 2),
        ("dreamer_standard", 0)]


def test_the_wall_time_estimate_counts_updates_not_the_seconds_of_prefill(tmp_path, monkeypatch):
    """Just after prefill (2,000 random env steps in seconds) the grid's estimate is the updates
    it has left at the pace the runs train: 2 runs x 58,000 env steps x C=100 per 1,000-step
    episode at 0.15 updates/s each, both at once, is 10h44m (a rate of env steps would have
    said minutes)."""
    from trainer import runs
    from trainer.research import compare

    a = compare.GridSettings(tasks=["walker_walk"], variants=["dreamer"], seeds=[0, 1], env_steps=60_000,
                             jobs=2, status_every=600, out=str(tmp_path))
    specs = compare.plan(a)
    for s in specs:
        s.run_dir.mkdir(parents=True)
        runs.atomic_write_json(s.run_dir / "run.json", {"protocol": {
            "updates_per_episode": 100, "time_limit": 1000, "prefill_episodes": 2}})
    now = 1000.0
    monkeypatch.setattr(compare.time, "monotonic", lambda: now)
    running = {i: (s, None, None) for i, s in enumerate(specs)}
    started = {id(s): (now - 600.0, 10) for s in specs}            # 90 updates in 600 s
    done_steps = {id(s): 2000 for s in specs}
    updates = {id(s): 100 for s in specs}
    assert compare.grid_estimate(specs, running, started, done_steps, updates, a) == \
        "; about 10h44m left (0.15 updates/s per run)"
    started = {id(s): (now - 1.0, 100) for s in specs}             # not timed long enough yet
    assert compare.grid_estimate(specs, running, started, done_steps, updates, a) == "; no estimate yet"
