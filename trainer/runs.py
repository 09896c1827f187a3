"""Shared helpers of the trainer CLIs: run directories, config overrides, seeding, devices,
metrics (JSON lines + optional callbacks, e.g. rerun), progress bars and Ctrl-C handling.

No ROS import here; the training, evaluation, loop and in-process paths all use it.

Run directory layout (every CLI that trains writes the same one)::

    RUN_DIR/
      config.yaml             the full training config (protocad_ros.model.config.Config)
      run.json                 how the run was started (argv, task, variant, seed, device, ...)
      metrics.jsonl            one JSON object per logged update: {"update", "wall_time", ...}
      checkpoints/latest.pt    newest checkpoint (atomic replace; what the policy node loads)
      eval/*.json              evaluation results (loop / online)
      bags/NAME/               MCAP logs written by the loop / online path (rosbag2 layout)
      metrics.rrd              rerun recording of the scalars (when --rerun is given)
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
import yaml

from protocad_ros.atomic import atomic_write_text
from trainer.run_input import (check_logs, check_settings_section, load_json_object,  # noqa: F401 - for the CLIs
                               load_yaml_mapping)

MetricsCallback = Callable[[int, Mapping[str, float]], None]

CHECKPOINT_NAME = "latest.pt"


# ----------------------------------------------------------------------------- run dirs
def default_run_dir(kind: str, task: str, variant: str) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{kind}-{task}-{variant}-{stamp}"


def checkpoint_path(run_dir: Path) -> Path:
    return Path(run_dir) / "checkpoints" / CHECKPOINT_NAME


def resume_run_dir(run_dir: str | os.PathLike | None, *, need_checkpoint: bool = True,
                   need_state: bool = True) -> tuple[Path, dict[str, Any]]:
    """The run directory `--resume` continues and its run.json (ValueError saying what is
    missing, rather than a traceback half-way through start-up)."""
    if not run_dir:
        raise ValueError("--resume needs --run-dir")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ValueError(f"--resume: {run_dir} is not a directory")
    if need_checkpoint and not checkpoint_path(run_dir).exists():
        raise ValueError(f"--resume: no checkpoint at {checkpoint_path(run_dir)}")
    state = run_dir / "run.json"
    if not state.exists():
        if need_state:
            raise ValueError(f"--resume: {state} is missing (not a run directory of this command?)")
        return run_dir, {}
    try:   # type, size and depth checked (trainer/run_input.py): a run.json is input
        return run_dir, load_json_object(state)
    except ValueError as e:
        raise ValueError(f"--resume: {e}") from None


def load_run_config(run_dir: str | os.PathLike):
    """RUN_DIR/config.yaml as a Config, or one ValueError line naming the file (not YAML, an
    unsafe tag, nested too deep, not a mapping, not a config)."""
    from protocad_ros.model.config import Config

    path = Path(run_dir) / "config.yaml"
    try:
        return Config.from_dict(load_yaml_mapping(path))
    except ValueError as exc:   # ConfigError is one
        text = str(exc)
        raise ValueError(f"--resume: {text if text.startswith(str(path)) else f'{path}: {text}'}") from None


def new_run_dir(run_dir: str | os.PathLike | None, kind: str, task: str, variant: str) -> Path:
    """The directory of a fresh run (default runs/KIND-TASK-VARIANT-STAMP); refuses one that
    already holds a run, so nothing is overwritten."""
    run_dir = Path(run_dir) if run_dir else default_run_dir(kind, task, variant)
    if checkpoint_path(run_dir).exists() or (run_dir / "bags").exists():
        raise ValueError(f"{run_dir} already holds a run: pass --resume to continue it, or "
                         "choose another --run-dir")
    return run_dir


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


# ----------------------------------------------------------------------------- config
def parse_set(items: Iterable[str] | None) -> dict[str, Any]:
    """`--set a.b=1 --set c=[1,2]` -> {'a.b': 1, 'c': [1, 2]} (values parsed as YAML)."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set expects KEY=VALUE (e.g. train.batch_size=8), got {item!r}")
        out[key.strip()] = yaml.safe_load(value) if value.strip() else ""
    return out


def flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def build_config(task: str | None = None, variant: str | None = None, preset: str | None = None,
                 config_file: str | Path | None = None, overrides: Mapping[str, Any] | None = None):
    """Config from (in increasing priority): preset defaults for task/variant, a YAML file
    (full Config.save() output or a partial nested mapping), `--set` overrides.

    Returns a protocad_ros.model.config.Config.
    """
    from protocad_ros.model.config import DEFAULT_CLI_PRESET, apply_overrides, make_config

    file_dict: dict[str, Any] = {}
    if config_file:
        try:
            text = Path(config_file).read_text()
        except OSError as exc:   # missing, a directory, unreadable
            raise ValueError(f"--config {config_file}: {exc.strerror or exc}") from None
        try:
            loaded = yaml.safe_load(text) or {}
        except yaml.YAMLError as exc:
            where = getattr(exc, "problem_mark", None)
            line = f" (line {where.line + 1}, column {where.column + 1})" if where else ""
            raise ValueError(f"--config {config_file}: not valid YAML{line}: "
                             f"{getattr(exc, 'problem', None) or exc}") from None
        if not isinstance(loaded, dict):
            raise ValueError(f"{config_file}: expected a YAML mapping at the top level")
        file_dict = loaded
    # task / variant / preset: flag > file > default
    task = task or file_dict.get("task") or "pendulum_swingup"
    variant = variant or file_dict.get("variant") or "protocad"
    preset = preset or file_dict.get("preset") or DEFAULT_CLI_PRESET
    settings = {k: v for k, v in flatten(file_dict).items() if k not in ("task", "variant", "preset")}
    settings.update(overrides or {})
    # own_settings and reference choose defaults of other fields, so they go to make_config first
    selectors = {k: settings[k] for k in SELECTOR_FIELDS if k in settings}
    cfg = make_config(task=task, preset=preset, variant=variant, **selectors)
    return apply_overrides(cfg, settings)   # ConfigError is a ValueError: one line in the CLIs


#: Config fields that choose the defaults of others (make_config applies their settings first).
SELECTOR_FIELDS = ("own_settings", "reference")

#: Config fields with flags of their own (--task, --variant, --preset: they pick the defaults
#: of every other field), so not among the generated options.
OWN_FLAG_FIELDS = ("task", "variant", "preset")
OWN_SETTINGS_HELP = ("a baseline with the settings it was published with (msgs_docs/training.md, Variants); "
                     "false: ProtoCAD's settings for every variant")


def _config_options_class(cfg: Any) -> type:
    """A dataclass of cfg's sections and settings (not OWN_FLAG_FIELDS), defaults = cfg's values."""
    import copy
    import dataclasses
    import typing

    import tyro

    hints = typing.get_type_hints(type(cfg))
    # A field of the class made here has no comment for tyro to read: the one setting gets its help.
    hints["own_settings"] = typing.Annotated[hints["own_settings"], tyro.conf.arg(help=OWN_SETTINGS_HELP)]  # noqa: F821 - a subscript, not a forward reference
    return dataclasses.make_dataclass("config", [
        (f.name, hints[f.name], dataclasses.field(default_factory=lambda v=getattr(cfg, f.name): copy.deepcopy(v)))
        for f in dataclasses.fields(cfg) if f.name not in OWN_FLAG_FIELDS])


def apply_config_flags(cfg: Any, args: Sequence[str], prog: str) -> Any:
    """cfg with the config options in `args` applied: one option per field of the config tree
    (`--train.batch_size 8`, `--world_model.gru_norm` / `--world_model.no_gru_norm`), generated
    from protocad_ros.model.config by tyro, with the field's comment as help and cfg's value as the
    default shown. `--help` among them prints them and exits; an unknown one exits 2."""
    import dataclasses

    import tyro

    options = _config_options_class(cfg)
    parsed = tyro.cli(options, args=list(args), prog=prog, use_underscores=True,
                      description="Config options (protocad_ros.model.config; defaults: the chosen "
                                  "--task / --variant / --preset, --config file and --set overrides).")
    cfg = dataclasses.replace(cfg, **{f.name: getattr(parsed, f.name) for f in dataclasses.fields(parsed)})
    cfg.validate()
    return cfg


