"""Run directories: where a run keeps everything, created, found again and resumed; run.json.
The trainer CLIs' other shared parts live beside it: run_config.py (the config a CLI builds),
torch_setup.py, metrics_log.py, cli_values.py, console.py (progress, Ctrl-C). No ROS import.

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

import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from protocad_ros.atomic import atomic_write_text
from protocad_ros.checkpoint.files import CONFIG_NAME
from protocad_ros.model.config import Config
from trainer.run_input import load_json_object, load_yaml_mapping

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


def save_run_config(run_dir: str | os.PathLike, cfg, ran: str | None = None) -> Path:
    """RUN_DIR/config.yaml, the one place a run's config is written: when the run directory is
    made (the config as asked), and again by the trainer that opens it (with `ran`: the precision
    that ran on this machine, PrecisionChoice.ran_here()). Atomic (Config.save)."""
    path = Path(run_dir) / CONFIG_NAME
    cfg.save(path, ran=ran)
    return path


def load_run_config(run_dir: str | os.PathLike):
    """RUN_DIR/config.yaml as a Config, or one ValueError line naming the file (not YAML, an
    unsafe tag, nested too deep, not a mapping, not a config)."""
    path = Path(run_dir) / CONFIG_NAME
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
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=json_default) + "\n")


def json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


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



