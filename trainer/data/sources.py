"""Where the dataset's bags are: the CLI's log paths expanded into bag directories and .mcap
files, searched within bounds (a folder that cannot be listed, or a walk deeper than
MAX_SEARCH_DEPTH, is one DatasetError line)."""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

from trainer.data.records import DatasetError


def find_sources(paths: Iterable[str | Path]) -> list[Path]:
    """Expand CLI paths into bags: a .mcap file, a directory with .mcap files in it (one bag),
    or a directory of such directories (searched recursively). Raises on paths with none."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise DatasetError(f"log path {p} does not exist")
        if p.is_file():
            if p.suffix != ".mcap":
                raise DatasetError(f"{p} is not an .mcap file (give a bag directory or .mcap files)")
            out.append(p)
            continue
        found = _bag_dirs(p)
        if not found:
            raise DatasetError(f"no .mcap files under {p}")
        out.extend(found)
    # unique, keep order
    seen, uniq = set(), []
    for s in out:
        r = s.resolve()
        if r not in seen:
            seen.add(r)
            uniq.append(s)
    return uniq


#: Deepest folder below a log path searched for bags (runs/*/bags/NAME is 3).
MAX_SEARCH_DEPTH = 8


def _bag_dirs(d: Path, depth: int = 0) -> list[Path]:
    """The bag directories under d: a folder the user cannot list (/proc's) or one deeper than
    MAX_SEARCH_DEPTH (a symlink loop) is one DatasetError line, not a traceback or a long walk."""
    try:
        entries = list(d.iterdir())
        if any(f.suffix == ".mcap" and f.is_file() for f in entries):
            return [d]
        subs = sorted(x for x in entries if x.is_dir() and not x.is_symlink() and not x.name.startswith("."))
    except OSError as exc:
        raise DatasetError(f"cannot search {d} for bags: {exc.strerror or exc}") from None
    if subs and depth >= MAX_SEARCH_DEPTH:
        raise DatasetError(f"{d}: folders nested more than {MAX_SEARCH_DEPTH} deep below the log path; "
                           "give the bag directories themselves")
    out: list[Path] = []
    for sub in subs:
        out.extend(_bag_dirs(sub, depth + 1))
    return out
