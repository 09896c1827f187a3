"""`protocad-compare`: a grid of tasks x variants x seeds, each an ordinary `protocad-online` run
directory, run as parallel worker processes, gathered into one `results.json` and reported.

    protocad-compare --tasks pendulum_swingup --variants protocad dreamer --seeds 0 1 2 \\
        --env-steps 30000 --wall-budget 85m --jobs 7 --out runs/compare-pend \\
        --anchor-seeds 0 -- --preset small --updates-per-episode 25
    protocad-compare --out runs/compare-pend ...same flags...   # resumes every unfinished run
    protocad-compare --report runs/compare-pend/results.json --markdown   # README section
    protocad-compare --report anchor/results.json compare/results.json   # two grids in one report
    protocad-compare --power-json power_table.json       # sizes the next paired grid; runs nothing

Each run is `python -m trainer.research.online --run-dir OUT/TASK/LABEL/seedS ...` with its own torch
thread budget (`--threads`) and device (`--devices`, assigned round robin), its output in
RUN_DIR/online.log. Re-running the same command skips finished runs and resumes the others
from their last checkpoint (`protocad-online --resume`: weights, optimisers, RNG, sampler;
counters from the bags on disk, which all count); a run killed before its first checkpoint
resumes from its bags. Ctrl-C (or SIGTERM) asks every run to stop cleanly (checkpoint, no final
evaluation) and exits 130; the runs also die with this process if it is killed outright.

Budgets: every run stops at `--env-steps`, or earlier when its own training wall time (carried
across resumes) reaches `--wall-budget`; either way it then runs the final evaluation on all
test contexts and saves its checkpoint and curves (results.json: which budget ended it, where).

Runs that span machines: OUT/results.json is rewritten each time a run finishes, at each status
line and when the grid is interrupted, so the rows of the finished runs can be committed at any
time, and `--report OUT/results.json` shows how far the others got (env steps, updates, latest
evaluation). Another machine then continues the grid with `--from-results THAT.json`: the
finished runs recorded there count as done (their rows are kept as they are, with where they
came from) and only the others run. Their budgets and the arguments after `--` must be this grid's.

`--anchor-seeds S...` adds the sanity anchor of the RL core: `dreamer` at DreamerV2's dmc_vision
settings (`reference=dreamerv2`) trained and evaluated on the unrandomized task (m=1 / m=1,d=1),
label `dreamer_standard`, to set beside DreamerV2's published curves on standard DMC.

Everything after `--` goes to every `protocad-online` run unchanged (preset, C, `--set` ...).
"""
from __future__ import annotations

import argparse
import ctypes
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from protocad_ros.model.hyperparameters import VARIANTS
from sim_bridge.contract.contexts import TASKS
from trainer import cli_values, console, runs
from trainer.provenance import stale_install
from trainer.research import report, results_json
from trainer.research.statistics import standard_context
from trainer.settings import arg, build, settings_parser


@dataclass
class RunSpec:
    task: str
    label: str           # variant, or results_json.ANCHOR_LABEL for the unrandomized dreamer
    variant: str
    seed: int
    run_dir: Path
    device: str = "cpu"
    extra: list[str] = field(default_factory=list)
    carried: dict | None = None   # its finished results.json row from --from-results

    def state(self, env_steps: int, wall_budget: float | None) -> str:
        """'done' (budget reached here), 'carried' (reached elsewhere: --from-results), 'resume'
        (a checkpoint to continue from) or 'fresh'."""
        result = runs.read_run_json(self.run_dir).get("result") or {}
        if reached_budget(result.get("status"), result.get("env_steps", 0), result.get("wall_time", 0.0),
                          env_steps, wall_budget):
            return "done"
        if self.carried is not None:
            return "carried"
        # protocad-online resumes from its bags too (a run killed before its first checkpoint)
        bags = self.run_dir / "bags"
        started = runs.checkpoint_path(self.run_dir).exists() or (bags.is_dir() and any(bags.iterdir()))
        return "resume" if started and (self.run_dir / "run.json").exists() else "fresh"


def reached_budget(status: str | None, env_steps: int, wall_time: float, budget_steps: int,
                   wall_budget: float | None) -> bool:
    """A run that ended at the grid's budget: its env steps, or its training wall time."""
    if status == "finished":
        return int(env_steps) >= budget_steps
    return status == "wall_budget" and bool(wall_budget) and float(wall_time) >= wall_budget


