"""The statistics of results.json (rliable's, Agarwal et al. 2021, written out: rliable itself
pulls arch, statsmodels, pandas and seaborn for these few functions): a run's score is its final
mean return on the test contexts; per task and variant the mean over seeds with a percentile
bootstrap interval; over tasks the mean, median and IQM with stratified bootstrap intervals; and
a paired comparison's per-seed differences with a Student-t interval."""
from __future__ import annotations

from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sim_bridge.contract.contexts import get_task
from trainer.research.results_json import PAPER_TABLE1


def standard_context(task: str) -> str:
    """The unrandomized task's context (every scale 1), e.g. 'm=1,d=1': the anchor's train and
    evaluation context, as a --train-context value."""
    return ",".join(f"{p}=1" for p in get_task(task).params)


def iqm(scores: np.ndarray) -> float:
    """Interquartile mean: the mean of the middle 50% (25% trimmed from each end)."""
    return float(_iqm_last_axis(np.asarray(scores, float)))


# The aggregates take each task's scores along the last axis, so bootstrap_ci computes all its
# replicates in one call (leading axis: replicate); on plain score vectors they give a float.
def _iqm_last_axis(scores: np.ndarray) -> np.ndarray:
    from scipy.stats import trim_mean

    return trim_mean(scores, 0.25, axis=-1)


def _float_or_array(x: np.ndarray) -> float | np.ndarray:
    return float(x) if np.ndim(x) == 0 else x


def aggregate_mean(per_task: Sequence[np.ndarray]) -> float | np.ndarray:
    """Mean over every task x seed score."""
    return _float_or_array(np.mean(np.concatenate(per_task, axis=-1), axis=-1))


def aggregate_median(per_task: Sequence[np.ndarray]) -> float | np.ndarray:
    """Median over tasks of the per-task mean (as the paper and rliable report it)."""
    return _float_or_array(np.median(np.stack([np.mean(s, axis=-1) for s in per_task], axis=-1), axis=-1))


def aggregate_iqm(per_task: Sequence[np.ndarray]) -> float | np.ndarray:
    return _float_or_array(_iqm_last_axis(np.concatenate(per_task, axis=-1)))


AGGREGATES: dict[str, Callable[[Sequence[np.ndarray]], float | np.ndarray]] = {
    "mean": aggregate_mean, "median": aggregate_median, "iqm": aggregate_iqm}


def bootstrap_ci(per_task: Sequence[Sequence[float]],
                 statistic: Callable[[Sequence[np.ndarray]], float | np.ndarray],
                 reps: int = 10_000, confidence: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Stratified percentile bootstrap interval of `statistic(per_task)`: every replicate
    resamples, independently per task, that task's scores with replacement. A single task is
    the ordinary bootstrap of its seeds. Deterministic for a seed. `statistic` reduces the
    last axis (the aggregates above): it gets every replicate at once, (reps, scores) per task."""
    arrays = [np.asarray(s, float) for s in per_task]
    if not arrays or any(a.size == 0 for a in arrays):
        raise ValueError("bootstrap_ci needs at least one score per task")
    rng = np.random.default_rng(seed)
    idx = [rng.integers(0, a.size, size=(reps, a.size)) for a in arrays]
    stats = np.asarray(statistic([a[i] for a, i in zip(arrays, idx)]))
    lo, hi = np.quantile(stats, [(1 - confidence) / 2, 1 - (1 - confidence) / 2])
    return float(lo), float(hi)


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
        agg = {"label": label, "tasks": len(per_task), "min_seeds": min(len(x) for x in per_task)}
        for name, fn in AGGREGATES.items():
            agg[name] = (fn(per_task), bootstrap_ci(per_task, fn, reps=reps))
        aggregates.append(agg)
    return {"rows": rows, "aggregates": aggregates}


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

