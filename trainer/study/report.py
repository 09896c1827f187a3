"""The study's report: per arm, the mean over seeds with a 95% Student-t interval of each figure
of its runs' eval.json files, as JSON (schema protocad-study/1) and a markdown table."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from scipy import stats

from protocad_ros.atomic import atomic_write_text
from trainer.run_input import load_json_object
from trainer.study.dataset import TASK
from trainer.study.grid import ARMS


def t_interval(values: Sequence[float]) -> tuple[float, float, float]:
    """Mean and 95% Student-t interval over seeds."""
    v = np.asarray(values, float)
    m = float(v.mean())
    if len(v) < 2:
        return m, float("nan"), float("nan")
    half = float(stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / np.sqrt(len(v)))
    return m, m - half, m + half


def figures(doc: Mapping[str, Any]) -> dict[str, float]:
    """The figures of one run that the report compares."""
    out: dict[str, float] = {}
    for split in ("test", "train"):
        ol = doc["open_loop"][split]
        img = np.asarray(ol["image_mse"], float)
        rew = np.asarray(ol["reward_abs_err"], float)
        out[f"{split}_image_mse_1_50"] = float(img.mean())
        out[f"{split}_image_mse_h10"] = float(img[9])
        out[f"{split}_image_mse_h50"] = float(img[-1])
        out[f"{split}_reward_err_1_50"] = float(rew.mean())
    for setting in ("test_grid", "test_light", "test_heavy", "train_to_test"):
        for target in ("log_m", "log_d"):
            for feat, v in doc["probes"].get(setting, {}).get(target, {}).items():
                out[f"r2_{setting}_{target}_{feat}"] = float(v["r2"])
    for k, v in (doc.get("health") or {}).items():
        out[f"health_{k}"] = float(v)
    return out


def gather(grid: Path) -> dict[str, Any]:
    arms: dict[str, Any] = {}
    for f in sorted(grid.glob("*/seed_*/eval.json")):
        doc = load_json_object(f)   # bounded: a run directory may hold anything
        try:
            doc["figures"] = figures(doc)
            arms.setdefault(str(doc["arm"]), []).append(doc)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise ValueError(f"{f}: not a protocad-study eval.json ({type(exc).__name__}: {exc})") from None
    result = {}
    for arm, docs in arms.items():
        per = [d.pop("figures") for d in docs]
        keys = sorted(set.intersection(*(set(p) for p in per)))
        result[arm] = {"seeds": sorted(d["seed"] for d in docs), "updates": sorted({d["updates"] for d in docs}),
                       "settings": docs[0]["settings"],
                       "figures": {k: dict(zip(("mean", "lo", "hi"), t_interval([p[k] for p in per]))) for k in keys},
                       "per_seed": {str(d["seed"]): f for d, f in zip(docs, per)}}
    return result


#: The study's primary figure (results.md, fixed before its results): unseen-context image MSE
#: over open-loop horizons 1-50; an arm is ahead of Dreamer where its paired interval lies below 0.
PRIMARY = "test_image_mse_1_50"


def paired(result: Mapping[str, Any], arm: str, base: str = "dreamer", key: str = PRIMARY) -> dict[str, Any] | None:
    """arm - base of one figure, paired by seed (the seeds both ran: the same data order), with
    its mean and 95% t-interval; None where either arm has no run."""
    a, b = result.get(arm), result.get(base)
    seeds = sorted(set(a["per_seed"]) & set(b["per_seed"]), key=int) if a and b else []
    if not seeds:
        return None
    d = [a["per_seed"][s][key] - b["per_seed"][s][key] for s in seeds]
    m, lo, hi = t_interval(d)
    verdict = "lower" if hi < 0 else "higher" if lo > 0 else "no difference shown"
    return {"arm": arm, "base": base, "figure": key, "seeds": [int(s) for s in seeds], "differences": d,
            "mean": m, "lo": lo, "hi": hi, "verdict": verdict}


def paired_line(p: Mapping[str, Any]) -> str:
    return (f"{p['arm']} - {p['base']}, {p['figure']} over {len(p['seeds'])} seeds: {p['mean']:+.5f} "
            f"[95% t-interval {p['lo']:+.5f}, {p['hi']:+.5f}]: {p['verdict']}")


ROWS = [("unseen image MSE, h 1-50", "test_image_mse_1_50", 5), ("unseen image MSE, h 10", "test_image_mse_h10", 5),
        ("unseen image MSE, h 50", "test_image_mse_h50", 5), ("training-context image MSE, h 1-50", "train_image_mse_1_50", 5),
        ("unseen reward error, h 1-50", "test_reward_err_1_50", 3), ("training reward error, h 1-50", "train_reward_err_1_50", 3),
        ("log m R2 in the unseen grid, h", "r2_test_grid_log_m_h", 2), ("log m R2 in the unseen grid, u", "r2_test_grid_log_m_u", 2),
        ("log m R2 light cluster, h", "r2_test_light_log_m_h", 2), ("log m R2 light cluster, u", "r2_test_light_log_m_u", 2),
        ("log m R2 heavy cluster, h", "r2_test_heavy_log_m_h", 2), ("log m R2 heavy cluster, u", "r2_test_heavy_log_m_u", 2),
        ("log m R2 train->unseen, h", "r2_train_to_test_log_m_h", 2), ("log m R2 train->unseen, u", "r2_train_to_test_log_m_u", 2),
        ("log d R2 in the unseen grid, h", "r2_test_grid_log_d_h", 2), ("log d R2 in the unseen grid, u", "r2_test_grid_log_d_u", 2),
        ("projection cosine", "health_proj_cosine", 2), ("prediction top prob.", "health_swav_pred_top", 3),
        ("target top prob.", "health_swav_target_top", 3), ("prediction entropy", "health_swav_pred_entropy", 2),
        ("target entropy", "health_swav_target_entropy", 2), ("modal share in a sequence", "health_modal_share", 2),
        ("between-sequence share of u", "health_proj_between_share", 2),
        ("prototypes' cosine to start", "health_proto_init_cosine", 3)]


def markdown(result: Mapping[str, Any]) -> str:
    """The figures of each arm (mean [95% t-interval] over its seeds), one column an arm in the
    order of the study's arm table."""
    arms = sorted(result, key=lambda a: list(ARMS).index(a) if a in ARMS else len(ARMS))
    head = "| figure | " + " | ".join(f"{a} ({len(result[a]['seeds'])} seeds)" for a in arms) + " |"
    lines = [head, "|---|" + "---|" * len(arms)]
    for label, key, digits in ROWS:
        cells = []
        for a in arms:
            f = result[a]["figures"].get(key)
            cells.append("" if f is None else f"{f['mean']:.{digits}f} [{f['lo']:.{digits}f}, {f['hi']:.{digits}f}]")
        if any(cells):
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(grid: Path, json_path: Path | None = None) -> dict[str, Any]:
    """Gather GRID, print the markdown table, write the JSON where asked; ValueError if no run
    has finished."""
    result = gather(Path(grid))
    if not result:
        raise ValueError(f"{grid}: no finished run (GRID/ARM/seed_S/eval.json)")
    pairs = [p for arm in result if arm != "dreamer" and (p := paired(result, arm)) is not None]
    print(markdown(result), *("", *map(paired_line, pairs)), sep="\n")
    doc = {"schema": "protocad-study/1", "task": TASK, "arms": result, "paired": pairs}
    if json_path:
        atomic_write_text(Path(json_path), json.dumps(doc, indent=1))
    return doc