def online_args_of(command: Sequence[str]) -> list[str]:
    """The arguments after `--` in a recorded protocad-compare command."""
    command = list(command)
    return command[command.index("--") + 1:] if "--" in command else []


def carry_finished_runs(specs: Sequence[RunSpec], a: GridSettings) -> int:
    """Marks the specs whose run finished in one of a.from_results (results.json written by this
    grid elsewhere: another machine, an earlier session). Returns how many. A file made with
    other budgets or other run arguments is refused (ValueError): its rows are not this grid's."""
    wanted = {(s.task, s.label, s.seed): s for s in specs}
    n = 0
    for path in a.from_results:
        try:   # unreadable, too large, not JSON, not a results.json: one line naming the option
            doc = results_json.load_results(path)
        except ValueError as exc:
            raise ValueError(f"--from-results {exc}") from None
        b = doc["budgets"]
        theirs = online_args_of(doc["command"])
        if (b["env_steps"], b["wall_budget_s"]) != (a.env_steps, a.wall_budget) or theirs != a.online_args:
            raise ValueError(
                f"--from-results {path}: its runs had budgets {b['env_steps']} env steps / wall "
                f"{b['wall_budget_s']} and run arguments {' '.join(theirs) or '(none)'}; this grid has "
                f"{a.env_steps} / {a.wall_budget} and {' '.join(a.online_args) or '(none)'}")
        for row in doc["runs"]:
            s = wanted.get((row["task"], row["label"], row["seed"]))
            if (s is None or s.carried is not None or row["variant"] != s.variant
                    or not reached_budget(row["status"], row["env_steps"], row["wall_time_s"],
                                          a.env_steps, a.wall_budget)):
                continue
            origin = row.get("carried_from") or {
                "results": str(path), "code_version": doc["code_version"], "machine": doc["machine"],
                "created": doc["created"]}
            s.carried = {**row, "carried_from": origin}
            n += 1
    return n


def plan(a: GridSettings) -> list[RunSpec]:
    specs: list[RunSpec] = []
    # Seed-major: the variants of a seed run side by side, so a grid cut short (or still
    # running) has compared seeds, not all of one variant and none of the other.
    grid = [(t, v, v, s) for t in a.tasks for s in a.seeds for v in a.variants]
    grid += [(t, results_json.ANCHOR_LABEL, "dreamer", s) for t in a.tasks for s in a.anchor_seeds]
    for i, (task, label, variant, seed) in enumerate(grid):
        extra = []
        if label == results_json.ANCHOR_LABEL:
            ctx = standard_context(task)
            # DreamerV2's own dmc_vision settings, so its published curve is the reference
            extra = ["--train-context", ctx, "--eval-split", "train", "--eval-contexts", ctx,
                     "--set", "reference=dreamerv2"]
        specs.append(RunSpec(task, label, variant, seed, Path(a.out) / task / label / f"seed{seed}",
                             a.devices[i % len(a.devices)], extra))
    return specs


def run_protocols(specs: Sequence[RunSpec]) -> dict[str, dict]:
    """Each task's evaluation protocol as its first compared run recorded it (run.json), for the
    random baseline; the anchor's runs are scored on the standard context, not on the grid's."""
    found: dict[str, dict] = {}
    for s in specs:
        if s.task in found or s.label == results_json.ANCHOR_LABEL:
            continue
        try:
            found[s.task] = json.loads((s.run_dir / "run.json").read_text())["protocol"]
        except (OSError, ValueError, KeyError, TypeError):
            continue   # carried from elsewhere, or not started: another run of the task may have it
    return found


def online_argv(spec: RunSpec, a: GridSettings, state: str) -> list[str]:
    argv = [sys.executable, "-m", "trainer.research.online", "--run-dir", str(spec.run_dir),
            "--env-steps", str(a.env_steps), "--device", spec.device, "--threads", str(a.threads),
            "--no-progress"]
    if a.wall_budget:
        argv += ["--wall-budget", str(a.wall_budget)]
    if state == "resume":
        return argv + ["--resume"]
    return argv + ["--task", spec.task, "--variant", spec.variant, "--seed", str(spec.seed),
                   *spec.extra, *a.online_args]


