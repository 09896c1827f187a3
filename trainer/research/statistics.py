"""The statistics of results.json (rliable's, Agarwal et al. 2021, written out: rliable itself
pulls arch, statsmodels, pandas and seaborn for these few functions): a run's score is its final
mean return on the test contexts; per task and variant the mean over seeds with a percentile
bootstrap interval; over tasks the mean, median and IQM with stratified bootstrap intervals; and
a paired comparison's per-seed differences with a Student-t interval; and, before a paired
comparison runs, its size: the power of the paired t-test, the pairs it needs and the table that
sizes the next comparison from the paper's gaps and DreamerV2's published seeds (`power_table`)."""
from __future__ import annotations

import json
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy import optimize, stats

from sim_bridge.contract.contexts import get_task
from trainer.research.results_json import DREAMERV2_SCORES, PAPER_ENV_STEPS, PAPER_TABLE1


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
    return stats.trim_mean(scores, 0.25, axis=-1)


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



# ---------------------------------------------------------------------- sizing a paired comparison
# A paired comparison (as paired_difference reads it) is a two-sided paired t-test at level alpha
# on n seed pairs whose differences ProtoCAD - Dreamer have standard deviation pair_sd. Its power
# for a true mean difference `effect` comes from the noncentral t distribution (n - 1 degrees of
# freedom, noncentrality effect / (pair_sd / sqrt(n))), not the normal approximation, which
# promises too much at the few pairs these grids afford.

def power_of(effect: float, pair_sd: float, n_pairs: int, alpha: float = 0.05) -> float:
    """The probability that the two-sided paired t-test at level alpha over n_pairs pairs
    rejects "no difference" when the true mean difference is `effect` (either sign) and the pairs'
    differences have standard deviation pair_sd; alpha itself when effect is 0."""
    _check_test(pair_sd, n_pairs, alpha)
    df = n_pairs - 1
    crit = stats.t.ppf(1 - alpha / 2, df)
    nc = abs(effect) / pair_sd * np.sqrt(n_pairs)
    # P(T < -crit) as P(T > crit) at -nc: scipy's nct.cdf returns NaN for some tiny lower tails
    return float(stats.nct.sf(crit, df, nc) + stats.nct.sf(crit, df, -nc))


def detectable_effect(pair_sd: float, n_pairs: int, alpha: float = 0.05, power: float = 0.8) -> float:
    """The smallest true mean paired difference (in return) that the paired t-test over n_pairs
    pairs detects with probability `power`: power_of(result, pair_sd, n_pairs, alpha) == power."""
    _check_test(pair_sd, n_pairs, alpha)
    if not alpha < power < 1:
        raise ValueError(f"power must lie between alpha ({alpha}) and 1, got {power}")
    hi = pair_sd
    while power_of(hi, pair_sd, n_pairs, alpha) < power:
        hi *= 2
    return float(optimize.brentq(lambda e: power_of(e, pair_sd, n_pairs, alpha) - power, 0.0, hi,
                        xtol=1e-9 * pair_sd, rtol=1e-12))


def pairs_needed(effect: float, pair_sd: float, alpha: float = 0.05, power: float = 0.8,
                 max_pairs: int = 100_000) -> int:
    """The fewest pairs (at least 2) with which the paired t-test detects a true mean difference
    `effect` with probability at least `power`; ValueError when even max_pairs do not (an effect
    of 0 never does)."""
    _check_test(pair_sd, 2, alpha)
    if not alpha < power < 1:
        raise ValueError(f"power must lie between alpha ({alpha}) and 1, got {power}")
    if power_of(effect, pair_sd, max_pairs, alpha) < power:
        raise ValueError(f"effect {effect:g} with pair SD {pair_sd:g}: more than {max_pairs} pairs "
                         f"needed for power {power:g}")
    lo, hi = 1, 2   # power grows with the pairs: lo fails (or is below 2), hi succeeds
    while power_of(effect, pair_sd, hi, alpha) < power:
        lo, hi = hi, min(2 * hi, max_pairs)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if power_of(effect, pair_sd, mid, alpha) >= power else (mid, hi)
    return hi


