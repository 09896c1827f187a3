"""results.json of `protocad-compare`: gathering, its schema, the statistics, and what is made
from it (the text report, the learning-curve PNG, the rerun recording, the README section).

Statistics follow rliable (Agarwal et al., "Deep RL at the Edge of the Statistical Precipice",
NeurIPS 2021): a run's score is its final mean return over the test contexts; per task and
variant the mean over seeds; over tasks the mean, the median of the per-task means and the
interquartile mean (IQM: the mean of the middle 50% of all task x seed scores, i.e.
`scipy.stats.trim_mean(scores, 0.25)`); 95% intervals from the stratified percentile bootstrap
(seeds resampled with replacement within each task). rliable itself is not a dependency: it
pulls arch, statsmodels, pandas and seaborn for the two functions below.

Schema (RESULTS_SCHEMA, checked on every save and load):

    {"schema": "protocad-compare/1",
     "command": [argv...], "code_version": "git commit[+dirty]", "created": "ISO 8601 UTC",
     "machine": {"cpu", "cores", "cpu_capability", "torch", "gpu"},
     "budgets": {"env_steps", "wall_budget_s", "jobs", "threads_per_run"},
     "wall_time_s": seconds the grid ran (summed over invocations),
     "runs": [{"task", "label", "variant", "seed", "run_dir", "status", "env_steps", "updates",
               (status: finished | wall_budget | running | interrupted | failed | missing;
               'running' only in a results.json written while its grid runs)
               "wall_time_s", "precision", "preset", "eval_split",
               "final": {"mean_return", "episodes", "per_context": {"m=0.2": return, ...}} | null,
               "curve": [{"env_steps", "mean_return", "tag"}],
               "render_quality": "fast" | "default"  (optional: how its envs rendered, from
               its config.yaml; absent in files written before 2026-12-04, whose runs all
               rendered "fast"),
               "reference", "collect_interval" (C), "prototype_freeze" (the effective count of
               updates the prototypes were frozen for; null for variants without them)
               (optional: absent in files written before the freeze was scaled to the run),
               "final_train": the final evaluation on the training contexts (optional:
               protocad-online --final-train-contexts),
               "superseded": why a row no longer counts (optional),
               "carried_from": {"results", "code_version", "machine", "created"}  (optional: a
               run finished elsewhere, taken over by `--from-results`)}],
     "random": {task: {"mean_return", "episodes", "per_context"}}}
"""
from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from trainer.provenance import code_version

SCHEMA_ID = "protocad-compare/1"

# Paper Table 1 ("compare"): unseen dynamics at 2M env steps, mean (std over seeds).
PAPER_TABLE1: dict[str, dict[str, tuple[float, float]]] = {
    "cheetah_run": {"protocad": (537.9, 46.7), "dreamer": (450.9, 57.5), "dreamerpro": (394.3, 60.2),
                    "dreamer_context": (528.0, 52.4), "drq": (471.1, 49.0)},
    "finger_spin": {"protocad": (585.0, 162.1), "dreamer": (453.0, 58.3), "dreamerpro": (458.5, 74.0),
                    "dreamer_context": (428.0, 43.0), "drq": (592.3, 48.4)},
    "hopper_hop": {"protocad": (176.6, 95.2), "dreamer": (112.6, 31.2), "dreamerpro": (148.2, 73.1),
                   "dreamer_context": (148.6, 77.5), "drq": (73.7, 16.2)},
    "hopper_stand": {"protocad": (829.6, 53.0), "dreamer": (818.1, 121.1), "dreamerpro": (644.2, 62.4),
                     "dreamer_context": (725.2, 110.4), "drq": (781.0, 175.4)},
    "pendulum_swingup": {"protocad": (802.0, 15.3), "dreamer": (712.8, 82.7), "dreamerpro": (737.0, 49.9),
                         "dreamer_context": (794.0, 14.0), "drq": (504.0, 272.1)},
    "quadruped_run": {"protocad": (529.0, 36.5), "dreamer": (444.1, 21.7), "dreamerpro": (502.6, 59.3),
                      "dreamer_context": (501.9, 39.7), "drq": (251.0, 184.6)},
    "walker_run": {"protocad": (447.1, 38.4), "dreamer": (392.9, 31.1), "dreamerpro": (378.0, 34.9),
                   "dreamer_context": (427.6, 30.7), "drq": (378.7, 50.1)},
    "walker_walk": {"protocad": (858.5, 15.4), "dreamer": (825.6, 24.4), "dreamerpro": (815.5, 53.6),
                    "dreamer_context": (845.5, 12.8), "drq": (927.1, 17.7)},
}
PAPER_ENV_STEPS = 2_000_000
#: protocad-compare's label of the anchor (Dreamer on the unrandomized task).
ANCHOR_LABEL = "dreamer_standard"

_NUM = {"type": "number"}
_INT = {"type": "integer"}
_EVAL = {"type": "object", "required": ["mean_return", "episodes", "per_context"],
         "properties": {"mean_return": _NUM, "episodes": _INT,
                        "per_context": {"type": "object", "additionalProperties": _NUM}}}
