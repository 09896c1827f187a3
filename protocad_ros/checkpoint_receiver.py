"""The policy node's side of checkpoints over ROS (msgs_docs/policy.md#checkpoints-over-ros).

`CheckpointReceiver` subscribes to a checkpoint publisher's announcement (`<topic>`) and chunks
(`<topic>/chunks`) and collects the chunks of the newest announced version in the executor
thread (cheap: bytes into a dict). When a version's chunks are all there it wakes the node's
checkpoint thread, which calls `install_received`: the version is verified (`Transfer.verify`:
size, sha256) and installed (`install`: written beside the node's own checkpoint file, loaded
from there with the node's file-reload code, and only then moved over that file), so the file
the node serves from is always a whole, loadable checkpoint and a restart serves it again.
A version that fails is rejected with one error line (which version, why) and counted.
"""
from __future__ import annotations

import hashlib
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from std_msgs.msg import String, UInt8MultiArray

from protocad_ros.atomic import atomic_open, file_signature, fsync_dir
from sim_bridge import qos, topics


class TransferRejected(Exception):
    """A received version that must not serve; the message says why (one log line)."""


@dataclass
class Transfer:
    announcement: topics.CheckpointAnnouncement
    chunks: dict[int, bytes]

    def verify(self) -> bytes:
        """The checkpoint's bytes, after the checks a faulty link or sender can fail."""
        a = self.announcement
        missing = [i for i in range(a.n_chunks) if i not in self.chunks]
        if missing:
            raise TransferRejected(f"incomplete: chunk(s) {missing[:5]} of {a.n_chunks} missing")
        data = b"".join(self.chunks[i] for i in range(a.n_chunks))
        if len(data) != a.size:
            raise TransferRejected(f"size mismatch: {len(data)} bytes received in {a.n_chunks} "
                                   f"chunk(s), {a.size} announced")
        digest = hashlib.sha256(data).hexdigest()
        if digest != a.sha256:
            raise TransferRejected(f"checksum mismatch: the {len(data)} bytes received have sha256 "
                                   f"{digest[:12]}..., {a.short_id}... announced")
        return data


def install(data: bytes, path: str | os.PathLike, load: Callable[[str], Any]) -> Any:
    """Write `data` atomically to a staging file beside `path`, `load(staging)` it, then move
    it over `path` (so the file keeps the (mtime, inode, size) signature the load saw).
    Returns what `load` returned; a load that fails is TransferRejected('not a checkpoint')."""
    path = Path(path)
    # Named like atomic_open's temporaries (.NAME.PID.*.tmp): remove_stale_temporaries(path)
    # clears what a killed install left, and two processes never share one.
    staging = path.with_name(f".{path.name}.{os.getpid()}.received.tmp")
    with atomic_open(staging, "wb") as f:
        f.write(data)
    try:
        loaded = load(str(staging))
    except Exception as e:  # noqa: BLE001 (CheckpointError, a config that does not fit)
        staging.unlink(missing_ok=True)
        raise TransferRejected(f"not a usable checkpoint: {e}".replace(str(staging), "the received file")) from None
    os.replace(staging, path)
    fsync_dir(path.parent)
    return loaded