def read_run_json(run_dir: str | os.PathLike) -> dict[str, Any]:
    """RUN_DIR/run.json, or {} when there is none or it is unreadable."""
    try:
        return load_json_object(Path(run_dir) / "run.json")
    except ValueError:   # missing, unreadable, not an object, too deep or too large
        return {}


def record_invocation(run_json: dict[str, Any], resume: bool, args: Sequence[str]) -> None:
    """run.json keeps the command that started the run (`argv`, `args`) and appends each
    resume's (`resumes_argv`), instead of the resume overwriting the original."""
    if resume and "argv" in run_json:
        run_json.setdefault("resumes_argv", []).append(list(sys.argv))
    else:
        run_json.update(argv=list(sys.argv), args=list(args))


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows '(default: X)' unless the help already says what the default is or there is none;
    a description or epilog written in lines keeps its lines."""

    def _fill_text(self, text, width, indent):
        if "\n" in text:
            return "\n".join(indent + line for line in text.splitlines())
        return super()._fill_text(text, width, indent)

    def _get_help_string(self, action):
        h = action.help or ""
        d = action.default
        if "default" in h or d is None or d is False or d is argparse.SUPPRESS or (isinstance(d, list) and not d):
            return h
        return super()._get_help_string(action)


# ----------------------------------------------------------------------------- seeding/device
def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    try:
        import torch

        torch.manual_seed(seed)
    except ImportError:  # pragma: no cover
        pass


def resolve_device(name: str | None) -> str:
    """'cpu' (default), 'cuda', 'cuda:N' or 'auto' (cuda when available)."""
    import torch

    name = (name or "cpu").lower()
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit(f"--device {name}: CUDA is not available on this machine (use cpu or auto)")
    if name != "cpu" and not name.startswith("cuda"):
        raise SystemExit(f"--device {name!r}: expected cpu, cuda, cuda:N or auto")
    return name


THREADS_HELP = ("torch intra-op threads (default 0 = auto: one per core, shared among torchrun's ranks "
                "on this machine; give 1 to runs that compute side by side)")


_TORCH_DEFAULT_THREADS: int | None = None


def retain_freed_memory() -> bool:
    """Keep memory that torch frees inside this process for its next allocation (glibc only).

    glibc hands every block of 128 KiB or more straight back to the kernel (mmap / munmap) and
    trims the heap top as soon as it is free, so each update's large activations (a 16 x 50
    batch of 64x64 images is 39 MB per float32 copy) are paid again as fresh zeroed pages:
    page faults, measured at 8-20% of a CPU update (more with two runs on the cores). Raising
    the mmap threshold to glibc's largest (32 MiB) and never trimming keeps them in the heap;
    the process holds its peak memory instead of returning it between updates. Returns
    whether glibc took both settings (False elsewhere: nothing changes)."""
    import ctypes

    m_trim_threshold, m_mmap_threshold = -1, -3   # <malloc.h>
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(m_mmap_threshold, 32 << 20) and mallopt(m_trim_threshold, 2**31 - 1))


def setup_torch(n: int | None) -> int:
    """This process's CPU runtime for training: the allocator (retain_freed_memory) and torch's
    intra-op threads: n > 0 as given; 0/None = auto: one per core (torch's default),
    shared out among the ranks torchrun started on this machine (LOCAL_WORLD_SIZE). The CLIs
    compute in turn with their envs and nodes, never beside them (collect, then update; a
    lock-step loop; the loop's nodes wait while it trains), so each has the cores while it
    computes; jobs that do run side by side (protocad-compare's) are given --threads. Returns
    the number of threads in use."""
    import torch

    global _TORCH_DEFAULT_THREADS
    retain_freed_memory()
    if _TORCH_DEFAULT_THREADS is None:   # before anything set it: torch's own, one per core
        _TORCH_DEFAULT_THREADS = torch.get_num_threads()
    if n:
        torch.set_num_threads(int(n))
    else:
        ranks = max(1, int(os.environ.get("LOCAL_WORLD_SIZE", "1")))
        torch.set_num_threads(max(1, _TORCH_DEFAULT_THREADS // ranks))
    return torch.get_num_threads()


# ----------------------------------------------------------------------------- metrics
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
            self._f.write(json.dumps(row, default=_json_default) + "\n")
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


# ----------------------------------------------------------------------------- progress
def progress(total: int | None, initial: int = 0, desc: str = "", disable: bool | None = None, unit: str = "it"):
    """A tqdm bar (to stderr; disabled automatically when stderr is not a terminal unless
    PROTOCAD_PROGRESS=1)."""
    from tqdm.auto import tqdm

    if disable is None:
        disable = not (sys.stderr.isatty() or os.environ.get("PROTOCAD_PROGRESS") == "1")
    return tqdm(total=total, initial=initial, desc=desc, disable=disable, unit=unit,
                dynamic_ncols=True, smoothing=0.05)


# ----------------------------------------------------------------------------- interrupts
@dataclass
class StopFlag:
    """Ctrl-C / SIGTERM turn into a flag the training loop checks between updates; a second
    Ctrl-C exits (130) without a traceback."""

    stop: bool = False
    signum: int | None = None
    _old: dict = field(default_factory=dict)

    def __enter__(self) -> "StopFlag":
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._old[sig] = signal.signal(sig, self._handler)
            except ValueError:  # not the main thread
                pass
        return self

    def _handler(self, signum, frame):
        if self.stop and signum == signal.SIGINT:
            # A second Ctrl-C: leave now, without a traceback. The clean-up of `finally` blocks
            # still runs (bags closed); checkpoints and run.json are written atomically, so
            # what is on disk stays valid either way.
            print("\n[protocad] SIGINT again: aborting", file=sys.stderr, flush=True)
            raise SystemExit(130)
        self.stop, self.signum = True, signum
        print(f"\n[protocad] {signal.Signals(signum).name}: stopping: finishing the current step, "
              "saving, exiting (press Ctrl-C again to abort)", file=sys.stderr, flush=True)

    def __exit__(self, *exc) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def _number(text: str, kind: type, ok, what: str):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not ok(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """argparse type: an int >= 1."""
    return _number(text, int, lambda v: v >= 1, "a positive integer")


def non_negative_int(text: str) -> int:
    """argparse type: an int >= 0."""
    return _number(text, int, lambda v: v >= 0, "an integer >= 0")


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    return _number(text, float, lambda v: 0 < v < float("inf"), "a number > 0")


def parse_duration(text: str | float) -> float:
    """'5400', '90m', '1h30m', '45s', '2h' -> seconds (argparse type; ValueError otherwise)."""
    import re

    t = str(text).strip().lower()
    try:
        return float(t)
    except ValueError:
        pass
    m = re.fullmatch(r"(?:(\d+(?:\.\d+)?)h)?(?:(\d+(?:\.\d+)?)m)?(?:(\d+(?:\.\d+)?)s)?", t)
    if not t or not m or not any(m.groups()):
        raise argparse.ArgumentTypeError(f"expected a duration like 5400, 90m, 1h30m or 45s, got {text!r}")
    h, mi, se = (float(g) if g else 0.0 for g in m.groups())
    return h * 3600 + mi * 60 + se


def format_duration(seconds: float) -> str:
    """Seconds as parse_duration reads them back: 45s, 12m, 3h10m."""
    seconds = max(0, int(round(seconds)))
    if seconds < 60:
        return f"{seconds}s"
    h, m = divmod(seconds // 60, 60)
    return f"{h}h{m:02d}m" if h else f"{m}m"


def torch_threads() -> int:
    import torch

    return torch.get_num_threads()


def fmt_seconds(s: float) -> str:
    s = int(round(s))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}h{m:02d}m{sec:02d}s" if h else (f"{m}m{sec:02d}s" if m else f"{sec}s")


def wait_until(ready: Callable[[], bool], *, what: str, timeout: float,
               alive: Callable[[], str | None] = lambda: None, stop=None,
               pause: Callable[[], None] = lambda: time.sleep(0.05)) -> bool:
    """Poll `ready()` (calling `pause()` in between) until it is true; TimeoutError naming
    `what`; RuntimeError at once with what `alive()` says when the process watched is gone;
    False when `stop.stop` (a runs.StopFlag) is raised."""
    deadline = time.monotonic() + timeout
    while True:
        if ready():
            return True
        if stop is not None and stop.stop:
            return False
        gone = alive()
        if gone:
            raise RuntimeError(gone)
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} within {timeout:.0f}s")
        pause()
