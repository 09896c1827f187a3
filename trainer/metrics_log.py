"""Training metrics: one JSON line per logged update (RUN_DIR/metrics.jsonl), optional callbacks
(rerun) and TensorBoard, a short echo line for the terminal, and reading them back."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from protocad_ros.atomic import atomic_write_text
from trainer.runs import json_default

MetricsCallback = Callable[[int, Mapping[str, float]], None]


class MetricsLogger:
    """Append-only JSON-lines metrics writer; each line carries `update` and `wall_time`
    (seconds since the run started, carried over across resumes) plus the scalars.
    Callbacks (e.g. the rerun scalar logger) get (update, metrics) for every logged line.
    path None: nothing is written (a data-parallel rank other than 0 keeps only the clock)."""

    def __init__(self, path: Path | None, callbacks: Iterable[MetricsCallback] = (), wall_offset: float = 0.0,
                 echo_every_s: float | None = None, tensorboard: bool = True):
        self.path = Path(path) if path is not None else None
        self._f = None
        self._tb = None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = open(self.path, "a", buffering=1)
            if tensorboard:
                self._tb = tensorboard_writer(self.path.parent / TENSORBOARD_DIR)
        self.callbacks = [c for c in callbacks if c is not None]
        self._t0 = time.monotonic() - float(wall_offset)
        # Without a terminal no progress bar shows: a line of losses now and then instead.
        if echo_every_s is None:
            echo_every_s = 0.0 if sys.stdout.isatty() else ECHO_EVERY_S
        self.echo_every_s, self._last_echo = float(echo_every_s), -_INF_TIME

    @property
    def wall_time(self) -> float:
        return time.monotonic() - self._t0

    def log(self, update: int, metrics: Mapping[str, Any], **extra: Any) -> dict:
        row = {"update": int(update), "wall_time": round(self.wall_time, 3), "time": round(time.time(), 3)}
        row.update(extra)
        for k, v in metrics.items():
            row[k] = _scalar(v)
        if self._f is not None:
            self._f.write(json.dumps(row, default=json_default) + "\n")
            self._f.flush()
        if self._tb is not None:
            kind = str(extra.get("kind", "train"))
            step = int(update) if kind == "train" else int(extra.get("env_steps", update))
            for k, v in row.items():
                if k not in ("update", "time", "env_steps") and isinstance(v, (int, float)) \
                        and not isinstance(v, bool):
                    self._tb.add_scalar(f"{kind}/{k}", v, step)
        if self.path is not None and self.echo_every_s and extra.get("kind") == "train" \
                and time.monotonic() - self._last_echo >= self.echo_every_s:
            self._last_echo = time.monotonic()
            print(echo_line(row), flush=True)
        for cb in self.callbacks:
            try:
                cb(int(update), {k: v for k, v in row.items() if isinstance(v, (int, float))})
            except Exception as exc:  # noqa: BLE001 - a broken visualizer must not stop training
                print(f"[metrics] callback {cb!r} failed: {exc}", file=sys.stderr)
                self.callbacks.remove(cb)
        return row

    def eval_hooks(self) -> list:
        """Callbacks that also take evaluation results (`log_eval(update, results)`)."""
        return [cb for cb in self.callbacks if hasattr(cb, "log_eval")]

    def close(self) -> None:
        if self._f is not None and not self._f.closed:
            self._f.close()
        if self._tb is not None:
            self._tb.close()
            self._tb = None
        for cb in self.callbacks:
            close = getattr(cb, "close", None)
            if callable(close):
                try:
                    close()
                except Exception as exc:  # noqa: BLE001
                    print(f"[metrics] closing {cb!r} failed: {exc}", file=sys.stderr)
        self.callbacks = []


#: TensorBoard event files go to RUN_DIR/tensorboard (`tensorboard --logdir RUN_DIR`); the
#: tags are KIND/NAME (train/wm_loss on the update axis, episode/train_return and
#: eval/eval_return on the env-step axis).
TENSORBOARD_DIR = "tensorboard"
#: Seconds between the loss lines printed when stdout is not a terminal.
ECHO_EVERY_S = 30.0
_INF_TIME = float("inf")
_ECHO_KEYS = ("wm_loss", "image_loss", "reward_loss", "kl", "swav_loss", "actor_loss", "critic_loss",
              "entropy", "imag_return", "loss", "q_loss", "alpha")


def tensorboard_writer(log_dir: Path):
    """A torch.utils.tensorboard SummaryWriter, or None (with a note) where tensorboard is not
    installed (the GPU machine's bare Python)."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError as exc:
        print(f"[metrics] no TensorBoard event files: {exc}", file=sys.stderr)
        return None
    return SummaryWriter(log_dir=str(log_dir))


def echo_line(row: Mapping[str, Any]) -> str:
    """'[train] update 120 (1.8 updates/s): wm_loss 412.1, reward_loss 0.05, ...' of a row."""
    vals = ", ".join(f"{k} {row[k]:.4g}" for k in _ECHO_KEYS if isinstance(row.get(k), (int, float)))
    rate = f" ({row['updates_per_s']:.2f} updates/s)" if isinstance(row.get("updates_per_s"), (int, float)) else ""
    return f"[train] update {row['update']}{rate}: {vals}"


def _scalar(v: Any) -> Any:
    if hasattr(v, "item"):
        v = v.item()
    if isinstance(v, float) and not np.isfinite(v):
        return str(v)
    return v


def read_metrics(path: Path) -> list[dict]:
    rows = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if line:
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError:  # a torn last line after a kill
                    pass
    return rows


def truncate_metrics(path: Path, max_update: int) -> None:
    """Drop lines logged after the checkpoint we resume from (they will be logged again).
    Episode rows stay: they describe collected data, which a resume keeps and counts, and their
    episodes are never collected again."""
    path = Path(path)
    if not path.exists():
        return
    rows = [r for r in read_metrics(path)
            if int(r.get("update", 0)) <= max_update or r.get("kind") == "episode"]
    atomic_write_text(path, "".join(json.dumps(r) + "\n" for r in rows))


class RunningMean:
    def __init__(self):
        self.sums: dict[str, float] = {}
        self.n: dict[str, int] = {}

    def add(self, metrics: Mapping[str, Any]) -> None:
        for k, v in metrics.items():
            try:
                v = float(v)
            except (TypeError, ValueError):
                continue
            if np.isfinite(v):
                self.sums[k] = self.sums.get(k, 0.0) + v
                self.n[k] = self.n.get(k, 0) + 1

    def pop(self) -> dict[str, float]:
        out = {k: self.sums[k] / self.n[k] for k in self.sums}
        self.sums, self.n = {}, {}
        return out