def _check_test(pair_sd: float, n_pairs: int, alpha: float) -> None:
    if not (np.isfinite(pair_sd) and pair_sd > 0):
        raise ValueError(f"pair_sd must be a positive number, got {pair_sd}")
    if int(n_pairs) != n_pairs or n_pairs < 2:
        raise ValueError(f"a paired t-test needs at least 2 pairs, got {n_pairs}")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must lie between 0 and 1, got {alpha}")


def dreamerv2_curve(task: str, env_steps: int) -> tuple[float, float]:
    """DreamerV2's published seeds on the standard task at `env_steps` (a point of the vendored
    curves, trainer/research/dreamerv2_dmc_vision.json): the mean over its seeds and their
    standard deviation (ddof 1). ValueError for a task or an env-step count the file does not
    hold (the curves are not interpolated)."""
    rs = [c for c in json.loads(DREAMERV2_SCORES.read_text())["curves"] if c["task"] == task]
    if not rs:
        raise ValueError(f"DreamerV2's published curves have no task {task!r} "
                         f"(they have {', '.join(sorted(PAPER_TABLE1))})")
    steps = sorted(set.intersection(*(set(c["env_steps"]) for c in rs)))
    if env_steps not in steps:
        raise ValueError(f"DreamerV2's published {task} curves have no point at {env_steps:,} env steps "
                         f"(they have {', '.join(f'{s:,}' for s in steps)})")
    v = np.array([c["return"][c["env_steps"].index(env_steps)] for c in rs], float)
    return float(v.mean()), float(v.std(ddof=1))


#: The paired walker_walk grid of issue 42 (msgs_docs/results/walker_paired_small.json): ProtoCAD -
#: Dreamer on the 64 unseen contexts at 30k env steps, seeds 0-4, small preset.
WALKER_GRID_DIFFS = (21.1, -59.6, 42.1, -70.8, -23.4)
WALKER_GRID_ENV_STEPS = 30_000
#: Measured: a 30k-env-step small-preset run (2,900 updates, bf16) takes about 1.6 h of one core.
CORE_HOURS_PER_30K = 1.6
POWER_BUDGETS = (30_000, 60_000, 120_000)


def _pairs_or_none(effect: float, pair_sd: float, alpha: float, power: float, max_pairs: int) -> int | None:
    try:
        return pairs_needed(effect, pair_sd, alpha, power, max_pairs)
    except ValueError:
        return None


def paper_gap(task: str) -> float:
    """The paper's relative gap on unseen dynamics at 2M env steps (Table 1): ProtoCAD / Dreamer - 1."""
    return PAPER_TABLE1[task]["protocad"][0] / PAPER_TABLE1[task]["dreamer"][0] - 1