RESULTS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "object",
    "required": ["schema", "command", "code_version", "created", "machine", "budgets", "wall_time_s",
                 "runs", "random"],
    "properties": {
        "schema": {"const": SCHEMA_ID},
        "command": {"type": "array", "items": {"type": "string"}},
        "code_version": {"type": "string"},
        "created": {"type": "string"},
        "machine": {"type": "object", "required": ["cpu", "cores", "cpu_capability", "torch", "gpu"]},
        "budgets": {"type": "object", "required": ["env_steps", "wall_budget_s", "jobs", "threads_per_run"],
                    "properties": {"env_steps": _INT, "wall_budget_s": {"type": ["number", "null"]},
                                   "jobs": _INT, "threads_per_run": _INT}},
        "wall_time_s": _NUM,
        "runs": {"type": "array", "items": {
            "type": "object",
            "required": ["task", "label", "variant", "seed", "run_dir", "status", "env_steps", "updates",
                         "wall_time_s", "precision", "preset", "eval_split", "final", "curve"],
            "properties": {
                "task": {"type": "string"}, "label": {"type": "string"}, "variant": {"type": "string"},
                "seed": _INT, "run_dir": {"type": "string"},
                "status": {"enum": ["finished", "wall_budget", "running", "interrupted", "failed", "missing"]},
                "env_steps": _INT, "updates": _INT, "wall_time_s": _NUM,
                "precision": {"type": "string"}, "preset": {"type": "string"},
                "eval_split": {"enum": ["test", "train"]},
                "render_quality": {"enum": ["fast", "default"]},
                "reference": {"type": "string"}, "collect_interval": _INT,
                "prototype_freeze": {"type": ["integer", "null"]},
                "final_train": _EVAL,
                "superseded": {"type": "string"},
                "final": {"oneOf": [{"type": "null"}, _EVAL]},
                "curve": {"type": "array", "items": {
                    "type": "object", "required": ["env_steps", "mean_return", "tag"],
                    "properties": {"env_steps": _INT, "mean_return": _NUM, "tag": {"type": "string"}}}},
                "carried_from": {"type": "object", "required": ["results", "code_version", "machine", "created"],
                                 "properties": {"results": {"type": "string"}, "code_version": {"type": "string"},
                                                "machine": {"type": "object"}, "created": {"type": "string"}}},
            }}},
        "random": {"type": "object", "additionalProperties": _EVAL},
    },
}


# ----------------------------------------------------------------------------- statistics
def standard_context(task: str) -> str:
    """The unrandomized task's context (every scale 1), e.g. 'm=1,d=1': the anchor's train and
    evaluation context, as a --train-context value."""
    from sim_bridge.contract.contexts import get_task

    return ",".join(f"{p}=1" for p in get_task(task).params)


def iqm(scores: np.ndarray) -> float:
    """Interquartile mean: the mean of the middle 50% (25% trimmed from each end)."""
    from scipy.stats import trim_mean

    return float(trim_mean(np.asarray(scores, float), 0.25))


def aggregate_mean(per_task: Sequence[np.ndarray]) -> float:
    """Mean over every task x seed score."""
    return float(np.mean(np.concatenate(per_task)))


def aggregate_median(per_task: Sequence[np.ndarray]) -> float:
    """Median over tasks of the per-task mean (as the paper and rliable report it)."""
    return float(np.median([np.mean(s) for s in per_task]))


def aggregate_iqm(per_task: Sequence[np.ndarray]) -> float:
    return iqm(np.concatenate(per_task))


AGGREGATES: dict[str, Callable[[Sequence[np.ndarray]], float]] = {
    "mean": aggregate_mean, "median": aggregate_median, "iqm": aggregate_iqm}


