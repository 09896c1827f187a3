"""The policy node's side of checkpoints over ROS (msgs_docs/policy.md#checkpoints-over-ros).

`CheckpointReceiver` subscribes to a checkpoint publisher's announcement (`<topic>`) and chunks
(`<topic>/chunks`). An announcement is checked first (`_refusal`: sizes within this node's
limits, with `trusted` keys its Ed25519 signature and a sequence number above the served one,
and the task and variant this node serves); only then are chunks of that version buffered, each
one checked on arrival (index, length and, when announced, its sha256: a bad chunk is dropped
alone, so a stranger's chunk cannot spoil a version). Chunks of any other version are dropped
unbuffered; when some of them may have been the announced version's (they beat the
announcement: two topics, two writers), the chunk subscription is created anew, and the
publisher's transient-local history brings them again.

When a version's chunks are all there it wakes the node's checkpoint thread, which calls
`install_received`: the version is verified (`Transfer.verify`: size, sha256) and installed
(`install`: loaded from the very bytes that were verified, with the node's file-reload code,
then written beside the node's own checkpoint file and moved over it, with its signature as
FILE.sig), so the file the node serves from is always a whole, loadable checkpoint and a restart
serves it again. A version that fails is rejected and counted; its error line is rate-limited
(protocad_ros/node/refusal_log.py: one line per cause per interval, with a count).
"""
from __future__ import annotations

import hashlib
import os
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from std_msgs.msg import String, UInt8MultiArray

from protocad_ros.atomic import atomic_open, fsync_dir
from protocad_ros.checkpoint.files import CheckpointMismatch
from protocad_ros.checkpoint.signing import (
    Manifest,
    SignatureRejected,
    TrustedKeys,
    signature_path,
    verify_manifest,
    write_signature_file,
)
from protocad_ros.node.refusal_log import RefusalLog
from sim_bridge.contract import qos, topics

#: max_checkpoint_bytes' default: 3x a paper-preset checkpoint with its optimizer states.
DEFAULT_MAX_BYTES = 512 << 20
#: Version ids, key ids, sizes: what varies between refusals of one cause (refusal_cause).
_VARYING = re.compile(r"[0-9a-f]{6,}|\d+")


def refusal_cause(counter: str | None, reason: str) -> str:
    """The rate-limiting key of a refusal: its counter and the start of its reason, with the
    numbers and ids that a flood would vary taken out."""
    return f"{counter or CheckpointReceiver.REJECTED}: {_VARYING.sub('#', reason)[:24]}"


class TransferRejected(Exception):
    """A received version that must not serve; the message says why (one log line), `counter`
    the node's counter for its kind (besides checkpoint_transfers_rejected)."""

    def __init__(self, reason: str, counter: str | None = None):
        super().__init__(reason)
        self.counter = counter


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


def manifest_of(a: topics.CheckpointAnnouncement) -> Manifest:
    """What the learner signed for this announcement (protocad_ros.checkpoint.signing.Manifest)."""
    return Manifest(a.sha256, a.size, a.task, a.variant, a.preset, a.updates, a.seq, a.key_id,
                    a.chunk_size, tuple(a.chunk_sha256))


#: How a received version is named in load errors (it has no file of its own yet).
RECEIVED = "the received file"


def install(data: bytes, path: str | os.PathLike, load: Callable[[str, bytes], Any],
            before_replace: Callable[[], None] = lambda: None) -> Any:
    """`load(RECEIVED, data)`: the verified bytes themselves, never a file read back; then write
    them atomically to a staging file beside `path`, call `before_replace()` (e.g. write its
    signature beside `path`) and move it over `path`. Returns what `load` returned; a load that
    fails is TransferRejected('not a usable checkpoint'), and nothing is written."""
    path = Path(path)
    try:
        loaded = load(RECEIVED, data)
    except Exception as e:  # noqa: BLE001 (CheckpointError, a config that does not fit)
        if isinstance(e, CheckpointMismatch):
            raise TransferRejected(f"does not fit: {e}", CheckpointReceiver.MISMATCH) from None
        raise TransferRejected(f"not a usable checkpoint: {e}") from None
    # Named like atomic_open's temporaries (.NAME.PID.*.tmp): remove_stale_temporaries(path)
    # clears what a killed install left, and two processes never share one.
    staging = path.with_name(f".{path.name}.{os.getpid()}.received.tmp")
    with atomic_open(staging, "wb") as f:
        f.write(data)
    try:
        before_replace()
    except BaseException:
        staging.unlink(missing_ok=True)
        raise
    os.replace(staging, path)
    fsync_dir(path.parent)
    return loaded


