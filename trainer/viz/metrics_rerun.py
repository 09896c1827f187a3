"""The training commands' `--rerun [RRD]` (protocad-train, -online, -loop): the MetricsLogger
callback writing the run's rerun recording. rerun itself (trainer/viz/rerun_log.py) loads only
when the option is given: training also runs on the GPU machine's bare Python, which has none."""
from __future__ import annotations

from pathlib import Path
from typing import Any


def metrics_callbacks(rerun: str | None, run_dir: Path, application: str) -> list[Any]:
    """What `--rerun [RRD]` asks for: nothing (None), or rerun_log's TrainingRecorder writing RRD
    (default RUN_DIR/metrics.rrd)."""
    if rerun is None:
        return []
    from trainer.viz.rerun_log import metrics_callback

    return [metrics_callback(rerun or Path(run_dir) / "metrics.rrd", application)]