def _die_with_parent() -> None:
    """Child side of Popen: get SIGKILL when the compare process dies (Linux prctl)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass
    os.setpgid(0, 0)   # Ctrl-C in the terminal reaches only us; we forward it once


def _runs_to_do(specs: Sequence[RunSpec], a: GridSettings) -> list[tuple[RunSpec, str]]:
    """The specs still to run, each with its state (printed for every spec)."""
    todo = []
    for s in specs:
        st = s.state(a.env_steps, a.wall_budget)
        origin = f" (from {s.carried['carried_from']['results']})" if st == "carried" else ""
        print(f"[compare] {s.task}/{s.label}/seed{s.seed}: {st}{origin}", flush=True)
        if st == "fresh" and s.run_dir.exists():
            shutil.rmtree(s.run_dir)   # killed before its first checkpoint: nothing to keep
        if st not in ("done", "carried"):
            todo.append((s, st))
    return todo


def _start_run(s: RunSpec, st: str, a: GridSettings) -> tuple[subprocess.Popen, object]:
    """A protocad-online worker for ``s``, its output appended to RUN_DIR/online.log; the
    process and that open log."""
    s.run_dir.mkdir(parents=True, exist_ok=True)
    log = open(s.run_dir / "online.log", "a")
    p = subprocess.Popen(online_argv(s, a, st), stdout=log, stderr=subprocess.STDOUT,
                         stdin=subprocess.DEVNULL, preexec_fn=_die_with_parent)
    print(f"[compare] started {s.task}/{s.label}/seed{s.seed} ({st}) pid {p.pid} on "
          f"{s.device}", flush=True)
    return p, log


def _ended_well(s: RunSpec, p: subprocess.Popen) -> bool:
    """Whether the ended run ``s`` reached one of its budgets; says how it ended either way."""
    res = runs.read_run_json(s.run_dir).get("result") or {}
    ok = p.returncode == 0 and res.get("status") in ("finished", "wall_budget")
    print(f"[compare] {s.task}/{s.label}/seed{s.seed}: exit {p.returncode}, "
          f"{res.get('status', 'no result')} at {res.get('env_steps', '?')} env steps"
          + ("" if ok else f" (see {s.run_dir / 'online.log'})"), flush=True)
    return ok


def _stop_runs(running: dict[int, tuple[RunSpec, subprocess.Popen, object]]) -> None:
    """Asks every run still going to stop (each checkpoints and exits), waits for them."""
    for s, p, log in running.values():
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for s, p, log in running.values():
        try:
            p.wait(timeout=300)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
        log.close()


def run_grid(specs: Sequence[RunSpec], a: GridSettings,
             on_progress: Callable[[dict[Path, tuple[int, int]]], None] = lambda running: None) -> int:
    """Runs every unfinished spec, at most a.jobs at once, calling on_progress(running: run dir
    -> (env steps, updates) of the runs going on) after each run ends and at each status line;
    an OSError or ValueError from it is reported and the runs go on. Returns the number that
    failed (-1: interrupted)."""
    todo = _runs_to_do(specs, a)
    running: dict[int, tuple[RunSpec, subprocess.Popen, object]] = {}
    failed = 0
    bar = console.progress(len(specs) * a.env_steps, desc="env steps (all runs)", unit="step")
    done_steps = {id(s): (a.env_steps if s.state(a.env_steps, a.wall_budget) in ("done", "carried") else 0)
                  for s in specs}
    bar.update(sum(done_steps.values()))
    last_status = time.monotonic() - a.status_every + min(a.status_every, FIRST_ESTIMATE_S)
    remaining = sum(a.env_steps - done_steps[id(s)] for s in specs)
    print(f"[compare] {len(todo)} of {len(specs)} runs to go, {remaining:,} env steps in all, "
          f"{a.jobs} at once; the estimated wall time follows a first timing of "
          f"{min(a.status_every, FIRST_ESTIMATE_S):.0f} s", flush=True)
    updates = {id(s): 0 for s in specs}

    def progress() -> None:
        try:
            on_progress({s.run_dir: (done_steps[id(s)], updates[id(s)]) for s, _, _ in running.values()})
        except (OSError, ValueError) as exc:   # a full disk, say: the runs matter more than the file
            print(f"[compare] could not write the grid's results ({exc}); the runs go on, and it is "
                  "tried again at the next status line", file=sys.stderr, flush=True)
    started = {}   # id(spec) -> (monotonic time, updates) when this invocation first saw it train
    with console.StopFlag() as stop:
        try:
            while (todo or running) and not stop.stop:
                while todo and len(running) < a.jobs and not stop.stop:
                    s, st = todo.pop(0)
                    p, log = _start_run(s, st, a)
                    running[p.pid] = (s, p, log)
                time.sleep(1.0)
                for pid, (s, p, log) in list(running.items()):
                    steps, updates[id(s)] = results_json.latest_progress(s.run_dir)
                    bar.update(max(0, steps - done_steps[id(s)]))
                    done_steps[id(s)] = max(done_steps[id(s)], steps)
                    if p.poll() is None:
                        continue
                    log.close()
                    del running[pid]
                    failed += 0 if _ended_well(s, p) else 1
                    progress()
                for s, _, _ in running.values():
                    if updates[id(s)] > 0:   # training, prefill over: its pace is the grid's
                        started.setdefault(id(s), (time.monotonic(), updates[id(s)]))
                if running and time.monotonic() - last_status > a.status_every:
                    last_status = time.monotonic()
                    print("[compare] " + ", ".join(f"{s.label}/seed{s.seed}: {done_steps[id(s)]}"
                                                   for s, _, _ in running.values())
                          + grid_estimate(specs, running, started, done_steps, updates, a), flush=True)
                    progress()
        finally:
            _stop_runs(running)
            bar.close()
    if stop.stop:
        print("[compare] interrupted: every run saved its checkpoint; re-run the same command to "
              "resume", flush=True)
        return -1
    return failed


#: Seconds of running before the first status line with a wall-time estimate.
FIRST_ESTIMATE_S = 120.0


def grid_estimate(specs, running, started, done_steps, updates, a) -> str:
    """'; about 3h10m left' from the updates/s the running runs made since this invocation saw
    them train and the updates the grid has left (env steps left x C per episode, from the
    runs' protocol in run.json), a.jobs at once. Updates are the cost: prefill (random actions,
    seconds) would make a rate of env steps promise hours too few; evaluations are not counted."""
    now = time.monotonic()
    rates = [(updates[id(s)] - started[id(s)][1]) / max(1e-9, now - started[id(s)][0])
             for s, _, _ in running.values()
             if id(s) in started and now - started[id(s)][0] > min(30.0, a.status_every)]
    rates = [r for r in rates if r > 0]
    protocol = next((p for p in (runs.read_run_json(s.run_dir).get("protocol") for s, _, _ in running.values())
                     if p), None)
    if not rates or not protocol:
        return "; no estimate yet"
    per_step = float(protocol["updates_per_episode"]) / float(protocol["time_limit"])
    prefill = int(protocol["prefill_episodes"]) * int(protocol["time_limit"])
    left = sum(max(0, a.env_steps - max(done_steps[id(s)], prefill)) * per_step for s in specs)
    per_run = sum(rates) / len(rates)
    seconds = left / (per_run * min(a.jobs, max(1, len(running))))
    return f"; about {cli_values.format_duration(seconds)} left ({per_run:.2f} updates/s per run)"


def earlier_grid_wall_time(out: Path) -> float:
    """Wall time of the grid's earlier invocations here (OUT/grid.json). Where none recorded
    its share, the time from the oldest run's config.yaml to now (call it before starting)."""
    try:
        return float(json.loads((Path(out) / "grid.json").read_text()).get("wall_time_s", 0.0))
    except (OSError, ValueError, AttributeError):
        starts = [p.stat().st_mtime for p in Path(out).glob("*/*/seed*/config.yaml")]
        return max(0.0, time.time() - min(starts)) if starts else 0.0