def record_signature(path: str | os.PathLike, a: topics.CheckpointAnnouncement) -> None:
    """FILE.sig for the version about to be installed at `path` (a restarted node with trusted
    keys verifies it, and knows the sequence number it served); an unsigned version leaves
    none, so an old signature never vouches for new bytes. Written before the file is moved
    into place: a failure here leaves the old file and its signature as they were."""
    if a.signature:
        write_signature_file(path, manifest_of(a), a.signature)
    else:
        signature_path(path).unlink(missing_ok=True)


@dataclass(frozen=True)
class ReceiverSettings:
    """What a CheckpointReceiver is handed by its node: limits, trust and callbacks.

    wake(): a version arrived whole (executor thread); the node's checkpoint thread then calls
    install_received. next_sha(): the version the node serves from its next episode on (not
    fetched again). serving(): what the node serves, for the rejection line. count(key, why):
    the node's counters, `why` a throttled warning. trusted: key id -> public key; None accepts
    unsigned versions. newest_seq(): the sequence number of the newest version the node holds
    (served or about to be; -1 if none is signed). fits(announcement): why the announced
    task/variant does not fit what the node serves, or None. refusals: the node's rate-limited
    refusal lines (a log of the receiver's own when None).
    """

    timeout_s: float
    wake: Callable[[], None]
    next_sha: Callable[[], str | None]
    serving: Callable[[], str]
    count: Callable[..., None]
    max_bytes: int = DEFAULT_MAX_BYTES
    trusted: TrustedKeys | None = None
    newest_seq: Callable[[], int] = lambda: -1
    fits: Callable[[topics.CheckpointAnnouncement], str | None] = lambda a: None
    refusals: RefusalLog | None = None


