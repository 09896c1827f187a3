"""What is made from results.json: the text report, the tables, the learning-curve PNG and rerun
recording, and the generated markdown section of a page (msgs_docs/results.md)."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from protocad_ros.atomic import atomic_write_text
from trainer.research.results_json import ANCHOR_LABEL, DREAMERV2_SCORES, PAPER_ENV_STEPS
from trainer.research.statistics import (
    aggregate_mean,
    bootstrap_ci,
    paired_difference,
    power_table,
    standard_context,
    summarize,
    unseen_train_ratio,
)


def _ci(v: float, ci: tuple[float, float]) -> str:
    return f"{v:.1f} [{ci[0]:.1f}, {ci[1]:.1f}]"


#: Below this many seeds a percentile bootstrap of the mean is little more than [min, max]
#: (with 3 seeds exactly that): tables show the range and call it one.
MIN_SEEDS_FOR_CI = 5


def _mean_and_spread(r: Mapping[str, Any]) -> str:
    if r["n"] < MIN_SEEDS_FOR_CI:
        return f"{r['mean']:.1f} (range {r['range'][0]:.1f}-{r['range'][1]:.1f})"
    return _ci(r["mean"], r["ci"])


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
    """Mean, median and IQM over tasks per variant. A task with fewer than MIN_SEEDS_FOR_CI
    seeds makes the stratified bootstrap little more than the spread of those few seeds, so
    such a variant shows its point values without an interval."""
    head = ["variant", "tasks", "fewest seeds per task", "mean [95% CI]", "median [95% CI]", "IQM [95% CI]"]
    rows = []
    for a in summary["aggregates"]:
        few = a["min_seeds"] < MIN_SEEDS_FOR_CI
        cells = [f"{a[k][0]:.1f} (no interval below {MIN_SEEDS_FOR_CI} seeds)" if few else _ci(*a[k])
                 for k in ("mean", "median", "iqm")]
        rows.append([a["label"], str(a["tasks"]), str(a["min_seeds"]), *cells])
    return head, rows


def _over_tasks(summary: Mapping[str, Any]) -> bool:
    """Whether an over-tasks table says anything a per-task row does not (more than one task)."""
    return bool(summary["aggregates"]) and max(a["tasks"] for a in summary["aggregates"]) > 1


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
           _text_table(*table_rows(doc, s))]
    if _over_tasks(s):
        out += ["", "over tasks (test contexts; stratified bootstrap):", _text_table(*aggregate_rows(s))]
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


def power_markdown(table: Mapping[str, Any]) -> str:
    """statistics.power_table as a markdown table: per task and budget DreamerV2's mean (SD of its
    seeds), the paper's gap, the expected effect, the pair SD with its source, the pairs for the
    table's power, the CPU core-hours here and the pairs at 1.5 times the pair SD."""
    pct = round(100 * table["power"])
    head = ["task", "env steps", "DreamerV2 mean (SD)", "paper gap", "expected effect", "pair SD (source)",
            f"pairs for {pct}% power", "CPU core-hours here", "pairs if the pair SD is 1.5x"]
    source = {"measured": "measured, walker grid", "dreamerv2_seeds": "√2 x DreamerV2's SD"}
    over = f"over {table['max_pairs']:,}"
    rows = [[r["task"], f"{r['env_steps'] // 1000}k", f"{r['dreamerv2_mean']:.1f} ({r['dreamerv2_sd']:.1f})",
             f"{100 * r['paper_gap']:+.1f}%", f"{r['expected_effect']:.1f}",
             f"{r['pair_sd']:.1f} ({source[r['pair_sd_source']]})",
             f"{r['pairs_needed']:,}" if r["pairs_needed"] is not None else over,
             f"{r['core_hours']:,.1f}" if r["core_hours"] is not None else "-",
             f"{r['pairs_if_sd_1_5x']:,}" if r["pairs_if_sd_1_5x"] is not None else over]
            for r in table["rows"]]
    return _md_table(head, rows)


def power_lines(table: Mapping[str, Any]) -> list[str]:
    """The walker grid's power and the cheapest row of statistics.power_table, one line each."""
    w, c, pct = table["walker_grid"], table["cheapest"], round(100 * table["power"])
    return [f"walker grid ({w['pairs']} pairs at {w['env_steps'] // 1000}k, pair SD {w['pair_sd']:.1f}): "
            f"detects {w['detectable_effect']:.1f} with {pct}% power; its power for the paper's gap "
            f"there ({w['paper_effect']:.1f}): {100 * w['power_for_paper_effect']:.1f}%",
            f"cheapest to power: {c['task']} at {c['env_steps'] // 1000}k env steps, {c['pairs_needed']} "
            f"pairs, {c['core_hours']:.1f} CPU core-hours"]


def print_power_table(json_path: str | None = None) -> int:
    """`protocad-compare --power`: print statistics.power_table as markdown and its two summary
    lines; write it as JSON too where asked (msgs_docs/results/power_table.json). Returns 0."""
    table = power_table()
    print(power_markdown(table), *("", *power_lines(table)), sep="\n", flush=True)
    if json_path:
        atomic_write_text(Path(json_path), json.dumps(table, indent=1) + "\n")
    return 0


def labels_of(doc: Mapping[str, Any], task: str) -> list[str]:
    return sorted({r["label"] for r in doc["runs"] if r["task"] == task and not r.get("superseded")})


