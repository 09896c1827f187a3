"""results.json of `protocad-compare`: the one name to import for its schema, gathering,
statistics and what is made from it (the text report, the learning-curve PNG, the rerun
recording, the generated markdown section). The code: results_json.py (the file itself: schema,
gathering, reading and writing), statistics.py and report.py.

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

from trainer.research.report import (
    BEGIN,
    DREAMERV2_SCORES,
    END,
    MIN_SEEDS_FOR_CI,
    aggregate_rows,
    anchor_rows,
    carried_sentence,
    combined,
    curves,
    dreamerv2_reference,
    format_report,
    labels_of,
    log_curves_rerun,
    markdown_section,
    paired_lines,
    plot_curves,
    power_lines,
    power_markdown,
    print_power_table,
    progress_rows,
    readme_section,
    superseded_lines,
    table_rows,
    update_readme,
    write_reports,
)
from trainer.research.results_json import (
    ANCHOR_LABEL,
    PAPER_ENV_STEPS,
    PAPER_TABLE1,
    RESULTS_SCHEMA,
    SCHEMA_ID,
    gather,
    gather_run,
    latest_progress,
    load_results,
    machine_info,
    random_baselines,
    runs_code_version,
    save_results,
    validate,
)
from trainer.research.statistics import (
    AGGREGATES,
    aggregate_iqm,
    aggregate_mean,
    aggregate_median,
    bootstrap_ci,
    detectable_effect,
    dreamerv2_curve,
    final_scores,
    iqm,
    paired_difference,
    pairs_needed,
    power_of,
    power_table,
    standard_context,
    summarize,
    unseen_train_ratio,
)

__all__ = [
    'AGGREGATES', 'ANCHOR_LABEL', 'BEGIN', 'DREAMERV2_SCORES', 'END', 'MIN_SEEDS_FOR_CI',
    'PAPER_ENV_STEPS', 'PAPER_TABLE1', 'RESULTS_SCHEMA', 'SCHEMA_ID', 'aggregate_iqm', 'aggregate_mean',
    'aggregate_median', 'aggregate_rows', 'anchor_rows', 'bootstrap_ci', 'carried_sentence', 'combined',
    'curves', 'detectable_effect', 'dreamerv2_curve', 'dreamerv2_reference', 'final_scores', 'format_report',
    'gather', 'gather_run', 'iqm',
    'labels_of', 'latest_progress', 'load_results', 'log_curves_rerun', 'machine_info',
    'markdown_section', 'paired_difference', 'paired_lines', 'pairs_needed', 'plot_curves', 'power_lines',
    'power_markdown', 'print_power_table', 'power_of', 'power_table', 'progress_rows',
    'random_baselines', 'readme_section', 'runs_code_version', 'save_results', 'standard_context',
    'summarize', 'superseded_lines', 'table_rows', 'unseen_train_ratio', 'update_readme', 'validate',
    'write_reports']
