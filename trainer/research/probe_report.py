"""What protocad-probe writes: its JSON (schema PROBE_SCHEMA, checked on every write), the text
tables it prints, a PNG (R^2 bars per feature and setting, open-loop error curves) and a rerun
recording of the window features coloured by context.

Rerun entity paths (all static):

=================================== ==========================================================
/probe                              AnnotationContext: class id = context index, its label
                                    ("test m=0.2 d=1.5") and a viridis colour of its log m
/probe/<feature>/pca2d/<split>      Points2D: one per window, the 2-D PCA of <feature> (fitted
                                    on both splits' windows), class id = its context
/probe/<feature>/pca2d/contexts     Points2D: each context's mean position, labelled
/probe/table                        TextDocument (markdown): the probe tables
/open_loop/<split>/image_mse        Scalars on the 'horizon' timeline (1..H)
/open_loop/<split>/reward_abs_err   Scalars on the 'horizon' timeline
=================================== ==========================================================

The recording carries its layout: tabs Features (a 2-D view per feature set), Open loop and Probes.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from protocad_ros.atomic import atomic_write_text
from sim_bridge.contract.contexts import context_label
from trainer.research.probe_fit import SETTINGS, Windows
from trainer.research.results_json import check_schema
from trainer.run_input import load_json_object
from trainer.viz.context_view import colormap, project

SCHEMA_ID = "protocad-probe/1"
HEADLINE_HORIZONS = (1, 10, 25, 50)

_NUM = {"type": "number"}
_INT = {"type": "integer", "minimum": 0}
_SCORE = {"type": "object", "required": ["r2", "spearman", "n_windows", "n_contexts"],
          "properties": {"r2": _NUM, "spearman": {"type": ["number", "null"]}, "n_windows": _INT,
                         "n_contexts": _INT}}
_CURVE = {"type": "array", "items": _NUM}
_OPEN_LOOP = {"type": "object", "required": ["horizons", "image_mse", "reward_abs_err", "n_segments"],
              "properties": {"horizons": {"type": "array", "items": {"type": "integer", "minimum": 1}},
                             "image_mse": {"oneOf": [{"type": "null"}, _CURVE]},
                             "reward_abs_err": _CURVE, "n_segments": _INT}}
PROBE_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "object",
    "required": ["schema", "command", "code_version", "checkpoint", "task", "variant", "updates", "env_steps", "settings", "features",
                 "contexts", "probes", "skipped", "open_loop", "assignment", "seconds"],
    "properties": {
        "schema": {"const": SCHEMA_ID},
        "command": {"type": "array", "items": {"type": "string"}},
        "code_version": {"type": "string"},
        "checkpoint": {"type": "string"},
        "task": {"type": "string"},
        "variant": {"type": "string"},
        "updates": _INT,
        "env_steps": {"type": ["integer", "null"]},
        "settings": {"type": "object", "required": ["episodes", "steps", "skip", "window", "context_steps",
                                                    "horizon", "max_contexts", "seed", "pixel_dim"]},
        "features": {"type": "object", "additionalProperties": _INT},
        "contexts": {"type": "array", "items": {
            "type": "object", "required": ["split", "context", "windows"],
            "properties": {"split": {"enum": ["train", "test"]},
                           "context": {"type": "object", "additionalProperties": _NUM},
                           "windows": _INT}}},
        "probes": {"type": "object", "propertyNames": {"enum": list(SETTINGS)},
                   "additionalProperties": {"type": "object", "additionalProperties": {
                       "type": "object", "additionalProperties": _SCORE}}},
        "skipped": {"type": "object", "additionalProperties": {
            "oneOf": [{"type": "string"}, {"type": "object", "additionalProperties": {"type": "string"}}]}},
        "open_loop": {"type": "object", "propertyNames": {"enum": ["train", "test"]},
                      "additionalProperties": _OPEN_LOOP},
        "assignment": {"oneOf": [{"type": "null"}, {
            "type": "object", "required": ["top_mean", "entropy_mean", "uniform_entropy", "prototypes", "steps"],
            "properties": {"top_mean": _NUM, "entropy_mean": _NUM, "uniform_entropy": _NUM,
                           "prototypes": _INT, "steps": _INT}}]},
        # absent in probes written before they were measured
        "health": {"oneOf": [{"type": "null"}, {"type": "object", "additionalProperties": _NUM}]},
        "collapsed": {"type": ["string", "null"]},
        "prototypes": {"oneOf": [{"type": "null"}, {
            "type": "object", "required": ["parameter", "cos_to_initial_mean", "cos_to_initial_min", "count",
                                           "prototype_freeze"],
            "properties": {"parameter": {"type": "string"}, "cos_to_initial_mean": _NUM,
                           "cos_to_initial_min": _NUM, "count": _INT,
                           "prototype_freeze": {"type": ["integer", "null"]},
                           # absent before --drift-from: the seeded draw
                           "start": {"oneOf": [{"const": "seeded draw"}, {
                               "type": "object", "required": ["policy", "sha256"],
                               "properties": {"policy": {"type": "string"}, "sha256": {"type": "string"}}}]}}}]},
        "seconds": _NUM,
    },
}


def validate(doc: Mapping[str, Any]) -> None:
    """The probe's JSON against PROBE_SCHEMA (ValueError naming where it fails)."""
    check_schema(doc, PROBE_SCHEMA, "probe JSON", SCHEMA_ID)