def bootstrap_ci(per_task: Sequence[Sequence[float]], statistic: Callable[[Sequence[np.ndarray]], float],
                 reps: int = 10_000, confidence: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Stratified percentile bootstrap interval of `statistic(per_task)`: every replicate
    resamples, independently per task, that task's scores with replacement. A single task is
    the ordinary bootstrap of its seeds. Deterministic for a seed."""
    arrays = [np.asarray(s, float) for s in per_task]
    if not arrays or any(a.size == 0 for a in arrays):
        raise ValueError("bootstrap_ci needs at least one score per task")
    rng = np.random.default_rng(seed)
    idx = [rng.integers(0, a.size, size=(reps, a.size)) for a in arrays]
    stats = np.array([statistic([a[i[r]] for a, i in zip(arrays, idx)]) for r in range(reps)])
    lo, hi = np.quantile(stats, [(1 - confidence) / 2, 1 - (1 - confidence) / 2])
    return float(lo), float(hi)


# ----------------------------------------------------------------------------- gathering
def _read_jsonl(path: Path) -> list[dict]:
    rows = []
    try:
        with open(path) as f:
            for line in f:
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError:
                    pass   # a torn last line after a kill
    except OSError:
        pass
    return rows


def _eval_entry(d: Mapping[str, Any]) -> dict[str, Any]:
    from trainer.learn.evaluate import context_label

    return {"mean_return": round(float(d["mean_return"]), 3),
            "episodes": int(d.get("episodes", 0)),
            "per_context": {context_label(pc["context"]): round(float(pc["mean_return"]), 3)
                            for pc in d.get("per_context", [])}}


def gather_run(task: str, label: str, variant: str, seed: int, run_dir: Path) -> dict[str, Any]:
    """One run directory of protocad-online as a results.json row."""
    run_dir = Path(run_dir)
    try:
        info = json.loads((run_dir / "run.json").read_text())
    except (OSError, json.JSONDecodeError):
        info = {}
    res = info.get("result") or {}
    curve, seen = [], set()
    for row in _read_jsonl(run_dir / "eval.jsonl"):
        if row.get("policy", "").startswith("random") or "mean_return" not in row:
            continue
        key = (int(row["env_steps"]), row.get("tag", ""))
        if key in seen:       # an evaluation repeated after a resume: keep the newest
            curve = [c for c in curve if (c["env_steps"], c["tag"]) != key]
        seen.add(key)
        curve.append({"env_steps": int(row["env_steps"]), "mean_return": round(float(row["mean_return"]), 3),
                      "tag": str(row.get("tag", ""))})
    curve.sort(key=lambda c: (c["env_steps"], c["tag"] == "final"))
    final = None
    try:
        final = _eval_entry(json.loads((run_dir / "eval" / "final.json").read_text()))
    except (OSError, json.JSONDecodeError, KeyError):
        pass
    proto = info.get("protocol") or {}
    row = {"task": task, "label": label, "variant": variant, "seed": int(seed), "run_dir": str(run_dir),
            "status": res.get("status", "missing" if not info else "failed"),
            "env_steps": int(res.get("env_steps", 0)), "updates": int(res.get("updates", 0)),
            "wall_time_s": float(res.get("wall_time", 0.0)), "precision": str(res.get("precision", "")),
            "preset": str(info.get("preset", "")), "eval_split": proto.get("eval_split") or "test",
            "final": final, "curve": curve}
    try:
        row["final_train"] = _eval_entry(json.loads((run_dir / "eval" / "final_train.json").read_text()))
    except (OSError, json.JSONDecodeError, KeyError):
        pass
    if "prototype_freeze" in res:
        row["prototype_freeze"] = res["prototype_freeze"]
    if "updates_per_episode" in proto:
        row["collect_interval"] = int(proto["updates_per_episode"])
    cfg = _saved_config(run_dir)
    quality = (cfg.get("train") or {}).get("render_quality")
    if quality:
        row["render_quality"] = str(quality)
    if cfg.get("reference"):
        row["reference"] = str(cfg["reference"])
    return row


def _saved_config(run_dir: Path) -> dict[str, Any]:
    """A run's saved config.yaml as a mapping ({} where there is none to read)."""
    import yaml

    try:
        cfg = yaml.safe_load((Path(run_dir) / "config.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return {}
    return cfg if isinstance(cfg, dict) else {}



def runs_code_version(specs: Iterable[Any]) -> str:
    """The code the runs were trained with (run.json `code_versions`, every invocation's), or,
    for runs that do not record it, the tree that gathered them, saying so."""
    seen: list[str] = []
    for s in specs:
        carried = getattr(s, "carried", None)
        try:
            versions = (carried["carried_from"]["code_version"].split(", ") if carried else
                        json.loads((Path(s.run_dir) / "run.json").read_text()).get("code_versions"))
        except (OSError, json.JSONDecodeError):
            versions = None
        if not versions:
            return f"{code_version()} (the gathering tree: the runs do not record their code)"
        seen += [v for v in versions if v not in seen]
    return ", ".join(seen) if seen else code_version()


def machine_info() -> dict[str, Any]:
    import torch

    from protocad_ros.model.precision import cpu_capability

    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"cpu": cpu, "cores": os.cpu_count() or 1, "cpu_capability": cpu_capability(),
            "torch": torch.__version__, "gpu": gpu, "platform": platform.platform()}


def gather(specs: Iterable[Any], *, command: Sequence[str], env_steps: int, wall_budget: float | None,
           jobs: int, threads: int, wall_time: float, random: Mapping[str, Any] | None = None,
           running: Mapping[Path, tuple[int, int]] | None = None) -> dict[str, Any]:
    """results.json from RunSpec-like objects (task, label, variant, seed, run_dir; `carried`: a
    row finished elsewhere, taken as it is unless the run finished here too). `running`: run
    directory -> (env steps, updates) its metrics show now, for the runs still going (their
    run.json still holds how the previous invocation ended)."""
    specs = list(specs)
    rows = []
    for s in specs:
        row = gather_run(s.task, s.label, s.variant, s.seed, s.run_dir)
        if running and s.run_dir in running:
            steps, updates = running[s.run_dir]
            row.update(status="running", env_steps=max(row["env_steps"], int(steps)),
                       updates=max(row["updates"], int(updates)))
        carried = getattr(s, "carried", None)
        done_here = row["status"] in ("finished", "wall_budget") and row["final"] is not None
        rows.append(carried if carried is not None and not done_here else row)
    return {"schema": SCHEMA_ID, "command": [str(c) for c in command], "code_version": runs_code_version(specs),
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "machine": machine_info(),
            "budgets": {"env_steps": int(env_steps), "wall_budget_s": wall_budget, "jobs": int(jobs),
                        "threads_per_run": int(threads)},
            "wall_time_s": round(float(wall_time), 1),
            "runs": rows,
            "random": {k: _eval_entry(v) for k, v in (random or {}).items()}}


def validate(doc: Mapping[str, Any]) -> None:
    """jsonschema validation against RESULTS_SCHEMA (ValueError with the first problem)."""
    try:
        import jsonschema
    except ImportError:   # the GPU machine's bare Python: say so, check again where it is installed
        print(f"[results] jsonschema is not installed: {SCHEMA_ID} not checked here", file=sys.stderr)
        return
    try:
        jsonschema.validate(doc, RESULTS_SCHEMA)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise ValueError(f"results.json does not match {SCHEMA_ID} at {where}: {exc.message}") from None


def save_results(doc: Mapping[str, Any], path: Path) -> Path:
    from protocad_ros.atomic import atomic_write_text

    validate(doc)
    atomic_write_text(Path(path), json.dumps(doc, indent=1) + "\n")
    return Path(path)


def load_results(path: str | Path) -> dict[str, Any]:
    try:
        doc = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not JSON: {exc}") from None
    validate(doc)
    return doc


# ----------------------------------------------------------------------------- summaries
def final_scores(doc: Mapping[str, Any]) -> dict[tuple[str, str], list[dict]]:
    """(task, label) -> the runs that have a final evaluation, in seed order."""
    out: dict[tuple[str, str], list[dict]] = {}
    for r in sorted(doc["runs"], key=lambda r: (r["task"], r["label"], r["seed"])):
        if r["final"] is not None and not r.get("superseded"):
            out.setdefault((r["task"], r["label"]), []).append(r)
    return out


def summarize(doc: Mapping[str, Any], reps: int = 10_000) -> dict[str, Any]:
    """Per (task, label): n, mean, 95% CI, env steps, paper figure; per label over tasks: mean,
    median, IQM with stratified-bootstrap CIs (randomized-context labels only)."""
    rows = []
    by_label: dict[str, dict[str, np.ndarray]] = {}
    for (task, label), rs in final_scores(doc).items():
        scores = np.array([r["final"]["mean_return"] for r in rs])
        lo, hi = bootstrap_ci([scores], aggregate_mean, reps=reps)
        paper = PAPER_TABLE1.get(task, {}).get(label)
        rows.append({"task": task, "label": label, "n": len(rs), "mean": float(scores.mean()),
                     "ci": (lo, hi), "range": (float(scores.min()), float(scores.max())), "env_steps": sorted({r["env_steps"] for r in rs}),
                     "updates": sorted({r["updates"] for r in rs}), "paper": paper,
                     "statuses": sorted({r["status"] for r in rs}),
                     "eval_split": rs[0]["eval_split"]})
        if rs[0]["eval_split"] == "test":
            by_label.setdefault(label, {})[task] = scores
    aggregates = []
    for label, tasks in sorted(by_label.items()):
        per_task = [tasks[t] for t in sorted(tasks)]
        agg = {"label": label, "tasks": len(per_task)}
        for name, fn in AGGREGATES.items():
            agg[name] = (fn(per_task), bootstrap_ci(per_task, fn, reps=reps))
        aggregates.append(agg)
    return {"rows": rows, "aggregates": aggregates}


def _ci(v: float, ci: tuple[float, float]) -> str:
    return f"{v:.1f} [{ci[0]:.1f}, {ci[1]:.1f}]"


#: Below this many seeds a percentile bootstrap of the mean is little more than [min, max]
#: (with 3 seeds exactly that): tables show the range and call it one.
MIN_SEEDS_FOR_CI = 5


def _mean_and_spread(r: Mapping[str, Any]) -> str:
    if r["n"] < MIN_SEEDS_FOR_CI:
        return f"{r['mean']:.1f} (range {r['range'][0]:.1f}-{r['range'][1]:.1f})"
    return _ci(r["mean"], r["ci"])


def paired_difference(doc: Mapping[str, Any], task: str, a: str = "protocad", b: str = "dreamer",
                      confidence: float = 0.95) -> dict[str, Any] | None:
    """The primary metric of a paired comparison: per seed that both labels finished, the final
    return of `a` minus that of `b`; their mean with a Student-t interval over the seeds (None
    with fewer than 2 pairs)."""
    from scipy import stats

    scores = final_scores(doc)
    by_seed = [{r["seed"]: r["final"]["mean_return"] for r in scores.get((task, lab), [])} for lab in (a, b)]
    seeds = sorted(set(by_seed[0]) & set(by_seed[1]))
    if len(seeds) < 2:
        return None
    diffs = np.array([by_seed[0][s] - by_seed[1][s] for s in seeds])
    half = stats.t.ppf((1 + confidence) / 2, len(diffs) - 1) * diffs.std(ddof=1) / np.sqrt(len(diffs))
    mean = float(diffs.mean())
    return {"task": task, "a": a, "b": b, "seeds": seeds, "diffs": [float(d) for d in diffs],
            "mean": mean, "ci": (mean - float(half), mean + float(half))}


def unseen_train_ratio(doc: Mapping[str, Any], task: str, label: str) -> dict[str, Any] | None:
    """Mean over seeds of (final return on unseen contexts) / (final return on training
    contexts), for the runs evaluated on both (protocad-online --final-train-contexts)."""
    ratios = [r["final"]["mean_return"] / r["final_train"]["mean_return"]
              for r in final_scores(doc).get((task, label), [])
              if r.get("final_train") and r["final_train"]["mean_return"] > 0]
    if not ratios:
        return None
    return {"task": task, "label": label, "n": len(ratios), "mean": float(np.mean(ratios)),
            "range": (float(min(ratios)), float(max(ratios)))}


def paired_lines(doc: Mapping[str, Any]) -> list[str]:
    """The paired difference and the unseen/train ratios, one line each, where the runs have them."""
    out = []
    tasks = sorted({r["task"] for r in doc["runs"]})
    for task in tasks:
        d = paired_difference(doc, task)
        if d is not None:
            verdict = ("ahead" if d["ci"][0] > 0 else "behind" if d["ci"][1] < 0 else "no difference shown")
            out.append(f"{task}: {d['a']} - {d['b']} paired over seeds {d['seeds']}: {d['mean']:+.1f} "
                       f"[95% t-interval {d['ci'][0]:+.1f}, {d['ci'][1]:+.1f}] ({verdict})")
        for label in sorted({r["label"] for r in doc["runs"] if r["task"] == task}):
            q = unseen_train_ratio(doc, task, label)
            if q is not None:
                out.append(f"{task}: {label} unseen/train ratio {q['mean']:.2f} over {q['n']} seed(s) "
                           f"(range {q['range'][0]:.2f}-{q['range'][1]:.2f})")
    return out


def _steps(values: Sequence[int]) -> str:
    return f"{values[0]:,}" if len(values) == 1 else f"{values[0]:,}-{values[-1]:,}"


def _paper(p: tuple[float, float] | None) -> str:
    return "-" if p is None else f"{p[0]:.1f} ± {p[1]:.1f}"


def table_rows(doc: Mapping[str, Any], summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    head = ["task", "variant", "seeds", "env steps", "updates",
            f"final return, mean [95% CI] (range below {MIN_SEEDS_FOR_CI} seeds)",
            "random policy", f"paper ({PAPER_ENV_STEPS // 1_000_000}M steps)"]
    rows = []
    for r in summary["rows"]:
        rnd = doc["random"].get(r["task"]) if r["eval_split"] == "test" else None
        ctx = standard_context(r["task"])
        label = r["label"] + ("" if r["eval_split"] == "test" else f" (train and eval on {ctx})")
        rows.append([r["task"], label, str(r["n"]), _steps(r["env_steps"]), _steps(r["updates"]),
                     _mean_and_spread(r), "-" if rnd is None else f"{rnd['mean_return']:.1f}",
                     _paper(r["paper"])])
    return head, rows


def _text_table(head: list[str], rows: list[list[str]]) -> str:
    w = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(head)]
    line = lambda cells: "  ".join(c.ljust(w[i]) for i, c in enumerate(cells))  # noqa: E731
    return "\n".join([line(head), line(["-" * x for x in w]), *(line(r) for r in rows)])


def _md_table(head: list[str], rows: list[list[str]]) -> str:
    return "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head),
                      *("| " + " | ".join(r) + " |" for r in rows)])


