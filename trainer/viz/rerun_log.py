"""Training-time rerun logging: losses and evaluation returns per context as time series on the
'update' timeline, plus (optionally) the context view of ``trainer.viz.visualize`` at chosen updates.

    rec = TrainingRecorder(run_dir / "metrics.rrd")          # or a rerun.RecordingStream
    rec.log_metrics(update, {"model_loss": 1.2, "kl": 3.0})  # every logged update
    rec.log_eval(update, results)                            # after every evaluation
    rec.log_context_view(update, agent, episodes)            # e.g. at the end of --demo
    rec.close()

``metrics_callback(rrd_path)`` is what protocad-train/-online/-loop hand their MetricsLogger
(`--rerun`, through trainer/viz/metrics_rerun.py, which imports this module only then): the callable it returns takes (update, metrics) like every MetricsLogger callback.

Entity paths (timeline ``update``; '.' in a metric name becomes '/'):

=================================== ==============================================================
/train/<metric>                     rr.Scalars: a training scalar (loss, KL, returns, ...)
/eval/<split>/<context>/return      rr.Scalars: mean evaluation return of one context, e.g.
                                    /eval/test/m0.4_d1.5/return
/eval/<split>/mean_return           rr.Scalars: mean over that split's contexts (paper protocol)
/eval/<split>/median_return         rr.Scalars: median over that split's contexts
/train/config                       rr.TextDocument (static): the run's config, when given
(context view)                      the entity paths of trainer/viz/context_log.py, on 'update'
=================================== ==============================================================
"""
from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb
import rerun.chunk as rc
import yaml

from protocad_ros.live_view import path_part
from trainer.viz.context_blueprint import context_blueprint_parts
from trainer.viz.context_log import log_context_view, log_open_loop, log_reconstructions
from trainer.viz.context_view import compute_context_view

SKIP_KEYS = frozenset({"update", "time"})


def metric_path(name: str) -> str:
    """'/train/<name>' with '.' and '/' as hierarchy, anything else odd turned into '_'."""
    parts = [path_part(p) for p in str(name).replace("/", ".").split(".") if p]
    return "/train/" + "/".join(parts or ["_"])


def _context_part(context: Mapping[str, float]) -> str:
    return "_".join(f"{path_part(str(k))}{float(v):g}" for k, v in context.items()) or "none"


def normalize_eval(results: Any, split: str | None = None) -> list[tuple[str, str, float]]:
    """(split, context path part, mean return) rows from the shapes evaluation code produces:

    * a mapping label -> return or list of returns, where label is 'train/m0.75' /
      'test m=0.4 d=1.5' / any string (split unknown: 'eval');
    * a sequence of records (mappings or objects) with ``context`` (dict), ``split`` and one of
      ``return`` / ``mean_return`` / ``returns`` / ``episode_returns``;
    * a mapping with a 'per_context' (or 'contexts') entry holding one of the above, e.g.
      trainer.learn.evaluate.EvalResult.to_dict() (its 'split' is the records' default split).
    """
    if hasattr(results, "to_dict") and hasattr(results, "per_context"):
        results = results.to_dict()
    if isinstance(results, Mapping):
        for key in ("per_context", "contexts"):
            if key in results:
                return normalize_eval(results[key], results.get("split", split))
        rows = []
        for label, value in results.items():
            split, name = _split_label(str(label))
            rows.append((split, name, _mean(value)))
        return rows
    rows = []
    for rec in results:
        get = rec.get if isinstance(rec, Mapping) else (lambda k, d=None, r=rec: getattr(r, k, d))
        context = get("context")
        rec_split = str(get("split", None) or split or "eval")
        value = None
        for key in ("return", "mean_return", "returns", "episode_returns"):
            if get(key) is not None:
                value = get(key)
                break
        if context is None or value is None:
            raise ValueError(f"evaluation record needs 'context' and a return: {rec!r}")
        rows.append((path_part(rec_split), _context_part(context), _mean(value)))
    return rows


def _split_label(label: str) -> tuple[str, str]:
    text = label.strip()
    for sep in ("/", " "):
        head, s, tail = text.partition(sep)
        if s and head in ("train", "test"):
            return head, _label_part(tail)
    return "eval", _label_part(text)


