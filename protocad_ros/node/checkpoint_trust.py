"""`CheckpointTrust`: which checkpoints the policy node may serve, for CheckpointServing
(protocad_ros/node/checkpoint_serving.py), which owns it; free of rclpy.

With `trusted_keys` nothing is served that a trusted key did not sign: the file needs its
detached signature FILE.sig (protocad_ros.checkpoint.signing), each new version a sequence
number above the newest one held, which is also kept apart from the served file
(rollback_floor.py), so that losing FILE.sig does not lower it. Without trusted keys unsigned
checkpoints are accepted: said loudly, and over checkpoint_topic only with `allow_unsigned`.

It owns the trusted keys, the rollback floor and the signature grace of a changed file; it is
handed the node's parameter dict and a logger.
"""
from __future__ import annotations

import time
from typing import Any

from protocad_ros.atomic import file_signature
from protocad_ros.checkpoint.signing import (
    SignatureRejected,
    SigningError,
    TrustedKeys,
    load_trusted_keys,
    parse_key_list,
    read_signature_file,
    signature_path,
    verify_file,
)
from protocad_ros.node.rollback_floor import RollbackFloor, RollbackStateError, default_state_path
from sim_bridge.nodekit.param_table import ConfigError

#: How long a changed checkpoint file may wait for its FILE.sig (a signer writes it after the
#: file) before it counts as unsigned.
SIGNATURE_GRACE_S = 5.0


class RollbackRejected(SignatureRejected):
    """A validly signed version that is not newer than the one served."""


class CheckpointTrust:
    """The trusted keys (None: unsigned accepted) and the rollback floor; see the module docstring."""

    def __init__(self, *, params: dict[str, Any], logger: Any):
        self._params, self._log = params, logger
        self.trusted: TrustedKeys | None = None   # key id -> public key
        self.rollback: RollbackFloor | None = None
        self._unsigned_since: tuple = (None, 0.0)   # (watch key, since): a file awaiting FILE.sig

    def load(self) -> None:
        """trusted_keys -> the trusted keys and the rollback floor (None: unsigned checkpoints are
        accepted: from the file said loudly, over checkpoint_topic only with allow_unsigned);
        a ConfigError for settings that do not go together."""
        p = self._params
        paths = parse_key_list(p["trusted_keys"])
        self.trusted, self.rollback = None, None
        if paths:
            try:
                self.trusted = load_trusted_keys(paths)
            except SigningError as e:
                raise ConfigError(f"trusted_keys: {e}") from None
            state = p["rollback_state"] or default_state_path(paths[0], p["checkpoint"] or "none")
            try:
                self.rollback = RollbackFloor(state, p["checkpoint"])
            except RollbackStateError as e:
                raise ConfigError(str(e)) from None
            minimum = (f"; no version signed below min_checkpoint_seq {p['min_checkpoint_seq']}"
                       if p["min_checkpoint_seq"] else "")
            self._log.info(f"serving only checkpoints signed by trusted key(s) "
                           f"{', '.join(sorted(self.trusted))}; rollback floor "
                           f"{self.rollback.seq} ({self.rollback.path}){minimum}")
        elif p["min_checkpoint_seq"]:
            raise ConfigError(f"min_checkpoint_seq:={p['min_checkpoint_seq']} without trusted_keys: only "
                              "signed versions carry a sequence number; give -p trusted_keys:=LEARNER.pub")
        elif p["checkpoint_topic"] and not p["allow_unsigned"]:
            raise ConfigError(f"checkpoint_topic:={p['checkpoint_topic']} without trusted_keys: anyone on "
                              "this DDS domain could replace the served model; give -p trusted_keys:="
                              "LEARNER.pub (protocad-keygen makes the pair; the learner signs with it), "
                              "or -p allow_unsigned:=true to accept unsigned checkpoints")
        elif p["checkpoint"] or p["checkpoint_topic"]:
            source = (f"over {p['checkpoint_topic']} (allow_unsigned:=true): anyone on this DDS "
                      "domain can replace the served model" if p["checkpoint_topic"] else "from its file")
            self._log.warning(f"no trusted_keys: this node accepts UNSIGNED checkpoints {source} "
                              "(protocad-keygen makes a key pair; msgs_docs/security.md)")

    def release(self) -> None:
        """Unconfigured: no keys, no floor (configure reads them again)."""
        self.trusted, self.rollback = None, None
        self._unsigned_since = (None, 0.0)

    @property
    def unsigned_topic(self) -> bool:
        """Unsigned checkpoints over ROS are accepted (allow_unsigned): shown in /diagnostics."""
        return bool(self._params["checkpoint_topic"]) and self.trusted is None

    @property
    def floor(self) -> int:
        """The rollback floor kept apart from the served file; -1 without trusted keys."""
        return self.rollback.seq if self.rollback is not None else -1

    def diagnostics(self) -> dict[str, Any]:
        return {"checkpoint_trusted_keys": ",".join(sorted(self.trusted)) if self.trusted else "",
                "checkpoint_rollback_floor": self.floor}

    def verified_seq(self, path: str, sha: str, size: int, newest: int) -> int:
        """The sequence number FILE.sig vouches for (-1 without trusted keys); SignatureRejected
        when it does not verify, RollbackRejected when it is not above `newest`, the newest one
        held."""
        if self.trusted is None:
            return -1
        manifest = verify_file(path, sha, size, self.trusted)
        if manifest.seq <= newest:
            raise RollbackRejected(f"rollback: sequence number {manifest.seq} is not above {newest}, "
                                   "the newest version this node holds (or min_checkpoint_seq - 1)")
        return manifest.seq

    def configured_seq(self, path: str, sha: str, size: int) -> int:
        """At configure: the file must verify (a ConfigError otherwise) and not be below the
        rollback floor kept apart from it; its number (-1: unsigned accepted) is the floor from
        now on."""
        if self.trusted is None:
            return -1
        try:
            seq = verify_file(path, sha, size, self.trusted).seq
            self.rollback.check_served(seq, f"checkpoint {path}")
            self.rollback.raise_to(seq)
        except SignatureRejected as e:
            raise ConfigError(f"checkpoint {path} is not signed by a trusted key: {e}") from None
        except RollbackStateError as e:
            raise ConfigError(str(e)) from None
        return seq

    def hold(self, seq: int) -> None:
        """A version about to serve: held from now on (installed on disk), so the floor survives
        losing FILE.sig; a state file that cannot be written is said, not fatal."""
        if self.rollback is not None and seq >= 0:
            try:
                self.rollback.raise_to(seq)
            except RollbackStateError as e:
                self._log.error(str(e))

    def watch_key(self, path: str) -> tuple | None:
        """What makes the poll look again: the file, and with trusted keys its FILE.sig."""
        sig = file_signature(path)
        if sig is None:
            return None
        return (sig, file_signature(signature_path(path)) if self.trusted is not None else None)

    def awaiting_signature(self, path: str, sha: str, key: tuple) -> bool:
        """With trusted keys, a changed file without its FILE.sig yet (or with the previous
        version's): its signer writes it after the file, so it is waited for SIGNATURE_GRACE_S
        before it counts."""
        if self.trusted is None:
            return False
        try:
            manifest, _ = read_signature_file(path)
            if manifest.sha256 == sha:
                return False
        except SignatureRejected:
            pass
        now = time.monotonic()
        since = self._unsigned_since if self._unsigned_since[0] == key else (key, now)
        self._unsigned_since = since
        return now - since[1] < SIGNATURE_GRACE_S