def save_grid_wall_time(out: Path, total: float) -> None:
    runs.atomic_write_json(Path(out) / "grid.json", {"wall_time_s": round(total, 1)})


# ---------------------------------------------------------------------- settings and CLI
@dataclass
class GridSettings:
    """A grid of protocad-online runs and what to report from it."""

    tasks: list[str] = arg(["pendulum_swingup"], choices=sorted(TASKS), group="grid")
    """tasks of the grid"""
    variants: list[str] = arg(["protocad", "dreamer"], choices=VARIANTS, group="grid")
    """variants of the grid"""
    seeds: list[int] = arg([0, 1, 2], nargs="*", group="grid")
    """seeds of every variant (none: only the anchor's)"""
    anchor_seeds: list[int] = arg([], nargs="*", group="grid")
    """also run dreamer on the unrandomized task (label dreamer_standard) with these seeds"""
    from_results: list[str] = arg([], nargs="+", metavar="RESULTS_JSON", group="grid")
    """results.json of this grid made elsewhere (another machine, an earlier session): the runs
    finished there count as done, their rows are kept, only the others run here (the budgets
    and the arguments after -- must be the same)"""
    env_steps: int = arg(2_000_000, group="budgets and resources")
    """env-step budget of every run"""
    wall_budget: float | None = arg(None, type=cli_values.parse_duration, metavar="DURATION",
                                    group="budgets and resources")
    """training wall-time budget of every run (e.g. 85m, 1h30m, 5400)"""
    jobs: int = arg(2, type=cli_values.positive_int, group="budgets and resources")
    """runs at once (worker processes)"""
    threads: int = arg(1, type=cli_values.non_negative_int, group="budgets and resources")
    """torch threads of each run"""
    devices: list[str] = arg(["cpu"], group="budgets and resources")
    """devices assigned to runs round robin (cpu, cuda, cuda:N)"""
    out: str | None = arg(None, group="output")
    """directory of the grid (default runs/compare-STAMP)"""
    report: list[str] = arg([], nargs="+", metavar="RESULTS_JSON", group="output")
    """only report from these results.json files (no runs): each file's tables in turn, one
    plot of all their curves (the anchor's grid and the comparison's, say)"""
    markdown: bool = arg(False, group="output")
    """print the README results section (generated from results.json)"""
    update_readme: str | None = arg(None, metavar="README", group="output")
    """replace the generated results section of this markdown file (README.md, or
    msgs_docs/results.md where the CPU results live) in place"""
    image: str | None = arg(None, metavar="PNG", group="output")
    """also write the learning-curve plot here, and link it from the markdown section (a path
    from the repository root; the link is made relative to --update-readme's file)"""
    rrd: str | None = arg(None, metavar="RRD", group="output")
    """write the curves' rerun recording here (a grid also writes OUT/curves.rrd)"""
    random_baseline: bool = arg(False, group="output")
    """evaluate the uniform random policy once per task (OUT/TASK/random.json, the final
    evaluation's contexts and episodes) and report it beside the variants"""
    random_episodes: int | None = arg(None, group="output")
    """episodes per context of --random-baseline (default: the runs' --final-episodes)"""
    ship: str | None = arg(None, metavar="POLICY_PT", group="output")
    """write the best run's policy here (highest final return on unseen contexts; bfloat16
    weights and provenance, POLICY_PT with .json beside it: trainer.research.ship)"""
    ship_label: str | None = arg(None, metavar="LABEL", group="output")
    """--ship only among this label's runs, whatever their evaluation split (dreamer_standard:
    the anchor's best run, by its final return on the standard task)"""
    ship_evaluation: str | None = arg(None, metavar="EVAL_JSON", group="output")
    """with --ship: `protocad-evaluate CHECKPOINT --random --json EVAL_JSON` of the shipped run's
    checkpoint on unseen contexts, kept in the provenance (checked to be that checkpoint's)"""
    power: bool = arg(False, group="sizing the next comparison (no runs)")
    """only print the table that sizes the next paired grid (statistics.power_table: per paper task
    and budget the expected effect, pair SD, pairs for 80%% power, core-hours); runs nothing"""
    power_json: str | None = arg(None, metavar="FILE", group="sizing the next comparison (no runs)")
    """--power, and write the table as JSON too (msgs_docs/results/power_table.json)"""
    status_every: float = arg(300.0, group="output")
    """seconds between status lines"""
    online_args: list[str] = arg([], "online_args", nargs=argparse.REMAINDER)
    """-- then arguments for every protocad-online run"""