def _label_part(text: str) -> str:
    # 'm=0.4 d=1.5' / 'm=0.4,d=1.5' -> 'm0.4_d1.5'
    text = text.replace("=", "").replace(",", " ").strip()
    return "_".join(path_part(t) for t in text.split()) or "none"


def _mean(value: Any) -> float:
    arr = np.asarray(value, np.float64).reshape(-1)
    if arr.size == 0:
        return float("nan")
    return float(arr.mean())


def training_blueprint(metric_names: Iterable[str] = (), eval_splits: Iterable[str] = ()):
    """One time-series view per training metric (grid) and the evaluation views."""
    views = [rrb.TimeSeriesView(origin=metric_path(m), name=m) for m in metric_names]
    train = rrb.Grid(*views, name="Training") if views else rrb.TimeSeriesView(
        origin="/train", name="Training")
    evals = []
    for split in eval_splits:
        evals.append(rrb.TimeSeriesView(origin=f"/eval/{split}", name=f"{split}: return per context",
                                        contents=[f"/eval/{split}/**",
                                                  f"- /eval/{split}/mean_return",
                                                  f"- /eval/{split}/median_return"]))
        evals.append(rrb.TimeSeriesView(origin=f"/eval/{split}", name=f"{split}: mean / median",
                                        contents=[f"/eval/{split}/mean_return",
                                                  f"/eval/{split}/median_return"]))
    tabs = [train]
    if evals:
        tabs.append(rrb.Grid(*evals, name="Evaluation"))
    return tabs


