"""results.json of `protocad-compare` itself: its schema, the paper's figures it is read
against, gathering a grid's run directories (finished or still going) and the random policy's
baselines into it, and reading and writing it checked against the schema. What is made from it
(the text report, the learning-curve PNG, the rerun recording, the generated markdown section) is
report.py's; its statistics (rliable's) statistics.py's.

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
from typing import Any, Iterable, Mapping, Sequence

import yaml

from protocad_ros.atomic import atomic_write_text
from protocad_ros.model.precision import cpu_capability
from trainer import run_input, runs
from trainer.learn.evaluate import DEFAULT_EPISODES, EvalPlan, context_label, evaluate_checkpoint, select_contexts
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
#: DreamerV2's published per-seed curves on standard DMC (danijar/dreamerv2
#: scores/dmc-vision-dreamerv2.json @07d906e, the paper's eight tasks up to 300k env steps).
DREAMERV2_SCORES = Path(__file__).with_name("dreamerv2_dmc_vision.json")
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
                "code_versions": {"type": "array", "maxItems": 64, "items": {"type": "string", "maxLength": 64}},
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
    return {"mean_return": round(float(d["mean_return"]), 3),
            "episodes": int(d.get("episodes", 0)),
            "per_context": {context_label(pc["context"]): round(float(pc["mean_return"]), 3)
                            for pc in d.get("per_context", [])}}


def gather_run(task: str, label: str, variant: str, seed: int, run_dir: Path) -> dict[str, Any]:
    """One run directory of protocad-online as a results.json row.

    The run's files are read as input: run.json bounded (trainer.run_input.load_json_object); an
    evaluation line or final.json that is torn or out of shape counts as not written; a run.json
    whose result or protocol is out of shape (a status outside the schema, a count that is no
    number) gathers the run as failed, with one line on stderr naming the file."""
    run_dir = Path(run_dir)
    try:   # written by a run, read as input: bounded in size and depth, an object or nothing
        info = run_input.load_json_object(run_dir / "run.json")
    except ValueError:
        info = {}
    try:
        fields = _run_json_fields(info)
    except (TypeError, ValueError, AttributeError, OverflowError) as exc:
        print(f"[results] {run_dir / 'run.json'}: {exc}; the run gathers as failed", file=sys.stderr)
        fields = _run_json_fields({"result": {"status": "failed"}})
    row = {"task": task, "label": label, "variant": variant, "seed": int(seed), "run_dir": str(run_dir),
           **{k: fields.pop(k) for k in ("status", "env_steps", "updates", "wall_time_s", "precision", "preset",
                                         "eval_split")},
           "final": _read_eval(run_dir / "eval" / "final.json"), "curve": _read_curve(run_dir / "eval.jsonl")}
    final_train = _read_eval(run_dir / "eval" / "final_train.json")
    if final_train is not None:
        row["final_train"] = final_train
    row.update(fields)   # prototype_freeze, code_versions, collect_interval where run.json has them
    cfg = _saved_config(run_dir)
    quality = (cfg.get("train") or {}).get("render_quality")
    if quality:
        row["render_quality"] = str(quality)
    if cfg.get("reference"):
        row["reference"] = str(cfg["reference"])
    return row


_STATUSES = RESULTS_SCHEMA["properties"]["runs"]["items"]["properties"]["status"]["enum"]


def _run_json_fields(info: Mapping[str, Any]) -> dict[str, Any]:
    """What run.json says of the run (status, counts, preset, protocol); raises TypeError,
    ValueError, AttributeError or OverflowError where a value is out of shape."""
    res = info.get("result") if isinstance(info.get("result"), dict) else {}
    proto = info.get("protocol") or {}
    status = res.get("status", "missing" if not info else "failed")
    if status not in _STATUSES:
        raise ValueError(f"result.status {str(status)[:40]!r} is none of {', '.join(_STATUSES)}")
    out = {"status": status, "env_steps": _count(res, "env_steps"), "updates": _count(res, "updates"),
           "wall_time_s": float(res.get("wall_time", 0.0)), "precision": str(res.get("precision", "")),
           "preset": str(info.get("preset", "")), "eval_split": proto.get("eval_split") or "test"}
    if out["eval_split"] not in ("test", "train"):
        raise ValueError(f"protocol.eval_split {str(out['eval_split'])[:40]!r} is neither test nor train")
    if "prototype_freeze" in res:
        freeze = res["prototype_freeze"]
        out["prototype_freeze"] = None if freeze is None else _count(res, "prototype_freeze")
    if isinstance(info.get("code_versions"), list):   # a grid can span commits and machines: per row
        # commit ids (+dirty): a crafted run.json's huge or odd entries stay out of results.json
        out["code_versions"] = [v for v in info["code_versions"] if isinstance(v, str) and len(v) <= 64][:64]
    if "updates_per_episode" in proto:
        out["collect_interval"] = _count(proto, "updates_per_episode")
    return out


def _count(d: Mapping[str, Any], key: str) -> int:
    value = d.get(key, 0)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value):
        raise ValueError(f"{key} {str(value)[:40]!r} is not a whole number")
    return int(value)


def _read_curve(path: Path) -> list[dict[str, Any]]:
    """The learning curve from eval.jsonl (the policy's evaluations, newest of a repeated one)."""
    curve, seen = [], set()
    for row in _read_jsonl(path):
        try:
            if not isinstance(row, dict) or str(row.get("policy", "")).startswith("random") or "mean_return" not in row:
                continue
            point = {"env_steps": int(row["env_steps"]), "mean_return": round(float(row["mean_return"]), 3),
                     "tag": str(row.get("tag", ""))}
        except (KeyError, TypeError, ValueError, OverflowError):
            continue   # out of shape: as a torn line is
        key = (point["env_steps"], point["tag"])
        if key in seen:       # an evaluation repeated after a resume: keep the newest
            curve = [c for c in curve if (c["env_steps"], c["tag"]) != key]
        seen.add(key)
        curve.append(point)
    curve.sort(key=lambda c: (c["env_steps"], c["tag"] == "final"))
    return curve


def _read_eval(path: Path) -> dict[str, Any] | None:
    """An evaluation's JSON (eval/final.json, ...) as a results.json entry; None where it is
    missing, torn or out of shape."""
    try:
        return _eval_entry(run_input.load_json_object(path))
    except (ValueError, TypeError, KeyError, AttributeError, OverflowError):
        return None


def _saved_config(run_dir: Path) -> dict[str, Any]:
    """A run's saved config.yaml as a mapping ({} where there is none to read)."""
    try:
        cfg = yaml.safe_load((Path(run_dir) / "config.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return {}
    return cfg if isinstance(cfg, dict) else {}



def runs_code_version(rows: Iterable[Mapping[str, Any]]) -> str:
    """The code the runs were trained with: each row's `code_versions` (run.json's, every
    invocation's), a carried row's file-level code_version where it has none; runs not started
    yet ran no code and do not count. Where a run that did start records none, the tree that
    gathered them, saying so."""
    seen: list[str] = []
    for r in rows:
        versions = r.get("code_versions")
        if not versions and r.get("carried_from"):
            versions = r["carried_from"]["code_version"].split(", ")
        if not versions and r["status"] == "missing":
            continue
        if not versions:
            return f"{code_version()} (the gathering tree: the runs do not record their code)"
        seen += [v for v in versions if v not in seen]
    return ", ".join(seen) if seen else code_version()


def machine_info() -> dict[str, Any]:
    import torch

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
    return {"schema": SCHEMA_ID, "command": [str(c) for c in command], "code_version": runs_code_version(rows),
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "machine": machine_info(),
            "budgets": {"env_steps": int(env_steps), "wall_budget_s": wall_budget, "jobs": int(jobs),
                        "threads_per_run": int(threads)},
            "wall_time_s": round(float(wall_time), 1),
            "runs": rows,
            "random": {k: _eval_entry(v) for k, v in (random or {}).items()}}


def latest_progress(run_dir: Path) -> tuple[int, int]:
    """The newest (env steps, updates) a run has logged (metrics.jsonl): what `gather`'s
    `running` holds for a run still going."""
    path = Path(run_dir) / "metrics.jsonl"
    try:
        with open(path, "rb") as f:
            f.seek(max(0, path.stat().st_size - 4096))
            lines = f.read().decode(errors="replace").splitlines()
    except OSError:
        return 0, 0
    for line in reversed(lines):
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if "env_steps" in row:
            return int(row["env_steps"]), int(row.get("update", 0))
    return 0, 0


def random_baselines(tasks: Sequence[str], out: str | Path, *, episodes: int | None, evaluate: bool = True,
                     protocols: Mapping[str, Mapping[str, Any]] | None = None) -> dict[str, dict]:
    """results.json's `random` entries: the uniform random policy on each task's final-evaluation
    protocol, evaluated once (OUT/TASK/random.json); evaluate=False: only those already there.
    `protocols[task]` is a run's run.json `protocol`: its contexts, episode length and (unless
    `episodes` is given) episodes per context, so the baseline plays the episodes the runs were
    scored on; a task without one gets the paper's protocol (every test context, 1000 env steps)."""
    found = {}
    for task in tasks:
        path = Path(out) / task / "random.json"
        if not path.exists() and not evaluate:
            continue
        if not path.exists():
            p = dict((protocols or {}).get(task) or {})
            split = p.get("eval_split", "test")
            contexts = select_contexts(task, split, p.get("eval_contexts"), p.get("final_max_contexts", 0))
            plan = EvalPlan(split=split, contexts=contexts, seed=7, progress=False,
                            episodes=episodes or p.get("final_episodes") or DEFAULT_EPISODES,
                            time_limit=p.get("time_limit"))
            res = evaluate_checkpoint(None, plan, task=task)
            runs.atomic_write_json(path, res.to_dict())
        found[task] = json.loads(path.read_text())
    return found


def check_schema(doc: Any, schema: Mapping[str, Any], name: str, schema_id: str) -> None:
    """jsonschema validation of a document of this package (ValueError with the first problem
    and where it is; skipped, said on stderr, where jsonschema is not installed: the GPU
    machine's bare Python, checked again where it is)."""
    try:
        import jsonschema
    except ImportError:
        print(f"[results] jsonschema is not installed: {schema_id} not checked here", file=sys.stderr)
        return
    try:
        jsonschema.validate(doc, schema)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise ValueError(f"{name} does not match {schema_id} at {where}: {exc.message}") from None


def validate(doc: Mapping[str, Any]) -> None:
    """results.json against RESULTS_SCHEMA (ValueError with the first problem)."""
    check_schema(doc, RESULTS_SCHEMA, "results.json", SCHEMA_ID)


def save_results(doc: Mapping[str, Any], path: Path) -> Path:
    validate(doc)
    atomic_write_text(Path(path), json.dumps(doc, indent=1) + "\n")
    return Path(path)


def load_results(path: str | Path) -> dict[str, Any]:
    """A results.json, bounded in size and depth and checked against RESULTS_SCHEMA (one
    ValueError line naming the file)."""
    doc = run_input.load_json_object(path)
    try:
        validate(doc)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    return doc