class CheckpointReceiver:
    """Subscriptions of one node to one checkpoint topic; see the module docstring.

    wake(): a version arrived whole (executor thread); the node's checkpoint thread then calls
    install_received. next_sha(): the version the node serves from its next episode on (not
    fetched again). serving(): what the node serves, for the rejection line. count(key, why):
    the node's counters (ACCEPTED, REJECTED), `why` a throttled warning.
    """

    ACCEPTED, REJECTED = "checkpoint_transfers", "checkpoint_transfers_rejected"

    def __init__(self, node, topic: str, *, timeout_s: float, wake: Callable[[], None],
                 next_sha: Callable[[], str | None], serving: Callable[[], str],
                 count: Callable[..., None]):
        self.node, self.timeout_s = node, timeout_s
        self._wake, self._next_sha, self._serving, self._count = wake, next_sha, serving, count
        self._lock = threading.Lock()
        self._received: Transfer | None = None   # whole, for install_received
        self.announced: topics.CheckpointAnnouncement | None = None
        self.last_announced = ""   # sha256 of the newest announcement heard (for diagnostics)
        self._progress_at = 0.0   # announcement or last new chunk of the announced version
        self._parts: dict[str, dict[int, bytes]] = {}
        self.sub_announce = node.create_subscription(String, topic, self._on_announcement,
                                                     qos.announcement_qos())
        self.topic = self.sub_announce.topic_name
        self.sub_chunks = node.create_subscription(UInt8MultiArray, topics.chunks_topic(self.topic),
                                                   self._on_chunk, qos.checkpoint_chunks_qos())
        self.timer = node.create_timer(min(1.0, max(timeout_s / 4, 0.05)), self._check_timeout)

    def destroy(self) -> None:
        self.node.destroy_subscription(self.sub_announce)
        self.node.destroy_subscription(self.sub_chunks)
        self.node.destroy_timer(self.timer)
        self._parts.clear()

    def _is_current(self, sha: str) -> bool:
        with self._lock:
            received = self._received
        return sha == (received.announcement.sha256 if received is not None else self._next_sha())

    def install_received(self, path: str, load: Callable[[str], Any]):
        """Checkpoint thread: verify and install the version that arrived whole, if any.
        Returns (*load(file), signature, sha256, what) for the node's hand-over, or None (none
        arrived, or it was rejected and said why)."""
        with self._lock:
            transfer, self._received = self._received, None
        if transfer is None:
            return None
        a = transfer.announcement
        try:
            policy, counters = install(transfer.verify(), path, load)
        except TransferRejected as e:
            self._on_reject(a, str(e))
            return None
        except Exception as e:  # noqa: BLE001 (a full disk, a bug): still one line, never the thread
            self._on_reject(a, f"could not install it: {type(e).__name__}: {e}")
            return None
        self._count(self.ACCEPTED)
        return (policy, counters, file_signature(path), a.sha256,
                f"version {a.short_id} from {self.topic} into {path}")

    def _on_reject(self, a: topics.CheckpointAnnouncement | None, reason: str) -> None:
        if a is None:   # a malformed message, not a version: a flood of them is throttled
            return self._count(self.REJECTED, f"{self.topic}: {reason}")
        self._count(self.REJECTED)
        self.node.get_logger().error(f"checkpoint version {a.short_id} (updates={a.updates}) from "
                                     f"{self.topic} rejected: {reason}; still serving {self._serving()}")

    def progress(self) -> str:
        """'' when idle, else e.g. '3fa9c2d1e4b0 12/50' (for diagnostics)."""
        a = self.announced   # read from any thread: len() of the dict, no iteration over it
        return f"{a.short_id} {min(len(self._parts.get(a.sha256, {})), a.n_chunks)}/{a.n_chunks}" if a else ""

    def _on_announcement(self, msg) -> None:
        try:
            ann = topics.read_checkpoint_announcement(msg.data)
        except ValueError as e:
            return self._on_reject(None, f"malformed announcement: {e}")
        self.last_announced = ann.sha256
        # The newest announcement wins, also over a version still coming in.
        if self.announced is not None and self.announced.sha256 != ann.sha256:
            self.node.get_logger().info(f"checkpoint version {self.announced.short_id} superseded by "
                                        f"{ann.short_id} before it arrived whole")
        for sha in [s for s in self._parts if s != ann.sha256]:
            del self._parts[sha]
        if self._is_current(ann.sha256):
            self.announced = None
            self._parts.pop(ann.sha256, None)
            return self.node.get_logger().info(f"checkpoint version {ann.short_id} announced on "
                                               f"{self.topic}: already serving it")
        self.announced, self._progress_at = ann, time.monotonic()
        self.node.get_logger().info(f"checkpoint version {ann.short_id} announced on {self.topic} "
                                    f"(updates={ann.updates}, {ann.size} bytes in {ann.n_chunks} chunk(s))")
        self._complete_if_whole()

    def _on_chunk(self, msg) -> None:
        try:
            sha, index, n, data = topics.read_checkpoint_chunk(msg)
        except ValueError as e:
            return self._on_reject(None, f"malformed chunk: {e}")
        a = self.announced
        if a is None or sha != a.sha256:
            if self._is_current(sha):
                return
            # Unannounced: it may have beaten its announcement (another topic, another writer).
            # Only the newest such version is kept, so memory stays at two checkpoints at most.
            for other in [s for s in self._parts if s != sha and (a is None or s != a.sha256)]:
                del self._parts[other]
        elif n != a.n_chunks:
            return self._reject(f"incomplete: chunk {index} says the version has {n} chunk(s), "
                                f"{a.n_chunks} announced")
        parts = self._parts.setdefault(sha, {})
        if a is not None and sha == a.sha256 and index not in parts:
            self._progress_at = time.monotonic()
        parts[index] = data
        self._complete_if_whole()

    def _complete_if_whole(self) -> None:
        a = self.announced
        parts = self._parts.get(a.sha256) if a else None
        # Indices beyond n_chunks (a chunk that disagreed with the announcement) do not count.
        if parts is None or len(parts) < a.n_chunks or any(i not in parts for i in range(a.n_chunks)):
            return
        self.announced = None
        del self._parts[a.sha256]
        with self._lock:
            self._received = Transfer(a, parts)   # a newer one replaces one not yet installed
        self._wake()

    def _reject(self, reason: str) -> None:
        a, self.announced = self.announced, None
        self._parts.pop(a.sha256, None)
        self._on_reject(a, reason)

    def _check_timeout(self) -> None:
        a = self.announced
        # Silence, not total time: a slow link that keeps delivering is waited for.
        if a is not None and time.monotonic() - self._progress_at > self.timeout_s:
            got = len(self._parts.get(a.sha256, {}))
            self._reject(f"incomplete: {got} of {a.n_chunks} chunk(s) arrived, none for "
                         f"{self.timeout_s:g} s")