def build_parser() -> argparse.ArgumentParser:
    return settings_parser(
        "protocad-compare",
        "Run tasks x variants x seeds as parallel protocad-online runs (resumable), gather their "
        "evaluation curves into OUT/results.json and report: final test-context return per task and "
        "variant (mean over seeds, 95% bootstrap CI, the paper's figure beside it), mean / median / "
        "IQM over tasks, a learning-curve PNG and a rerun recording. Arguments after `--` go to "
        "every protocad-online run.",
        [(None, GridSettings)])


def _reported_docs(a: GridSettings) -> tuple[list[dict], list[str], dict]:
    """--report: the files' documents, their paths, and all of them combined."""
    if a.ship and len(a.report) > 1:
        raise ValueError("--ship takes the best run of one results.json: give --report one file")
    docs, sources = [results_json.load_results(p) for p in a.report], list(a.report)
    return docs, sources, report.combined(docs, sources)   # a run in two files: refused before anything is written


def _run_and_gather(a: GridSettings, argv: Sequence[str] | None) -> tuple[list[dict], list[str], dict, int]:
    """Runs the grid into a.out (resuming what is there), keeping OUT/results.json current;
    returns its document, path and combination as _reported_docs does, and the number of
    runs that failed (-1: interrupted, with the finished runs' results saved)."""
    if warning := stale_install():
        print(f"[compare] warning: {warning}", file=sys.stderr, flush=True)
    out_dir = Path(a.out)
    specs = plan(a)
    carried = carry_finished_runs(specs, a)   # a file it cannot take: refused before anything is made
    out_dir.mkdir(parents=True, exist_ok=True)
    if a.from_results:
        print(f"[compare] {carried} finished run(s) carried from {', '.join(a.from_results)}",
              flush=True)
    earlier, t0 = earlier_grid_wall_time(out_dir), time.monotonic()
    command = ["protocad-compare", *(sys.argv[1:] if argv is None else argv)]

    def save(random: dict, running: dict | None = None) -> dict:
        doc = results_json.gather(specs, command=command, env_steps=a.env_steps, wall_budget=a.wall_budget,
                       jobs=a.jobs, threads=a.threads, wall_time=earlier + time.monotonic() - t0,
                       random=random, running=running)
        results_json.save_results(doc, out_dir / "results.json")
        return doc

    def random_rows(evaluate: bool = True) -> dict:
        return results_json.random_baselines(a.tasks, a.out, episodes=a.random_episodes, evaluate=evaluate,
                                  protocols=run_protocols(specs))

    # Rewritten as runs finish, at each status line and when cut short: what finished can
    # be committed anytime, and `--report` shows where the others stand.
    failed = run_grid(specs, a, on_progress=lambda running: save(random_rows(evaluate=False), running))
    save_grid_wall_time(out_dir, earlier + time.monotonic() - t0)
    if failed < 0:
        save(random_rows(evaluate=False))
        print(f"[compare] results of the finished runs so far: {out_dir / 'results.json'}", flush=True)
        return [], [], {}, failed
    docs = [save(random_rows() if a.random_baseline else {})]
    sources = [str(out_dir / "results.json")]
    everything = report.combined(docs, sources)
    print(f"[compare] {len(specs)} runs, {failed} failed; results: {sources[0]}", flush=True)
    return docs, sources, everything, failed


