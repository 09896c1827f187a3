"""A run's signing key (msgs_docs/security.md#signed-by-default): the Ed25519 key pair with
which protocad-loop and protocad-fleet sign the checkpoints their policy nodes load, and whose
public half those nodes get as `trusted_keys`.

    RUN_DIR/keys/checkpoint.key   private, mode 0600, made on first use, reused on --resume
    RUN_DIR/keys/checkpoint.pub   public: what other machines' policy nodes trust

An existing private key that others may read (group or world bits) is refused, not used.
"""
from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path

from cryptography.hazmat.primitives import serialization

from protocad_ros.checkpoint.signing import SigningError, generate_keypair, key_id, load_private_key

KEY_DIR = "keys"
KEY_NAME = "checkpoint"


@dataclass(frozen=True)
class RunKey:
    private: Path
    public: Path
    key_id: str
    made: bool   # made now (else reused)


def key_paths(run_dir: str | os.PathLike) -> tuple[Path, Path]:
    d = Path(run_dir) / KEY_DIR
    return d / f"{KEY_NAME}.key", d / f"{KEY_NAME}.pub"


def run_key(run_dir: str | os.PathLike) -> RunKey:
    """The run's key pair: made if there is none, else reused (its public half rewritten if it
    is missing). SigningError when the private key is unusable or readable by others."""
    private, public = key_paths(run_dir)
    if not private.exists():
        return RunKey(private, public, generate_keypair(private, public), True)
    mode = stat.S_IMODE(private.stat().st_mode)
    if mode & 0o077:
        raise SigningError(f"the run key {private} is readable by others (mode {mode:04o}): "
                           f"chmod 600 {private}, or remove it to make a new one")
    key = load_private_key(private)
    if not public.exists():
        public.write_bytes(key.public_key().public_bytes(
            serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))
    return RunKey(private, public, key_id(key.public_key()), False)


def describe(key: RunKey) -> str:
    """One line for the launchers' banners."""
    return (f"checkpoints signed with the run key {key.key_id} ({'made' if key.made else 'reused'}: "
            f"{key.private}); policy nodes trust {key.public}")
