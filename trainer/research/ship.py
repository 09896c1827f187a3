"""Ship the best policy of a comparison: `protocad-compare --report RESULTS_JSON --ship OUT.pt`.

The best run is the one with the highest final mean return on unseen contexts (the test split)
among the finished runs of results.json (optionally of one task / label). Its checkpoint is
written as a policy file (protocad_ros.checkpoint.save_policy: bfloat16 weights, no optimizer
states, a few MB) whose provenance says where it comes from: the results.json entry (task,
variant, seed, env steps, updates, final scores per context), the commands that trained it, the
code version(s) and the SHA-256 of the training checkpoint it was cut from.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from protocad_ros.atomic import file_sha256
from protocad_ros.checkpoint.agent_file import load_checkpoint, save_policy
from protocad_ros.checkpoint.files import CheckpointError, existing_checkpoint_file
from trainer import runs
from trainer.learn.evaluate import context_label


def best_run(doc: Mapping[str, Any], task: str | None = None, label: str | None = None) -> dict[str, Any]:
    """The finished run with the highest final mean return: among the runs evaluated on the
    test split (unseen contexts), or, where `label` names them, among that label's runs
    whatever their split (the anchor's final is on its training context). ValueError when there
    is none."""
    rows = candidates(doc, task, label)
    return max(rows, key=lambda r: r["final"]["mean_return"])


def candidates(doc: Mapping[str, Any], task: str | None = None, label: str | None = None) -> list[dict[str, Any]]:
    """The runs best_run chooses among (ValueError when there is none)."""
    rows = [r for r in doc["runs"] if r.get("final") and r.get("status") in ("finished", "wall_budget")
            and (task is None or r["task"] == task) and (label is None or r["label"] == label)
            and (label is not None or r.get("eval_split", "test") == "test")]
    if not rows:
        what = " ".join(f"{k} {v}" for k, v in (("task", task), ("label", label)) if v)
        raise ValueError("no finished run with a final evaluation"
                         + (" on unseen (test) contexts" if label is None else "")
                         + (f" for {what}" if what else "") + " in results.json")
    return rows


def unseen_evaluation(path: str | Path, checkpoint: Path) -> dict[str, Any]:
    """The summary of `protocad-evaluate CHECKPOINT --random --json PATH` for `checkpoint` on the
    test split (ValueError if the file evaluates another checkpoint, another version of it, or
    another split)."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"--ship-evaluation {path}: {exc}") from None
    mine = [r for r in doc.get("results", []) if Path(r.get("policy", "")).resolve() == checkpoint.resolve()]
    if not mine:
        raise ValueError(f"--ship-evaluation {path} does not evaluate {checkpoint}")
    r = mine[0]
    named = r.get("sha256")
    if named is not None:
        actual = file_sha256(checkpoint)
        if named != actual:   # a crafted value (not a string, any length) is refused, never sliced raw
            raise ValueError(f"--ship-evaluation {path} evaluated another version of {checkpoint} "
                             f"(sha256 {str(named)[:12]}..., the file's is now {actual[:12]}...)")
    if r.get("split") != "test":
        raise ValueError(f"--ship-evaluation {path} is on the {r.get('split')!r} split, not the unseen (test) one")
    rnd = next((x for x in doc.get("random", []) if x.get("task") == r["task"]), None)
    return {"file": str(path), "split": "test", "episodes": r["episodes"],
            "mean_return": r["mean_return"], "median_over_contexts": r.get("median_over_contexts"),
            "random_mean_return": rnd["mean_return"] if rnd else None,
            "per_context": {context_label(c["context"]): c["mean_return"] for c in r["per_context"]}}


def ship_best(doc: Mapping[str, Any], out: str | Path, results_path: str | Path,
              task: str | None = None, label: str | None = None,
              evaluation: str | Path | None = None) -> tuple[Path, dict[str, Any]]:
    """Write the best run's policy file to `out`; returns (path, its provenance). `evaluation`:
    a protocad-evaluate --json file of that run's checkpoint on unseen contexts, kept in the
    provenance."""
    among = candidates(doc, task, label)
    row = best_run(doc, task, label)
    ckpt = existing_checkpoint_file(row["run_dir"])
    try:
        agent, counters = load_checkpoint(ckpt, restore_rng=False, optimizer_states=False)
    except CheckpointError as err:
        raise ValueError(f"cannot ship {row['run_dir']}: {err}") from None
    info = runs.read_run_json(row["run_dir"])
    where = ("unseen contexts" if row.get("eval_split", "test") == "test"
             else f"its {row.get('eval_split')} context(s)")
    kind = f"{label} run" if label else "run"
    provenance = {
        "what": f"{row['task']} {row['label']} seed {row['seed']}: "
                + (f"the only finished {kind} of {Path(results_path).name} (final evaluated on {where})"
                   if len(among) == 1 else
                   f"the best final return on {where} among the {len(among)} finished {kind}s of "
                   f"{Path(results_path).name}"),
        "results_json": str(results_path),
        "results_entry": {k: row[k] for k in ("task", "label", "variant", "seed", "env_steps", "updates",
                                               "prototype_freeze", "preset", "precision", "render_quality",
                                               "reference", "collect_interval", "final") if k in row},
        "grid_command": list(doc.get("command", [])),
        "run_command": list(info.get("argv", [])),
        "resume_commands": list(info.get("resumes_argv", [])),
        "code_versions": list(info.get("code_versions", [])) or [doc.get("code_version", "unknown")],
        "source_checkpoint": str(ckpt),
        "source_checkpoint_sha256": file_sha256(ckpt),
        "counters": {k: v for k, v in counters.items() if isinstance(v, (int, float))},   # not the sampler state
    }
    if info.get("init_policy"):   # the policy file the run started from (--init-policy)
        provenance["init_policy"] = info["init_policy"]
    if evaluation is not None:
        provenance["unseen_evaluation"] = unseen_evaluation(evaluation, ckpt)
    return save_policy(out, agent, provenance), provenance


def shipped_line(path: Path, prov: Mapping[str, Any]) -> str:
    """What ship_best wrote, in one line: the run, its scores, the file and its size."""
    unseen = prov.get("unseen_evaluation")
    return (f"shipped {prov['what']} (final {prov['results_entry']['final']['mean_return']:.1f}"
            + (f"; unseen contexts {unseen['mean_return']:.1f}, random {unseen['random_mean_return']:.1f}"
               if unseen and unseen["random_mean_return"] is not None else "")
            + f") as {path} ({path.stat().st_size / 1e6:.1f} MB; provenance: {path.with_suffix('.json')})")
