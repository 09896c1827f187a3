"""Atomic file writes: a reader sees the old file or the new one, never a partial one.

Used for checkpoints, their config.yaml and the trainer's run files, so that Ctrl-C, a kill
or a full disk in the middle of a write loses nothing that was there before.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from pathlib import Path
from typing import IO, Iterator


def fsync_dir(path: str | os.PathLike) -> None:
    """Make a rename in `path` durable (best effort: not every filesystem allows it)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside `path`; on a clean exit it is flushed, fsynced and renamed
    over `path` (os.replace is atomic within one filesystem); on an exception it is removed
    and `path` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The writer's pid in the name lets a later start tell an interrupted write's leftover
    # from a write in progress (remove_stale_temporaries).
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def file_signature(path: str | os.PathLike) -> tuple[int, int, int] | None:
    """(mtime, inode, size), None if there is no file: an atomic replace always changes it (a
    new inode), so a reader polling it sees each new version once, never a partial one."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_ino, st.st_size)


def file_sha256(path: str | os.PathLike) -> str:
    """sha256 of a file's bytes (hex): the version id of a checkpoint sent over ROS, and what
    an evaluation or a shipped policy names the file it measured by."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_open(path, "w") as f:
        f.write(text)


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Delete what interrupted atomic writes of `path` left beside it (`.NAME.PID.*.tmp` of a
    process that no longer runs); returns the removed files. A writer calls it when it starts."""
    path = Path(path)
    removed = []
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        pid_text = tmp.name[len(path.name) + 2:].split(".", 1)[0]
        if pid_text.isdigit() and int(pid_text) != os.getpid() and _alive(int(pid_text)):
            continue
        if pid_text.isdigit() and int(pid_text) == os.getpid():
            continue
        try:
            tmp.unlink()
            removed.append(tmp)
        except OSError:
            pass
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
