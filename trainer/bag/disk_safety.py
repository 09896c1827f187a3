"""What keeps a bag valid when the disk fills or a file is removed mid-way: an unbuffered file
whose every record is written whole or raises, a reserve of free space kept beside the bag, and
the cut that ends a failed file at its last complete chunk and index (DataEnd + a footer without
summary: valid MCAP, which readers scan)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

from trainer.bag.bag_info import FileInfo, TopicInfo

RESERVE_BYTES = 64 * 1024   # kept free beside the bag, to close it validly on a full disk
_DATA_END = b"\x0f" + (4).to_bytes(8, "little") + (0).to_bytes(4, "little")
_FOOTER = b"\x02" + (20).to_bytes(8, "little") + bytes(20) + b"\x89MCAP0\r\n"


class CheckedFile:
    """An unbuffered file for the mcap Writer that never writes a record half-way silently:
    a short write is retried until complete or an OSError, and `good` is the end of the last
    complete write (the mcap Writer writes each chunk, index and summary record in one call)."""

    def __init__(self, path: Path):
        self._f = open(path, "xb", buffering=0)
        self.good = 0

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        done = 0
        while done < len(view):
            n = self._f.write(view[done:])
            if not n:
                raise OSError(28, "No space left on device (short write)")
            done += n
        self.good = self._f.tell()
        return done

    def tell(self) -> int:
        return self._f.tell()

    def flush(self) -> None:
        pass

    def fileno(self) -> int:
        return self._f.fileno()

    def close(self) -> None:
        self._f.close()

    @property
    def closed(self) -> bool:
        return self._f.closed


def make_reserve(path: Path, notes: list[str]) -> None:
    """RESERVE_BYTES written and synced at `path`, freed when the bag must close on a full disk
    (a note says why there is none)."""
    try:
        with open(path, "wb") as f:
            f.write(bytes(RESERVE_BYTES))
            f.flush()
            os.fsync(f.fileno())
    except OSError as exc:
        path.unlink(missing_ok=True)
        notes.append(f"no space reserve ({exc})")


def drop_reserve(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass


def end_file_at(stream: CheckedFile, cut: int, name: str) -> str:
    """Cut a failed file back to `cut` bytes and end it with DataEnd + footer; closes it and
    returns the note that says what was done."""
    try:
        fd = stream.fileno()
        os.ftruncate(fd, cut)
        os.lseek(fd, cut, os.SEEK_SET)
        os.write(fd, _DATA_END + _FOOTER)
        os.fsync(fd)
        return f"{name} cut back to its last complete chunk and index ({cut} bytes) and ended without a summary"
    except OSError as exc:
        return f"{name} could not be ended ({exc}): readers recover its complete chunks"
    finally:
        try:
            stream.close()
        except OSError:
            pass


class FailureRecovery:
    """A BagWriter's bookkeeping for a failed write, owned by it: the reserve of free space beside
    the bag, what is on disk (the counts taken after every committed chunk, and the end of the
    file they describe), and the salvage that cuts the failed file back to them. Handed, when
    built, the writer's bag directory, its topic and file records (the same dict and list the
    writer fills: the counts are theirs) and its salvage_notes (where the reserve and the
    salvage say what they did)."""

    def __init__(self, *, bag_dir: Path, topics: Mapping[str, TopicInfo], files: list[FileInfo],
                 notes: list[str]):
        self._bag_dir, self._topics, self._files, self._notes = bag_dir, topics, files, notes
        self.reserve = bag_dir / ".protocad-reserve"
        #: (messages, {topic: messages}, messages in the current file, end of that file).
        self._committed: tuple[int, dict[str, int], int, int] = (0, {}, 0, 0)
        make_reserve(self.reserve, notes)

    def drop_reserve(self) -> None:
        drop_reserve(self.reserve)

    def commit(self, stream: CheckedFile, count: int) -> None:
        """Remember the counts of what is on disk (`count` messages in all): a failure loses
        only the open chunk. A bag file deleted while recording takes writes without an error
        (its inode lives on), so that is checked here too and treated as a write failure."""
        if self._files and os.fstat(stream.fileno()).st_nlink == 0:
            raise OSError(2, f"{self._bag_dir / self._files[-1].path} was removed while recording")
        self.snapshot(stream, count)

    def snapshot(self, stream: CheckedFile, count: int) -> None:
        """The counts, and the end of the file they describe. A failure cuts the file back to
        that end, not to its last complete write: a chunk can be on disk with its message index
        refused (a disk that fills between the two), and the counts never included it."""
        self._committed = (count, {n: t.message_count for n, t in self._topics.items()},
                           self._files[-1].message_count, stream.good)

    def salvage(self, stream: CheckedFile | None) -> int:
        """After a failure: the reserve is freed, the topic and file counts go back to what the
        file holds (the rest is lost), and the open file is cut back to them and ended.
        Returns the number of messages the bag holds."""
        drop_reserve(self.reserve)
        total, per_topic, in_file, cut = self._committed
        for n, t in self._topics.items():
            t.message_count = per_topic.get(n, 0)
        self._files[-1].message_count = in_file
        if stream is not None and not stream.closed:
            self._notes.append(end_file_at(stream, cut, self._files[-1].path))
        return total
