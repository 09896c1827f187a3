"""A policy node's rollback floor, kept apart from the checkpoint it serves
(msgs_docs/security.md#rollback).

With `trusted_keys` a node takes no signed version whose sequence number is not above the
newest one it holds. FILE.sig beside the served file says that number after a restart, but
whoever can write the checkpoint directory can delete FILE.sig (and FILE): the node would start
without a floor and take a captured older version. So the node also keeps the highest number it
ever held in a small state file of its own, by default beside the first trusted key (a
directory the checkpoint's writers need not reach), one file per served checkpoint path:

    learner.pub.served-3fa9c2d1e4b05a77.json   {"format": ..., "checkpoint": "/abs/agent.pt", "seq": N}

A node whose served file is signed below its floor refuses to start (the message names the
state file: restore the newer checkpoint, or delete the state file to accept the older one).
Free of ROS.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from protocad_ros.atomic import atomic_write_text

STATE_FORMAT = "protocad-ros/rollback-floor"


class RollbackStateError(RuntimeError):
    """A state file that cannot be read or written; says which and why."""


def default_state_path(trusted_key: str | os.PathLike, checkpoint: str | os.PathLike) -> Path:
    """Beside the trusted key: KEY.served-<16 hex of the checkpoint's absolute path>.json."""
    key = Path(trusted_key)
    tag = hashlib.sha256(str(Path(checkpoint).absolute()).encode()).hexdigest()[:16]
    return key.with_name(f"{key.name}.served-{tag}.json")


class RollbackFloor:
    """The highest sequence number held (-1: none yet), read from and raised in `path`."""

    def __init__(self, path: str | os.PathLike, checkpoint: str | os.PathLike):
        self.path, self.checkpoint = Path(path), str(Path(checkpoint).absolute())
        self.seq = self._read()

    def _read(self) -> int:
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return -1
        except OSError as e:
            raise RollbackStateError(f"cannot read the rollback state {self.path}: {e}") from None
        try:
            d = json.loads(text)
            if not isinstance(d, dict) or d.get("format") != STATE_FORMAT or type(d.get("seq")) is not int:
                raise ValueError(f"not a {STATE_FORMAT} file")
        except ValueError as e:
            raise RollbackStateError(f"rollback state {self.path} is unreadable ({e}); delete it "
                                     "to start without a floor") from None
        return d["seq"]

    def raise_to(self, seq: int) -> None:
        """Record `seq` if it is above the floor (atomically: a crash leaves old or new)."""
        if seq <= self.seq:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.path, json.dumps({"format": STATE_FORMAT, "checkpoint": self.checkpoint,
                                                     "seq": int(seq)}) + "\n")
        except OSError as e:
            raise RollbackStateError(f"cannot write the rollback state {self.path}: {e} (set "
                                     "rollback_state:=FILE to keep it elsewhere)") from None
        self.seq = int(seq)

    def check_served(self, seq: int, what: str) -> None:
        """RollbackStateError unless `seq` (the served file's) is at or above the floor."""
        if seq < self.seq:
            raise RollbackStateError(
                f"{what} is signed with sequence number {seq}, below {self.seq}, which this node "
                f"held before (rollback state {self.path}): restore the newer checkpoint, or delete "
                "the state file to accept this one")