def aggregate_rows(summary: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    head = ["variant", "tasks", "mean [95% CI]", "median [95% CI]", "IQM [95% CI]"]
    rows = [[a["label"], str(a["tasks"]), _ci(*a["mean"]), _ci(*a["median"]), _ci(*a["iqm"])]
            for a in summary["aggregates"]]
    return head, rows


def progress_rows(doc: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    """The runs without a final evaluation yet (running, cut short, failed): how far each got
    and its latest evaluation, so a grid that spans sessions shows where it stands."""
    head = ["task", "variant", "seed", "status", "env steps", "updates", "latest evaluation"]
    budget = int(doc["budgets"]["env_steps"])
    rows = []
    for r in sorted(doc["runs"], key=lambda r: (r["task"], r["label"], r["seed"])):
        if r["final"] is not None:
            continue
        last = r["curve"][-1] if r["curve"] else None
        rows.append([r["task"], r["label"], str(r["seed"]), r["status"], f"{r['env_steps']:,} of {budget:,}",
                     f"{r['updates']:,}",
                     "-" if last is None else f"{last['mean_return']:.1f} at {last['env_steps']:,} env steps"])
    return head, rows


def format_report(doc: Mapping[str, Any]) -> str:
    s = summarize(doc)
    out = [f"results of {' '.join(doc['command'])}", f"code {doc['code_version']}; "
           f"{_machine_line(doc['machine'])}; grid wall time {doc['wall_time_s'] / 60:.1f} min"
           + carried_sentence(doc), "",
           _text_table(*table_rows(doc, s)), "", "over tasks (test contexts; stratified bootstrap):",
           _text_table(*aggregate_rows(s))]
    paired = paired_lines(doc)
    if paired:
        out += ["", "paired (the primary metric of msgs_docs/results.md):", *paired]
    superseded = superseded_lines(doc)
    if superseded:
        out += ["", "superseded (kept as measured, counted nowhere):", *superseded]
    progress = progress_rows(doc)
    if progress[1]:
        out += ["", f"not finished ({len(progress[1])} of {len(doc['runs'])} runs; as of {doc['created']}):",
                _text_table(*progress)]
    anchor = anchor_rows(doc)
    if anchor[1]:
        out += ["", "anchor vs DreamerV2's published seeds (standard task):", _text_table(*anchor)]
    return "\n".join(out)


def carried_sentence(doc: Mapping[str, Any]) -> str:
    """'. LABEL/seedS, ... finished elsewhere and came from FILE (machine; code)' for the rows
    taken over by --from-results, one sentence per file; '' when there are none."""
    origins: dict[str, list[str]] = {}
    for r in doc["runs"]:
        c = r.get("carried_from")
        if c:
            key = f"{c['results']} ({_machine_line(c['machine'])}; code {c['code_version']})"
            origins.setdefault(key, []).append(f"{r['label']}/seed{r['seed']}")
    return "".join(f". {', '.join(runs)} finished elsewhere and came from {where}"
                   for where, runs in origins.items())


def _machine_line(m: Mapping[str, Any]) -> str:
    gpu = f", GPU {m['gpu']}" if m.get("gpu") else ", no GPU"
    return f"{m['cpu']}, {m['cores']} cores, CPU capability {m['cpu_capability']}{gpu}, torch {m['torch']}"


# ----------------------------------------------------------------------------- curves
def curves(doc: Mapping[str, Any], task: str, label: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Env steps, mean over seeds and a 95% bootstrap interval of the test return at every
    env-step count that every seed of (task, label) evaluated at."""
    rs = [r for r in doc["runs"] if r["task"] == task and r["label"] == label and r["curve"]
          and not r.get("superseded")]
    if not rs:
        return (np.zeros(0),) * 4
    per_run = [{c["env_steps"]: c["mean_return"] for c in r["curve"]} for r in rs]
    steps = sorted(set.intersection(*(set(p) for p in per_run)))
    mean, lo, hi = [], [], []
    for st in steps:
        v = np.array([p[st] for p in per_run])
        mean.append(v.mean())
        a, b = bootstrap_ci([v], aggregate_mean, reps=2000) if len(v) > 1 else (v[0], v[0])
        lo.append(a)
        hi.append(b)
    return np.array(steps), np.array(mean), np.array(lo), np.array(hi)


#: DreamerV2's published per-seed curves on standard DMC (danijar/dreamerv2
#: scores/dmc-vision-dreamerv2.json @07d906e, the paper's eight tasks up to 300k env steps).
DREAMERV2_SCORES = Path(__file__).with_name("dreamerv2_dmc_vision.json")


def dreamerv2_reference(task: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """DreamerV2's published seeds on the standard task: env steps, mean, min and max over its
    seeds at every step all of them report (empty arrays for a task it has no curve of)."""
    doc = json.loads(DREAMERV2_SCORES.read_text())
    rs = [c for c in doc["curves"] if c["task"] == task]
    if not rs:
        return (np.zeros(0),) * 4
    steps = sorted(set.intersection(*(set(c["env_steps"]) for c in rs)))
    v = np.array([[dict(zip(c["env_steps"], c["return"]))[s] for s in steps] for c in rs])
    return np.array(steps), v.mean(0), v.min(0), v.max(0)


def anchor_rows(doc: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    """The anchor beside DreamerV2's published seeds at every env-step count both have: our mean
    over seeds, theirs with its range, and whether ours lies within that range."""
    head = ["task", "env steps", "dreamer_standard (mean of seeds)", "DreamerV2 mean (range)",
            "within range"]
    rows = []
    for task in sorted({r["task"] for r in doc["runs"] if r["label"] == ANCHOR_LABEL}):
        x, m, _, _ = curves(doc, task, ANCHOR_LABEL)
        n = len({r["seed"] for r in doc["runs"] if r["task"] == task and r["label"] == ANCHOR_LABEL})
        ours = dict(zip(x.tolist(), m.tolist()))
        for st, rm, lo, hi in zip(*dreamerv2_reference(task)):
            if int(st) in ours:
                v = ours[int(st)]
                rows.append([task, f"{int(st):,}", f"{v:.1f} (n={n})", f"{rm:.0f} ({lo:.0f}-{hi:.0f})",
                             "yes" if lo <= v <= hi else ("above" if v > hi else "no")])
    return head, rows


def labels_of(doc: Mapping[str, Any], task: str) -> list[str]:
    return sorted({r["label"] for r in doc["runs"] if r["task"] == task and not r.get("superseded")})


def superseded_lines(doc: Mapping[str, Any]) -> list[str]:
    """One line per superseded row: kept as measured, counted nowhere."""
    return [f"{r['task']} {r['label']} seed {r['seed']}"
            + (f" ({r['final']['mean_return']:.1f})" if r["final"] else "") + f": {r['superseded']}"
            for r in sorted(doc["runs"], key=lambda r: (r["task"], r["label"], r["seed"])) if r.get("superseded")]


def plot_curves(doc: Mapping[str, Any], path: str | Path) -> Path:
    """PNG: one panel per task, return vs env steps, a line per variant with its 95% band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = sorted({r["task"] for r in doc["runs"]})
    fig, axes = plt.subplots(1, max(1, len(tasks)), figsize=(5.2 * max(1, len(tasks)), 3.8), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        for label in labels_of(doc, task):
            x, m, lo, hi = curves(doc, task, label)
            if not x.size:
                continue
            n = len({r["seed"] for r in doc["runs"] if r["task"] == task and r["label"] == label})
            split = next(r["eval_split"] for r in doc["runs"] if r["task"] == task and r["label"] == label)
            name = f"{label} (n={n}" + (f", {standard_context(task)} only)" if split == "train" else ")")
            line, = ax.plot(x, m, marker="o", ms=3, label=name, gid=f"curve:{label}")
            ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2, linewidth=0)
        if any(r["task"] == task and r.get("base_label", r["label"]) == ANCHOR_LABEL for r in doc["runs"]):
            x, m, lo, hi = dreamerv2_reference(task)
            if x.size:   # the anchor's reference: DreamerV2's seeds, their range as the band
                until = max(r["env_steps"] for r in doc["runs"] if r["task"] == task)
                keep = x <= max(until, x[0])
                ax.errorbar(x[keep], m[keep], yerr=[m[keep] - lo[keep], hi[keep] - m[keep]],
                            color="black", ls=":", lw=1.2, marker="s", ms=4, capsize=4,
                            label="DreamerV2 published (mean, range of 5 seeds)", gid="curve:dreamerv2")
        rnd = doc["random"].get(task)
        if rnd is not None:
            ax.axhline(rnd["mean_return"], color="gray", ls="--", lw=1, label="random policy")
        ax.set_title(task)
        ax.set_xlabel("env steps")
        tested = any(r["task"] == task and r["eval_split"] == "test" for r in doc["runs"])
        ax.set_ylabel("mean return, test contexts" if tested else f"mean return, {standard_context(task)}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    fig.savefig(tmp, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)
    os.replace(tmp, path)
    return path


def log_curves_rerun(doc: Mapping[str, Any], path: str | Path) -> Path:
    """The same curves in a rerun recording, timeline `env_steps`:
    /curves/<task>/<label>/mean (mean over seeds) and /curves/<task>/<label>/seed<S>."""
    import rerun as rr

    rec = rr.RecordingStream("protocad-compare", recording_id=f"compare-{doc['created']}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec.save(str(path))
    for task in sorted({r["task"] for r in doc["runs"]}):
        for label in labels_of(doc, task):
            x, m, _, _ = curves(doc, task, label)
            for st, v in zip(x, m):
                rec.set_time("env_steps", sequence=int(st))
                rec.log(["curves", task, label, "mean"], rr.Scalars(float(v)))   # parts: escaped by rerun
            for r in doc["runs"]:
                if r["task"] == task and r["label"] == label:
                    for c in r["curve"]:
                        rec.set_time("env_steps", sequence=int(c["env_steps"]))
                        rec.log(["curves", task, label, f"seed{r['seed']}"], rr.Scalars(float(c["mean_return"])))
    rec.flush()
    rec.disconnect()
    return path


# ----------------------------------------------------------------------------- README section
BEGIN, END = "<!-- protocad-compare results: begin -->", "<!-- protocad-compare results: end -->"


def combined(docs: Sequence[Mapping[str, Any]], sources: Sequence[str] | None = None) -> dict[str, Any]:
    """The runs and random baselines of several results.json documents in one (for the plot and
    the rerun recording): the anchor's grid and the comparison's, say. A variant trained in
    several setups (the anchor at the small preset and at DreamerV2's sizes, or rendered
    'fast' and with dm_control's default look) is one curve per setup, labelled with what
    differs: `LABEL (PRESET preset)`, `LABEL (QUALITY render)` or both; `base_label` keeps the
    variant's own. A run (task, label, setup, seed) in two of them is refused: its curve would
    count twice."""
    names = list(sources) if sources else [f"document {i + 1}" for i in range(len(docs))]
    setups: dict[tuple[str, str], set[tuple[str, str]]] = {}
    for doc in docs:
        for r in doc["runs"]:
            setups.setdefault((r["task"], r["label"]), set()).add(_setup(r))
    seen: dict[tuple[str, str, int], str] = {}
    runs, random = [], {}
    for doc, name in zip(docs, names):
        for r in doc["runs"]:
            both = setups[(r["task"], r["label"])]
            differs = [f"{value} {what}" for i, (what, value) in enumerate(zip(("preset", "render"), _setup(r)))
                       if len({setup[i] for setup in both}) > 1]
            if differs:
                r = {**r, "label": f"{r['label']} ({', '.join(differs)})", "base_label": r["label"]}
            key = (r["task"], r["label"], r["seed"])
            if key in seen:
                raise ValueError(f"{key[0]}/{key[1]}/seed{key[2]} is in both {seen[key]} and {name}; "
                                 "report a run from one results.json (continue a grid with --from-results)")
            seen[key] = name
            runs.append(r)
        for task, entry in doc["random"].items():
            random.setdefault(task, entry)
    return {"runs": runs, "random": random, "created": max(d["created"] for d in docs)}


def _setup(run: Mapping[str, Any]) -> tuple[str, str]:
    """(preset, render quality) of a results.json row; rows written before the render quality was
    recorded rendered 'fast', the only look runs had then."""
    return (str(run["preset"]), str(run.get("render_quality") or "fast"))


def _section_body(doc: Mapping[str, Any]) -> list[str]:
    s = summarize(doc)
    b = doc["budgets"]
    wall = f", wall budget {b['wall_budget_s'] / 60:.0f} min per run" if b["wall_budget_s"] else ""
    statuses = sorted({r["status"] for r in doc["runs"]})
    lines = ["```bash", " ".join(doc["command"]), "```", "",
             f"Machine: {_machine_line(doc['machine'])}. Code: {doc['code_version']}. "
             f"Budget {b['env_steps']:,} env steps per run{wall}; {b['jobs']} runs at once, "
             f"{b['threads_per_run']} torch thread(s) each; the grid took {doc['wall_time_s'] / 60:.0f} min "
             f"of wall time{carried_sentence(doc)}. Run endings: {', '.join(statuses)}.", ""]
    head, rows = table_rows(doc, s)
    if rows:
        lines += [_md_table(head, rows), ""]
    paired = paired_lines(doc)
    if paired:
        lines += ["Paired (the primary metric of [results.md](msgs_docs/results.md)):", "",
                  *(f"- {p}" for p in paired), ""]
    superseded = superseded_lines(doc)
    if superseded:
        lines += ["Superseded (kept as measured, counted nowhere):", "", *(f"- {x}" for x in superseded), ""]
    progress = progress_rows(doc)
    if progress[1]:
        lines += [f"Not finished yet ({len(progress[1])} of {len(doc['runs'])} runs; as of {doc['created']}):", "",
                  _md_table(*progress), ""]
    if s["aggregates"] and max(a["tasks"] for a in s["aggregates"]) > 1:
        lines += ["Over tasks (test contexts; 95% stratified bootstrap intervals):", "",
                  _md_table(*aggregate_rows(s)), ""]
    anchor = anchor_rows(doc)
    if anchor[1]:
        lines += ["Sanity anchor: `dreamer_standard` (Dreamer trained and evaluated on the "
                  "unrandomized task) against DreamerV2's five published seeds on standard DMC "
                  "(danijar/dreamerv2 `scores/dmc-vision-dreamerv2.json` @07d906e; black squares "
                  "and their range in the plot):", "", _md_table(*anchor), ""]
    return lines


def markdown_section(docs: Sequence[Mapping[str, Any]], image: str | None = None,
                     sources: Sequence[str] | None = None, target: str = "README.md") -> str:
    """The generated results section of `target` (a markdown file, paths relative to the
    repository root) from one or more results.json documents (`sources`: their paths, in the
    same order): per document its command, machine, budget and tables, then the plot of all
    their curves, linked relative to `target`. Everything in it comes from `docs` (and the given
    paths), so it regenerates byte-identically."""
    names = list(sources) if sources else ["results.json"] * len(docs)
    lines = [BEGIN,
             f"*Generated from {' and '.join(f'`{n}`' for n in names)} by `protocad-compare --report "
             f"{' '.join(names)}{f' --image {image}' if image else ''} --update-readme {target}`; "
             "do not edit by hand.*", ""]
    for doc, name in zip(docs, names):
        if len(docs) > 1:
            lines += [f"**`{name}`**", ""]
        lines += _section_body(doc)
    if image:
        link = image if os.path.isabs(image) else os.path.relpath(image, Path(target).parent)
        lines += [f"![test-context return vs env steps]({link})", ""]
    lines.append(END)
    return "\n".join(lines)


def update_readme(readme: Path, section: str) -> None:
    """Replace the text between BEGIN and END (inclusive) in `readme` (ValueError without them)."""
    from protocad_ros.atomic import atomic_write_text

    text = Path(readme).read_text()
    i, j = text.find(BEGIN), text.find(END)
    if i < 0 or j < i:
        raise ValueError(f"{readme} has no generated results section ({BEGIN} ... {END}); add the two "
                         "markers where it belongs")
    atomic_write_text(Path(readme), text[:i] + section + text[j + len(END):])


def readme_section(readme: Path) -> str | None:
    text = Path(readme).read_text()
    i, j = text.find(BEGIN), text.find(END)
    return None if i < 0 or j < i else text[i:j + len(END)]