def power_table(budgets: Sequence[int] = POWER_BUDGETS, alpha: float = 0.05, power: float = 0.8,
                core_hours_per_30k: float = CORE_HOURS_PER_30K, max_pairs: int = 100_000) -> dict[str, Any]:
    """What the next paired ProtoCAD-vs-Dreamer grid costs to power, for each of the paper's eight
    tasks at each env-step budget (a point of DreamerV2's published curves), as JSON-able data:

    * `expected_effect` = the paper's relative gap at 2M env steps (paper_gap) x DreamerV2's mean
      at that budget. The assumption: the paper's relative gap carried to the curve's level at a
      smaller budget (nothing measured says the gap is that size so early; it may be smaller);
    * `pair_sd`: walker_walk at 30k, the measured SD of the walker grid's paired differences
      (`pair_sd_source` "measured"); elsewhere sqrt(2) x the SD of DreamerV2's seeds at that
      budget, the SD of a difference of two independent runs ("dreamerv2_seeds"; paired env
      draws make the true one smaller where the arms' returns correlate: on walker_walk at 30k
      the measured SD is half this estimate);
    * `pairs_needed` for `power` at `alpha` (null above max_pairs), and the CPU cost here:
      2 runs per pair x core_hours_per_30k per 30k env steps, linear in env steps;
      `pairs_if_sd_1_5x`: the pairs if the pair SD is 1.5 times the one assumed (an SD from five
      seeds is that uncertain and more).

    `walker_grid`: the effect the walker grid could detect with `power` (and what the normal
    approximation would claim), its power for the paper's walker_walk gap carried to 30k, and the
    independent-pair SD the other rows assume, for that row. `cheapest`: the row with the fewest
    core-hours. Values rounded as msgs_docs/results/power_table.json holds them."""
    diffs = np.array(WALKER_GRID_DIFFS)
    measured_sd = float(diffs.std(ddof=1))
    rows = []
    for task in sorted(PAPER_TABLE1):
        gap = paper_gap(task)
        for steps in budgets:
            mean, sd = dreamerv2_curve(task, steps)
            effect = gap * mean
            measured = task == "walker_walk" and steps == WALKER_GRID_ENV_STEPS
            pair_sd = measured_sd if measured else float(np.sqrt(2) * sd)
            n, n_wide = (_pairs_or_none(effect, f * pair_sd, alpha, power, max_pairs) for f in (1.0, 1.5))
            hours_per_run = core_hours_per_30k * steps / 30_000
            rows.append({"task": task, "env_steps": steps, "dreamerv2_mean": round(mean, 1),
                         "dreamerv2_sd": round(sd, 1), "paper_gap": round(gap, 4),
                         "expected_effect": round(effect, 1), "pair_sd": round(pair_sd, 1),
                         "pair_sd_source": "measured" if measured else "dreamerv2_seeds",
                         "pairs_needed": n, "core_hours": None if n is None else round(2 * n * hours_per_run, 1),
                         "pairs_if_sd_1_5x": n_wide})
    walker_mean, walker_sd = dreamerv2_curve("walker_walk", WALKER_GRID_ENV_STEPS)
    walker_effect = paper_gap("walker_walk") * walker_mean
    z = stats.norm.ppf(1 - alpha / 2) + stats.norm.ppf(power)
    cheapest = min((r for r in rows if r["core_hours"] is not None), key=lambda r: r["core_hours"])
    return {
        "what": "pairs a paired ProtoCAD - Dreamer grid needs to detect the paper's gap, per task and budget",
        "test": "two-sided paired t-test, power from the noncentral t distribution",
        "alpha": alpha, "power": power, "max_pairs": max_pairs, "paper_env_steps": PAPER_ENV_STEPS,
        "core_hours_per_run_per_30k_env_steps": core_hours_per_30k, "runs_per_pair": 2,
        "dreamerv2": "danijar/dreamerv2 scores/dmc-vision-dreamerv2.json @07d906e (5 seeds, standard DMC)",
        "rows": rows,
        "walker_grid": {"env_steps": WALKER_GRID_ENV_STEPS, "pairs": len(diffs),
                        "diffs": list(WALKER_GRID_DIFFS), "pair_sd": round(measured_sd, 1),
                        "detectable_effect": round(detectable_effect(measured_sd, len(diffs), alpha, power), 1),
                        "detectable_effect_normal_approximation": round(z * measured_sd / np.sqrt(len(diffs)), 1),
                        "independent_pair_sd": round(float(np.sqrt(2) * walker_sd), 1),
                        "paper_effect": round(walker_effect, 1),
                        "power_for_paper_effect": round(power_of(walker_effect, measured_sd, len(diffs), alpha), 3)},
        "cheapest": {k: cheapest[k] for k in ("task", "env_steps", "pairs_needed", "core_hours")},
    }
