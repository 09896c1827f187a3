"""`protocad-study`: the world-model study on fixed logs (issue 51). Does ProtoCAD's context
module stay alive, and does it make the world model predict unseen physics better than Dreamer's,
measured against a world model given the true context (the ceiling)? Only world models train
(no behaviour), all arms on the same bags with the same seeds, so seed noise is that of a world
model, not of a policy.

    protocad-study record --data DATA --seed 0           # the dataset (bags + dataset.json)
    protocad-study run --data DATA --grid GRID --arms dreamer,protocad_paper --seeds 0,1,2 \\
        --updates 500 [--shard 0/2]                      # train + evaluate; resumes where it stopped
    protocad-study report --grid GRID --json study.json  # the tables (markdown) and the JSON

record: the shipped walker policy with exploration noise on the 25 training contexts
(DATA/train), and the evaluation set: the shipped policy's mode on all 64 unseen and 25 training
contexts (DATA/eval). dataset.json names the command, the seed, the policy's sha256 and every
bag's. run: for every arm x seed, RUN = GRID/ARM/seed_S: a world model trained on DATA/train for
--updates updates (checkpoints every 100; a killed run resumes from its last), then evaluated on
DATA/eval into RUN/eval.json: open-loop image and reward error at each horizon 1..50 after 5
observed frames, per split; linear probes of log m and log d (protocad-probe's, on the same
windows); the context module's health (trainer.learn.context_health). report: per arm, the mean
over seeds with a 95% t-interval of each figure.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from trainer import settings, torch_setup
from trainer.settings import arg
from trainer.study.dataset import record
from trainer.study.grid import ARMS, plan_runs, run_grid
from trainer.study.report import write_report


@dataclass
class StudySettings:
    """What protocad-study does: record the dataset, run the arms, or report them."""

    mode: str = arg("report", "mode", nargs="?", choices=("record", "run", "report"))
    """record | run | report"""
    data: str = "study-data"
    """the dataset directory (record writes it; run reads DATA/train and DATA/eval)"""
    grid: str = "study-grid"
    """the runs' directory (GRID/ARM/seed_S)"""
    arms: str = "dreamer,protocad_paper,true_context"
    """comma-separated arms: """ + ", ".join(ARMS)
    seeds: str = "0,1,2,3,4"
    """comma-separated seeds"""
    updates: int = 500
    """world-model updates per run"""
    shard: str = "0/1"
    """I/N: run only the runs whose index is I modulo N (two processes on two cores: 0/2 and 1/2)"""
    seed: int = 0
    """record: seeds the policy's noise and the envs"""
    train_episodes: int = 2
    """record: episodes per training context"""
    noise: float = 0.3
    """record: exploration noise (std) on the shipped policy's actions in the training set"""
    eval_steps: int = 150
    """record: observations per evaluation episode (one per context)"""
    json: str | None = arg(None, metavar="FILE")
    """report: write the per-arm figures as JSON"""
    threads: int = arg(1, help=settings.THREADS_HELP)


def build_parser():
    return settings.settings_parser(
        "protocad-study", (__doc__ or "").split("\n\n")[0].replace("`protocad-study`: ", ""),
        [(None, StudySettings)])


def main(argv: Sequence[str] | None = None) -> int:
    parsed = settings.parse(build_parser(), argv, config_help=False)
    s = parsed.get(StudySettings)
    try:
        return run(s)
    except (ValueError, OSError) as exc:
        print(f"protocad-study: error: {exc}", file=sys.stderr)
        return 2


def run(s: StudySettings) -> int:
    """Do what `s.mode` says."""
    if s.mode == "report":
        write_report(Path(s.grid), Path(s.json) if s.json else None)
        return 0
    torch_setup.setup_torch(s.threads)
    if s.mode == "record":
        record(Path(s.data), s.seed, s.train_episodes, s.noise, s.eval_steps)
        return 0
    try:
        shard = tuple(int(x) for x in s.shard.split("/"))
        seeds = [int(x) for x in s.seeds.split(",") if x]
    except ValueError:
        raise ValueError(f"--shard {s.shard!r} must be I/N and --seeds {s.seeds!r} integers, comma-separated") from None
    if len(shard) != 2:
        raise ValueError(f"--shard {s.shard!r} must be I/N")
    run_grid(Path(s.data), Path(s.grid), plan_runs([a for a in s.arms.split(",") if a], seeds, shard), s.updates)
    return 0


if __name__ == "__main__":
    sys.exit(main())