def superseded_lines(doc: Mapping[str, Any]) -> list[str]:
    """One line per superseded row: kept as measured, counted nowhere."""
    return [f"{r['task']} {r['label']} seed {r['seed']}"
            + (f" ({r['final']['mean_return']:.1f})" if r["final"] else "") + f": {r['superseded']}"
            for r in sorted(doc["runs"], key=lambda r: (r["task"], r["label"], r["seed"])) if r.get("superseded")]


def plot_curves(doc: Mapping[str, Any], path: str | Path) -> Path:
    """PNG: one panel per task, return vs env steps, a line per variant with its 95% band."""
    # A Figure of its own, not pyplot's: no global backend or figure registry to set or leak.
    from matplotlib.figure import Figure

    tasks = sorted({r["task"] for r in doc["runs"]})
    fig = Figure(figsize=(5.2 * max(1, len(tasks)), 3.8))
    axes = fig.subplots(1, max(1, len(tasks)), squeeze=False)
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


BEGIN, END = "<!-- protocad-compare results: begin -->", "<!-- protocad-compare results: end -->"


def combined(docs: Sequence[Mapping[str, Any]], sources: Sequence[str] | None = None) -> dict[str, Any]:
    """The runs and random baselines of several results.json documents in one (for the plot and
    the rerun recording): the anchor's grid and the comparison's, say. A variant trained in
    several setups (the anchor at the small preset and at DreamerV2's sizes, or rendered
    'fast' and with dm_control's default look) is one curve per setup, labelled with what
    differs: `LABEL (PRESET preset)`, `LABEL (QUALITY render)` or both; `base_label` keeps the
    variant's own. A run (task, label, setup, seed) in two of them is refused: its curve would
    count twice. Superseded rows count nowhere, curves included, so they are left out: the grid
    that superseded them (its seeds again) reports beside them."""
    names = list(sources) if sources else [f"document {i + 1}" for i in range(len(docs))]
    setups: dict[tuple[str, str], set[tuple[str, str]]] = {}
    for doc in docs:
        for r in doc["runs"]:
            if not r.get("superseded"):
                setups.setdefault((r["task"], r["label"]), set()).add(_setup(r))
    seen: dict[tuple[str, str, int], str] = {}
    runs, random = [], {}
    for doc, name in zip(docs, names):
        for r in doc["runs"]:
            if r.get("superseded"):
                continue
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


def _section_body(doc: Mapping[str, Any], target: str) -> list[str]:
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
        plan = _relative_link("msgs_docs/results.md", target)
        lines += [f"Paired (the primary metric of [results.md]({plan})):", "",
                  *(f"- {p}" for p in paired), ""]
    superseded = superseded_lines(doc)
    if superseded:
        lines += ["Superseded (kept as measured, counted nowhere):", "", *(f"- {x}" for x in superseded), ""]
    progress = progress_rows(doc)
    if progress[1]:
        lines += [f"Not finished yet ({len(progress[1])} of {len(doc['runs'])} runs; as of {doc['created']}):", "",
                  _md_table(*progress), ""]
    if _over_tasks(s):
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
        lines += _section_body(doc, target)
    if image:
        lines += [f"![test-context return vs env steps]({_relative_link(image, target)})", ""]
    lines.append(END)
    return "\n".join(lines)


def _relative_link(path: str, target: str) -> str:
    """`path` (from the repository root) as a link from the markdown file `target`."""
    return path if os.path.isabs(path) else os.path.relpath(path, Path(target).parent)


def update_readme(readme: Path, section: str) -> None:
    """Replace the text between BEGIN and END (inclusive) in `readme` (ValueError without them)."""
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


def write_reports(docs: Sequence[Mapping[str, Any]], sources: Sequence[str], everything: Mapping[str, Any], *,
                  grid_dir: Path | None, image: str | None, rrd: str | None, markdown: bool,
                  readme: str | None) -> None:
    """protocad-compare's output from results.json documents (`everything`: them combined): the
    text report, the curves' plot and rerun recording, the markdown section (printed, and into
    `readme`). `grid_dir`: the grid's directory, where the plot and recording go besides where
    asked; None (--report): only where asked."""
    print("\n\n".join(format_report(d) for d in docs), flush=True)
    # Never by default into the directory of a results.json only read: that may be the source
    # tree (msgs_docs/results/).
    if grid_dir is None:
        png = plot_curves(everything, image) if image else "not written (--image PNG)"
    else:
        png = plot_curves(everything, grid_dir / "curves.png")
        if image:
            shutil.copyfile(png, image)
    rrd_path = rrd or (None if grid_dir is None else grid_dir / "curves.rrd")
    try:
        rrd_text = log_curves_rerun(everything, rrd_path) if rrd_path else "not written (--rrd PATH)"
    except ImportError:   # rerun-sdk absent (the GPU machine's bare Python)
        rrd_text = "not written (rerun-sdk is not installed)"
    print(f"[compare] plot: {png}\n[compare] rerun: {rrd_text}", flush=True)
    if markdown:
        print(markdown_section(docs, image=image, sources=sources))
    if readme:
        update_readme(Path(readme), markdown_section(docs, image=image, sources=sources, target=readme))
        print(f"[compare] updated the results section of {readme}", flush=True)