class CheckpointReceiver:
    """Subscriptions of one node to one checkpoint topic, with its ReceiverSettings (the
    node's limits and callbacks); see the module docstring."""

    ACCEPTED, REJECTED = "checkpoint_transfers", "checkpoint_transfers_rejected"
    SIGNATURE, ROLLBACK = "checkpoint_signatures_rejected", "checkpoint_rollbacks_rejected"
    LIMITS, MISMATCH = "checkpoint_limits_rejected", "checkpoint_mismatches"
    DROPPED = "checkpoint_chunks_dropped"

    def __init__(self, node, topic: str, settings: ReceiverSettings):
        s = settings
        self.node, self.timeout_s, self.max_bytes, self.trusted = node, s.timeout_s, s.max_bytes, s.trusted
        self._wake, self._next_sha, self._serving, self._count = s.wake, s.next_sha, s.serving, s.count
        self._newest_seq, self._fits = s.newest_seq, s.fits
        self._lock = threading.Lock()
        self._received: Transfer | None = None   # whole, for install_received
        self.announced: topics.CheckpointAnnouncement | None = None   # verified, coming in
        self.last_announced = ""   # sha256 of the newest announcement accepted (for diagnostics)
        self._progress_at = 0.0   # announcement or last new chunk of the announced version
        self._parts: dict[int, bytes] = {}   # the announced version's chunks so far
        self._buffered = 0                   # their bytes
        self._refetch = False   # chunks of no announced version were dropped (maybe early ones)
        self.refusals = s.refusals or RefusalLog(node.get_logger().error)
        self.sub_announce = node.create_subscription(String, topic, self._on_announcement,
                                                     qos.announcement_qos())
        self.topic = self.sub_announce.topic_name
        self.sub_chunks = self._subscribe_chunks()
        self.timer = node.create_timer(min(1.0, max(s.timeout_s / 4, 0.05)), self._check_timeout)

    def _subscribe_chunks(self):
        return self.node.create_subscription(UInt8MultiArray, topics.chunks_topic(self.topic),
                                             self._on_chunk, qos.checkpoint_chunks_qos())

    def destroy(self) -> None:
        self.node.destroy_subscription(self.sub_announce)
        self.node.destroy_subscription(self.sub_chunks)
        self.node.destroy_timer(self.timer)
        self._forget_parts()
        self.refusals.flush(force=True)

    def buffered_bytes(self) -> int:
        """Bytes held for versions not installed yet: the one coming in plus one whole one."""
        with self._lock:
            received = self._received
        return self._buffered + (received.announcement.size if received is not None else 0)

    def _is_current(self, sha: str) -> bool:
        with self._lock:
            received = self._received
        return sha == (received.announcement.sha256 if received is not None else self._next_sha())

    def install_received(self, path: str, load: Callable[[str], Any]):
        """Checkpoint thread: verify and install the version that arrived whole, if any.
        Returns (*load(file), sha256, what, seq) for the node's hand-over, or None (none
        arrived, or it was rejected and said why)."""
        with self._lock:
            transfer, self._received = self._received, None
        if transfer is None:
            return None
        a = transfer.announcement
        try:
            policy, counters = install(transfer.verify(), path, load,
                                       before_replace=lambda: record_signature(path, a))
        except TransferRejected as e:
            self._on_reject(a, str(e), e.counter)
            return None
        except Exception as e:  # noqa: BLE001 (a full disk, a bug): still one line, never the thread
            self._on_reject(a, f"could not install it: {type(e).__name__}: {e}")
            return None
        self._count(self.ACCEPTED)
        return (policy, counters, a.sha256, f"version {a.short_id} from {self.topic} into {path}",
                a.seq if a.signature else -1)

    def _on_reject(self, a: topics.CheckpointAnnouncement | None, reason: str,
                   counter: str | None = None) -> None:
        if a is None:   # a malformed message, not a version: a flood of them is throttled
            return self._count(self.REJECTED, f"{self.topic}: {reason}")
        self._count(self.REJECTED)
        if counter is not None:
            self._count(counter)
        # One line per cause per interval: a flood of fresh version ids is counted, not logged.
        self.refusals.refuse(refusal_cause(counter, reason),
                             f"checkpoint version {a.short_id} (updates={a.updates}) from "
                             f"{self.topic} rejected: {reason}; still serving {self._serving()}")

    def progress(self) -> str:
        """'' when idle, else e.g. '3fa9c2d1e4b0 12/50' (for diagnostics)."""
        a = self.announced   # read from any thread: len() of the dict, no iteration over it
        return f"{a.short_id} {min(len(self._parts), a.n_chunks)}/{a.n_chunks}" if a else ""

    # ------------------------------------------------------------------ announcements
    def _limits(self, a: topics.CheckpointAnnouncement) -> str | None:
        if a.size > self.max_bytes:
            return f"too large: {a.size} bytes announced, max_checkpoint_bytes is {self.max_bytes}"
        if not topics.MIN_CHUNK_SIZE <= a.chunk_size <= topics.MAX_CHUNK_SIZE:
            return (f"chunk_size {a.chunk_size} outside the publisher's range "
                    f"[{topics.MIN_CHUNK_SIZE}, {topics.MAX_CHUNK_SIZE}]")
        if a.n_chunks > topics.MAX_CHUNKS:
            return f"{a.n_chunks} chunks, more than {topics.MAX_CHUNKS}"
        return None

    def _rollback_floor(self) -> int:
        """No version at or below this sequence number is taken: what the node holds, what
        waits for the checkpoint thread and what is coming in (a replayed older signed
        version must not push a newer one out)."""
        with self._lock:
            received = self._received
        held = [self._newest_seq()] + [a.seq for a in (received and received.announcement, self.announced)
                                       if a is not None and a.signature]
        return max(held)

    def _refusal(self, a: topics.CheckpointAnnouncement) -> tuple[str, str] | None:
        """(counter, reason) when the announced version must not be fetched, else None."""
        why = self._limits(a)
        if why:
            return self.LIMITS, why
        if self.trusted is not None:
            try:
                verify_manifest(manifest_of(a), a.signature, self.trusted)
            except SignatureRejected as e:
                return self.SIGNATURE, str(e)
            if not a.chunk_sha256:
                return self.SIGNATURE, "signed without per-chunk hashes"
        if self._is_current(a.sha256):
            return None
        if self.trusted is not None and a.seq <= (floor := self._rollback_floor()):
            return self.ROLLBACK, (f"rollback: sequence number {a.seq} is not above {floor}, the "
                                   "newest version this node holds (or min_checkpoint_seq - 1)")
        why = self._fits(a)
        return (self.MISMATCH, f"does not fit: {why}") if why else None

    def _on_announcement(self, msg) -> None:
        try:
            ann = topics.read_checkpoint_announcement(msg.data)
        except ValueError as e:
            return self._on_reject(None, f"malformed announcement: {e}")
        if self.announced is not None and ann.sha256 == self.announced.sha256:
            return   # heard again (a rediscovery): it is coming in already
        refused = self._refusal(ann)
        if refused is not None:
            # Nothing changes: a refused announcement never interrupts a version coming in.
            return self._on_reject(ann, refused[1], refused[0])
        if self._is_current(ann.sha256) and self._replayed(ann):
            return
        self.last_announced = ann.sha256
        # The newest accepted announcement wins, also over a version still coming in.
        if self.announced is not None:
            self.node.get_logger().info(f"checkpoint version {self.announced.short_id} superseded by "
                                        f"{ann.short_id} before it arrived whole")
        self._forget_parts()
        if self._is_current(ann.sha256):
            return self.node.get_logger().info(f"checkpoint version {ann.short_id} announced on "
                                               f"{self.topic}: already serving it")
        self.announced, self._progress_at = ann, time.monotonic()
        signed = f", signed by key {ann.key_id}, seq {ann.seq}" if self.trusted is not None else ""
        self.node.get_logger().info(f"checkpoint version {ann.short_id} announced on {self.topic} "
                                    f"(updates={ann.updates}, {ann.size} bytes in {ann.n_chunks} "
                                    f"chunk(s){signed})")
        if self._refetch:
            self._resubscribe()

    def _replayed(self, a: topics.CheckpointAnnouncement) -> bool:
        """The served version announced with a sequence number below the one coming in: an old
        signed announcement replayed, which must not stop a newer version (unsigned, the
        newest announcement wins)."""
        coming = self.announced
        return self.trusted is not None and coming is not None and a.seq <= coming.seq

    def _resubscribe(self) -> None:
        """A new reader gets the writers' transient-local history again: the announced
        version's chunks that arrived before its announcement and were dropped."""
        self._refetch = False
        old, self.sub_chunks = self.sub_chunks, self._subscribe_chunks()
        self.node.destroy_subscription(old)

    # ------------------------------------------------------------------ chunks
    def _drop(self, why: str | None = None) -> None:
        self._count(self.DROPPED, why)

    def _on_chunk(self, msg) -> None:
        try:
            sha, index, n = topics.read_checkpoint_chunk_label(msg)
        except ValueError as e:
            return self._drop(f"{self.topic} chunk dropped: malformed: {e}")
        a = self.announced
        if a is None or sha != a.sha256:
            # Not buffered: no announced version is coming in under this id. It may have beaten
            # its announcement, though: the next accepted one re-reads the history.
            self._refetch = self._refetch or not self._is_current(sha)
            return self._drop()
        where = f"{self.topic} chunk {index} of version {a.short_id} dropped"
        if n != a.n_chunks:
            return self._drop(f"{where}: it says the version has {n} chunk(s), {a.n_chunks} announced")
        if index in self._parts:
            return self._drop()   # a re-send, or a second writer: the first good one stays
        if len(msg.data) != a.chunk_length(index):
            return self._drop(f"{where}: {len(msg.data)} bytes, {a.chunk_length(index)} expected")
        data = bytes(msg.data)
        if a.chunk_sha256 and hashlib.sha256(data).hexdigest() != a.chunk_sha256[index]:
            return self._drop(f"{where}: its sha256 is not the announced one")
        self._parts[index] = data
        self._buffered += len(data)   # at most a.size: one chunk per index, each of its length
        self._progress_at = time.monotonic()
        self._complete_if_whole()

    def _complete_if_whole(self) -> None:
        a = self.announced
        if a is None or len(self._parts) < a.n_chunks:
            return
        parts = self._parts
        self.announced = None
        self._parts, self._buffered = {}, 0
        with self._lock:
            self._received = Transfer(a, parts)   # a newer one replaces one not yet installed
        self._wake()

    def _forget_parts(self) -> None:
        self.announced = None
        self._parts, self._buffered = {}, 0

    def _reject(self, reason: str) -> None:
        a = self.announced
        self._forget_parts()
        self._on_reject(a, reason)

    def _check_timeout(self) -> None:
        self.refusals.flush()
        a = self.announced
        # Silence, not total time: a slow link that keeps delivering is waited for.
        if a is not None and time.monotonic() - self._progress_at > self.timeout_s:
            self._reject(f"incomplete: {len(self._parts)} of {a.n_chunks} chunk(s) arrived, none "
                         f"for {self.timeout_s:g} s")