def main(argv: Sequence[str] | None = None) -> int:
    a = build(GridSettings, vars(build_parser().parse_args(argv)))
    if a.online_args and a.online_args[0] == "--":
        a.online_args = a.online_args[1:]
    failed = 0
    try:
        if a.power or a.power_json:
            return report.print_power_table(a.power_json)
        if a.report:
            docs, sources, everything = _reported_docs(a)
        else:
            a = dataclasses.replace(a, out=str(Path(a.out or time.strftime("runs/compare-%Y%m%d-%H%M%S"))))
            docs, sources, everything, failed = _run_and_gather(a, argv)
            if failed < 0:
                return 130

        report.write_reports(docs, sources, everything, grid_dir=None if a.report else Path(a.out), image=a.image,
                        rrd=a.rrd, markdown=a.markdown, readme=a.update_readme)
        if a.ship:
            from trainer.research.ship import ship_best, shipped_line

            path, prov = ship_best(docs[0], a.ship, sources[0], label=a.ship_label, evaluation=a.ship_evaluation)
            print(f"[compare] {shipped_line(path, prov)}", flush=True)
    except (ValueError, OSError) as exc:
        print(f"protocad-compare: error: {exc}", file=sys.stderr)
        return 2
    return 0 if a.report or not failed else 1


if __name__ == "__main__":
    sys.exit(main())