class TrainingRecorder:
    """Rerun time series of a training run on the 'update' timeline.

    target: an .rrd path (written as it goes; complete after close()), or a
    rerun.RecordingStream (e.g. from protocad_ros.live_view.open_stream('spawn')).
    Callable as a MetricsLogger callback: ``recorder(update, metrics)`` = log_metrics.
    """

    def __init__(self, target: str | Path | Any, *, application_id: str = "protocad_train",
                 recording_id: str | None = None, config: Any = None):
        if isinstance(target, (str, Path)):
            path = Path(target)
            if path.suffix != ".rrd":
                raise ValueError(f"rerun recording path must end in .rrd, got {str(path)!r}")
            path.parent.mkdir(parents=True, exist_ok=True)
            self.path: Path | None = path
            self.recording = rr.RecordingStream(application_id, recording_id=recording_id)
            self.recording.save(str(path))
            self._owned = True
        elif hasattr(target, "log") and hasattr(target, "set_time"):
            self.path, self.recording, self._owned = None, target, False
        else:
            raise TypeError(f"TrainingRecorder target must be an .rrd path or a "
                            f"rerun.RecordingStream, got {type(target).__name__}")
        self._metrics: list[str] = []
        self._eval_splits: list[str] = []
        self._context_tabs: list[Any] = []
        self._closed = False
        if config is not None:
            self.log_config(config)

    # ---------------------------------------------------------------------------- metrics
    def __call__(self, update: int, metrics: Mapping[str, Any]) -> None:
        self.log_metrics(update, metrics)

    def log_metrics(self, update: int, metrics: Mapping[str, Any]) -> None:
        """One point per numeric entry at ``update`` (non-numeric entries and the bookkeeping
        keys 'update' and 'time' are skipped; NaN/inf are logged and show as gaps)."""
        rec = self.recording
        rec.set_time("update", sequence=int(update))
        new = False
        for name, value in metrics.items():
            if name in SKIP_KEYS or isinstance(value, bool):
                continue
            try:
                v = float(value.item() if hasattr(value, "item") else value)
            except (TypeError, ValueError):
                continue
            rec.log(metric_path(name), rr.Scalars(v))
            if name not in self._metrics:
                self._metrics.append(name)
                new = True
        if new:
            self._send_blueprint()

    def log_eval(self, update: int, per_context_returns: Any) -> list[tuple[str, str, float]]:
        """Evaluation returns per context (see ``normalize_eval`` for accepted shapes), plus
        mean and median per split. Returns the normalized rows."""
        rec = self.recording
        rows = normalize_eval(per_context_returns)
        rec.set_time("update", sequence=int(update))
        by_split: dict[str, list[float]] = {}
        for split, name, value in rows:
            rec.log(f"/eval/{split}/{name}/return", rr.Scalars(value))
            if math.isfinite(value):
                by_split.setdefault(split, []).append(value)
        for split, vals in by_split.items():
            rec.log(f"/eval/{split}/mean_return", rr.Scalars(float(np.mean(vals))))
            rec.log(f"/eval/{split}/median_return", rr.Scalars(float(np.median(vals))))
        if any(s not in self._eval_splits for s in by_split):
            self._eval_splits += [s for s in by_split if s not in self._eval_splits]
            self._send_blueprint()
        return rows

    def log_config(self, config: Any) -> None:
        """The run's config as a static text document (/train/config)."""
        d = config.to_dict() if hasattr(config, "to_dict") else config
        text = d if isinstance(d, str) else yaml.safe_dump(d, sort_keys=False)
        self.recording.log("/train/config", rr.TextDocument(text), static=True)

    # ---------------------------------------------------------------------------- context view
    def log_context_view(self, update: int, agent: Any, episodes: Sequence[Any], *,
                         projection: str = "pca", open_loop: bool = True, context_steps: int = 5,
                         horizon: int = 50, num_episodes: int = 4, **kw: Any):
        """The context view of trainer.viz.visualize (embeddings, prototypes, assignments,
        reconstructions, open loop) for ``agent`` on ``episodes`` at ``update``; returns the
        ContextView."""
        view = compute_context_view(agent, episodes, projection=projection, **kw)
        log_context_view(self.recording, view, update=update)
        log_reconstructions(self.recording, agent, view.episodes, num_episodes=num_episodes,
                            update=update)
        if open_loop and horizon > 0:
            log_open_loop(self.recording, agent, view.episodes, context_steps=context_steps,
                          horizon=horizon, num_episodes=num_episodes, update=update)
        self._context_tabs = context_blueprint_parts(view)
        self._send_blueprint()
        return view

    # ---------------------------------------------------------------------------- plumbing
    def _send_blueprint(self) -> None:
        tabs = training_blueprint(self._metrics, self._eval_splits) + list(self._context_tabs)
        try:
            self.recording.send_blueprint(rrb.Blueprint(rrb.Tabs(*tabs)))
        except Exception as exc:  # noqa: BLE001 - a layout problem must never stop training
            print(f"[rerun_log] blueprint not sent: {exc}", file=sys.stderr)

    def flush(self) -> None:
        self.recording.flush()

    def close(self) -> None:
        """Flush; an owned .rrd file is complete afterwards. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self.recording.flush()
        if self._owned:
            self.recording.disconnect()

    def __enter__(self) -> "TrainingRecorder":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def metrics_callback(rrd_path: str | Path | None, application: str = "protocad-train",
                     recording_id: str | None = None) -> TrainingRecorder | None:
    """The training scalars' callback of protocad-train/-online/-loop: a TrainingRecorder writing
    ``rrd_path`` (callable as (update, metrics); ``.recording`` is the stream, ``.log_eval``
    and ``.log_context_view`` are there for the evaluation and the loop); None without a path."""
    if not rrd_path:
        return None
    return TrainingRecorder(rrd_path, application_id=application, recording_id=recording_id)


def read_recording(path: str | Path) -> dict[str, dict[str, Any]]:
    """What an .rrd file holds, per entity path (rerun's own reader, rerun.chunk.RrdReader):
    {'rows': n, 'timelines': {...}, 'static': bool, 'columns': {component or timeline: [row
    values...]}}; the key '__blueprints' counts the blueprint stores. For tests and scripts."""
    reader = rc.RrdReader(str(path))
    out: dict[str, dict[str, Any]] = {}
    for ch in reader.stream().to_chunks():
        rb = ch.to_record_batch()
        d = out.setdefault(ch.entity_path, {"rows": 0, "timelines": set(), "static": False,
                                            "columns": {}})
        d["rows"] += ch.num_rows
        d["timelines"].update(ch.timeline_names)
        d["static"] = d["static"] or ch.is_static
        for name in rb.schema.names:
            if name == "rerun.controls.RowId":
                continue
            col = rb.column(name)
            if pa.types.is_timestamp(col.type) or pa.types.is_duration(col.type):
                col = col.cast(pa.int64())  # nanoseconds, as logged
            d["columns"].setdefault(name, []).extend(col.to_pylist())
    out["__blueprints"] = {"rows": len(reader.blueprints()), "timelines": set(), "static": True,
                           "columns": {}}
    return out