def migrate(doc: dict[str, Any]) -> dict[str, Any]:
    """A probe JSON written before the freeze had one name: its prototypes' `frozen_updates`
    read as `prototype_freeze` (the run.json and results.json name)."""
    protos = doc.get("prototypes")
    if isinstance(protos, dict) and "frozen_updates" in protos and "prototype_freeze" not in protos:
        doc["prototypes"] = {("prototype_freeze" if k == "frozen_updates" else k): v for k, v in protos.items()}
    return doc


def write_json(doc: Mapping[str, Any], path: Path) -> None:
    validate(doc)
    atomic_write_text(path, json.dumps(doc, indent=2, allow_nan=False) + "\n")


def read_json(path: str | Path) -> dict[str, Any]:
    """A probe JSON, bounded in size and depth and checked against PROBE_SCHEMA (ValueError
    naming the file)."""
    try:
        doc = migrate(load_json_object(path))
    except ValueError as exc:
        raise ValueError(f"not a probe JSON: {exc}") from None
    try:
        validate(doc)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    return doc


# ----------------------------------------------------------------------------- text
def _fmt(v: float | None, width: int = 6) -> str:
    return "-".rjust(width) if v is None or not math.isfinite(v) else f"{v:{width}.2f}"


def probe_table(probes: Mapping[str, Any], target: str) -> str:
    """Rows = settings, columns = features: 'R2 (rank)' of the probe for `target`."""
    rows = [(s, probes[s][target]) for s in SETTINGS if target in probes.get(s, {})]
    if not rows:
        return f"{target}: no probe (see 'skipped' in the JSON)"
    feats = list(dict.fromkeys(f for _, r in rows for f in r))
    head = f"{target:<14}" + "".join(f"{f:>16}" for f in feats)
    lines = [head, "-" * len(head)]
    for setting, r in rows:
        cells = "".join(f"{_fmt(r[f]['r2'])} ({_fmt(r[f]['spearman'], 5)})".rjust(16) if f in r else " " * 16
                        for f in feats)
        lines.append(f"{setting:<14}{cells}")
    return "\n".join(lines)


def open_loop_table(open_loop: Mapping[str, Any], horizons: Sequence[int] = HEADLINE_HORIZONS) -> str:
    """Image MSE and reward error at a few horizons, one row per split."""
    lines = ["open loop     " + "".join(f"  k={k:<3} mse / |dr|" for k in horizons)]
    for split, ol in open_loop.items():
        cells = []
        for k in horizons:
            if k > len(ol["horizons"]):
                cells.append(" " * 19)
                continue
            mse = "-" if ol["image_mse"] is None else f"{ol['image_mse'][k - 1]:.5f}"
            cells.append(f"  {mse:>8} / {ol['reward_abs_err'][k - 1]:6.3f}")
        lines.append(f"{split + ' (' + str(ol['n_segments']) + ' seg)':<14}" + "".join(cells))
    return "\n".join(lines)


