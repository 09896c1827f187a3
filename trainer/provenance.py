"""Which code a run trained with. `scripts/protocad setup` installs protocad-ros non-editable
(the ament layout needs data_files), so the checkout a command is started from may have moved on
from what is installed: setup.py records the commit it installs in trainer/build_info.json, and
runs name that one. Standard library only: setup.py loads this file before anything is installed.
"""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

BUILD_INFO = "build_info.json"


def git_commit(tree: Path) -> str:
    """HEAD of the checkout at `tree`, '+dirty' with uncommitted changes, 'unknown' outside git."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=tree, capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=tree,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return head.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def build_info() -> dict[str, str] | None:
    """What setup.py recorded when it installed this copy (`commit`, `source`: the checkout), or
    None when this code runs from its checkout."""
    try:
        info = json.loads((Path(__file__).resolve().parent / BUILD_INFO).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return info if isinstance(info, dict) else None


def code_version() -> str:
    """The commit of the code that runs: an installed copy's recorded one, else the checkout
    this file is in."""
    info = build_info()
    if info:
        return str(info.get("commit", "unknown"))
    return git_commit(Path(__file__).resolve().parents[1])


def stale_install() -> str | None:
    """A warning when the installed copy is not its checkout's current commit (a `git pull`
    without `scripts/protocad setup`): the runs would train and record the older code. Two
    uncommitted states of one commit look alike here; `scripts/protocad` re-installs on any
    change to the sources."""
    info = build_info()
    if not info or not Path(info.get("source", "")).is_dir():
        return None
    now = git_commit(Path(info["source"]))
    if now in ("unknown", info.get("commit")):
        return None
    return (f"the installed protocad-ros is commit {info.get('commit')} but its checkout {info['source']} "
            f"is at {now}: this runs the installed code; `scripts/protocad setup` installs the checkout's")