def _mean_range(values: Sequence[float], digits: int = 2) -> str:
    v = [x for x in values if x is not None and math.isfinite(x)]
    if not v:
        return "-"
    f = f".{digits}f"
    return f"{np.mean(v):{f}}" if len(v) == 1 else f"{np.mean(v):{f}} ({min(v):{f}} to {max(v):{f}})"


def _r2_table(group: Sequence[Mapping[str, Any]], variant: str, target: str) -> str:
    feats = list(dict.fromkeys(f for d in group for st in d["probes"].values() for f in st.get(target, {})))
    lines = [f"| {target}: {variant} ({len(group)}) | " + " | ".join(feats) + " |", "|---" * (len(feats) + 1) + "|"]
    for setting in SETTINGS:
        scores = [d["probes"].get(setting, {}).get(target, {}) for d in group]
        if any(scores):
            cells = [_mean_range([sc[f]["r2"] for sc in scores if f in sc]) for f in feats]
            lines.append(f"| {setting} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _open_loop_rows(group: Sequence[Mapping[str, Any]], variant: str, horizons: Sequence[int]) -> list[str]:
    rows = []
    for split in ("test", "train"):
        curves = [d["open_loop"][split] for d in group if split in d["open_loop"]]
        cells = []
        for k in horizons:
            mse = [c["image_mse"][k - 1] for c in curves if c["image_mse"] and k <= len(c["image_mse"])]
            dr = [c["reward_abs_err"][k - 1] for c in curves if k <= len(c["reward_abs_err"])]
            cells.append(f"{np.mean(mse):.4f} / {np.mean(dr):.3f}" if mse and dr else "-")
        if curves:
            rows.append(f"| {variant} ({len(curves)}) | {split} | " + " | ".join(cells) + " |")
    return rows


def summary_markdown(docs: Sequence[Mapping[str, Any]], horizons: Sequence[int] = HEADLINE_HORIZONS) -> str:
    """Probes of several checkpoints (a grid's seeds of each variant) as markdown: per target and
    variant, the R^2 of each feature in each setting, mean over the checkpoints (min to max);
    then the open-loop image MSE and reward error at a few horizons, mean over the checkpoints."""
    by_variant: dict[str, list[Mapping[str, Any]]] = {}
    for d in docs:
        by_variant.setdefault(d["variant"], []).append(d)
    targets = list(dict.fromkeys(t for d in docs for st in d["probes"].values() for t in st))
    parts = ["R^2 of linear probes on window means, mean over the checkpoints (min to max):"]
    parts += [_r2_table(group, variant, t) for t in targets for variant, group in sorted(by_variant.items())]
    head = ["| open loop | split | " + " | ".join(f"k={k}: image MSE / reward abs err" for k in horizons) + " |",
            "|---|---" + "|---" * len(horizons) + "|"]
    parts.append("\n".join(head + [r for v, g in sorted(by_variant.items()) for r in _open_loop_rows(g, v, horizons)]))
    rows = [r for v, g in sorted(by_variant.items()) if (r := _prototype_row(g, v))]
    if rows:
        parts.append("\n".join(["| prototypes | cosine to their initial values | top assignment probability |",
                                "|---|---|---|", *rows]))
    return "\n\n".join(parts)


def _prototype_row(group: Sequence[Mapping[str, Any]], variant: str) -> str | None:
    cos = [d["prototypes"]["cos_to_initial_mean"] for d in group if d.get("prototypes")]
    top = [d["assignment"]["top_mean"] for d in group if d.get("assignment")]
    if not cos and not top:
        return None
    return f"| {variant} ({len(group)}) | {_mean_range(cos, 3) if cos else '-'} | {_mean_range(top, 3) if top else '-'} |"


def report_text(doc: Mapping[str, Any]) -> str:
    targets = list(dict.fromkeys(t for s in doc["probes"].values() for t in s))
    head = (f"{doc['task']} {doc['variant']} ({doc['updates']} updates): {doc['checkpoint']}\n"
            "probes: R2 (Spearman) of ridge probes on window means, by setting and feature")
    parts = [head] + [probe_table(doc["probes"], t) for t in targets] + [open_loop_table(doc["open_loop"])]
    a = doc.get("assignment")
    if a:
        parts.append(f"prototype assignment w: top probability {a['top_mean']:.3f} on average (uniform: "
                     f"{1 / a['prototypes']:.3f}), entropy {a['entropy_mean']:.2f} nats of at most "
                     f"{a['uniform_entropy']:.2f}")
    h = doc.get("health")
    if h:
        parts.append(health_line(h, doc.get("collapsed")))
    c = doc.get("prototypes")
    if c:
        parts.append(prototypes_line(c, doc["updates"]))
    return "\n\n".join(parts)


def health_line(h: Mapping[str, float], collapsed: str | None = None) -> str:
    """The context module's health figures on the unseen contexts, and whether they say collapsed."""
    return (f"context health on the unseen contexts (msgs_docs/training.md#context-health): projection cosine "
            f"{h['proj_cosine']:.2f}, top probability {h['swav_pred_top']:.3f} predicted / "
            f"{h['swav_target_top']:.3f} targets, entropy {h['swav_pred_entropy']:.2f} / {h['swav_target_entropy']:.2f}, "
            f"modal share {h['modal_share']:.2f}, between-sequence share of u {h['proj_between_share']:.2f}"
            + (f"; COLLAPSED: {collapsed}" if collapsed else ""))


def prototypes_line(c: Mapping[str, Any], updates: int) -> str:
    """Whether training moved the prototypes, in one line."""
    frozen = ("" if c["prototype_freeze"] is None
              else f"; frozen for the first {c['prototype_freeze']:,} of its {updates:,} updates")
    start = c.get("start", "seeded draw")
    start = ("their seeded initial values" if start == "seeded draw"
             else f"those of {Path(start['policy']).name}, where the run started")
    return (f"prototypes c_k: cosine to {start} {c['cos_to_initial_mean']:.3f} on average, "
            f"{c['cos_to_initial_min']:.3f} at the least (1.000: never trained){frozen}")


# ----------------------------------------------------------------------------- PNG
def write_png(doc: Mapping[str, Any], path: Path) -> None:
    """R^2 bars (one panel per target: settings on x, a bar per feature) above the open-loop
    error curves of both splits."""
    # A Figure of its own, not pyplot's: no global backend or figure registry to set or leak.
    from matplotlib.figure import Figure

    targets = list(dict.fromkeys(t for s in doc["probes"].values() for t in s))
    fig = Figure(figsize=(6 * max(2, len(targets)), 8))
    axes = fig.subplots(2, max(2, len(targets)), squeeze=False)
    for ax, target in zip(axes[0], targets):
        _bars(ax, doc["probes"], target)
    for ax in axes[0][len(targets):]:
        ax.axis("off")
    for ax, key, label in ((axes[1][0], "image_mse", "image MSE per pixel (0..1)"),
                           (axes[1][1], "reward_abs_err", "|reward error|")):
        curves = [(split, ol) for split, ol in doc["open_loop"].items() if ol[key] is not None]
        for split, ol in curves:
            ax.plot(ol["horizons"], ol[key], label=f"{split} contexts", marker=".")
        ax.set_xlabel(f"open-loop horizon (agent steps after {doc['settings']['context_steps']} observed frames)")
        ax.set_ylabel(label)
        if curves:
            ax.legend()
        else:
            ax.text(0.5, 0.5, f"{doc['variant']} has no image decoder", ha="center", transform=ax.transAxes)
    for ax in axes[1][2:]:
        ax.axis("off")
    fig.suptitle(f"protocad-probe: {doc['task']} {doc['variant']}, {doc['updates']} updates")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def _bars(ax: Any, probes: Mapping[str, Any], target: str) -> None:
    settings = [s for s in SETTINGS if target in probes.get(s, {})]
    feats = list(dict.fromkeys(f for s in settings for f in probes[s][target]))
    width = 0.8 / max(1, len(feats))
    for i, f in enumerate(feats):
        vals = [probes[s][target].get(f, {}).get("r2", np.nan) for s in settings]
        # Far-negative R^2 (an extrapolation that misses) would squash every other bar.
        ax.bar(np.arange(len(settings)) + i * width, np.clip(vals, -1.0, 1.0), width, label=f)
    ax.set_xticks(np.arange(len(settings)) + 0.4 - width / 2, settings)
    ax.set_ylim(-1.0, 1.0)
    ax.axhline(0.0, color="black", linewidth=0.5)
    ax.set_title(f"probe R^2 for {target} (clipped at -1)")
    ax.legend(fontsize="small", ncol=2)


# ----------------------------------------------------------------------------- rerun
def write_rrd(doc: Mapping[str, Any], windows: Windows, contexts: Sequence[tuple[str, dict]], path: Path) -> None:
    """The window features in 2-D PCA, coloured and labelled by context (see the table above)."""
    import rerun as rr

    rec = rr.RecordingStream("protocad_probe")
    rec.save(str(path))
    labels = [context_label(c, s) for s, c in contexts]
    colours = colormap(np.log([c["m"] for _, c in contexts]))
    rec.log("/probe", rr.AnnotationContext([rr.AnnotationInfo(id=i, label=lab, color=tuple(int(x) for x in col))
                                            for i, (lab, col) in enumerate(zip(labels, colours))]), static=True)
    for feat, X in windows.features.items():
        Y, _ = project(X, 2, "pca")
        for split in ("train", "test"):
            mask = windows.split == split
            rec.log(f"/probe/{feat}/pca2d/{split}", rr.Points2D(Y[mask], class_ids=windows.context[mask],
                                                               radii=-3.0 if split == "test" else -2.0), static=True)
        ids = np.unique(windows.context)
        means = np.stack([Y[windows.context == i].mean(0) for i in ids])
        rec.log(f"/probe/{feat}/pca2d/contexts", rr.Points2D(means, class_ids=ids, radii=-6.0,
                                                            show_labels=False), static=True)
    rec.log("/probe/table", rr.TextDocument("```\n" + report_text(doc) + "\n```", media_type="text/markdown"),
            static=True)
    for split, ol in doc["open_loop"].items():
        for key in ("image_mse", "reward_abs_err"):
            if ol[key] is None:
                continue
            for k, v in zip(ol["horizons"], ol[key]):
                rec.set_time("horizon", sequence=k)
                rec.log(f"/open_loop/{split}/{key}", rr.Scalars(v))
    rec.send_blueprint(probe_blueprint(list(windows.features), list(doc["open_loop"])))
    rec.flush()
    rec.disconnect()


def probe_blueprint(features: Sequence[str], splits: Sequence[str]):
    """Tabs: the features (one 2-D view each, both splits and the context means), the open-loop
    curves, the tables."""
    import rerun.blueprint as rrb

    views = [rrb.Spatial2DView(origin=f"/probe/{f}/pca2d", name=f"{f}: PCA, by context") for f in features]
    curves = [rrb.TimeSeriesView(origin="/open_loop", name=name, contents=[f"/open_loop/{s}/{key}" for s in splits])
              for key, name in (("image_mse", "open loop: image MSE"), ("reward_abs_err", "open loop: |reward error|"))]
    return rrb.Blueprint(rrb.Tabs(rrb.Grid(*views, name="Features"), rrb.Horizontal(*curves, name="Open loop"),
                                  rrb.TextDocumentView(origin="/probe/table", name="Probes")))
