"""Signing keys (msgs_docs/security.md): a run's key pair, and the two commands that make and
use one by hand.

A run's key (#signed-by-default) is the Ed25519 key pair with which protocad-loop and
protocad-fleet sign the checkpoints their policy nodes load, and whose public half those nodes
get as `trusted_keys`.

    RUN_DIR/keys/checkpoint.key   private, mode 0600, made on first use, reused on --resume
    RUN_DIR/keys/checkpoint.pub   public: what other machines' policy nodes trust

An existing private key that others may read (group or world bits) is refused, not used.

    protocad-keygen learner                    # learner.key (0600) + learner.pub
    protocad-sign-checkpoint --key learner.key runs/x/checkpoints/latest.pt   # latest.pt.sig

The signatures themselves are protocad_ros/checkpoint/signing.py (no torch, no ROS).
"""
from __future__ import annotations

import os
import stat
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from cryptography.hazmat.primitives import serialization

from protocad_ros.checkpoint.signing import (
    SigningError,
    generate_keypair,
    key_id,
    load_private_key,
    sign_file,
    signature_path,
)
from trainer.settings import arg, build, settings_parser

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


# ---------------------------------------------------------------------- command lines
@dataclass
class KeygenSettings:
    """protocad-keygen's options."""

    name: str = arg("protocad-checkpoint", "name", nargs="?")
    """path prefix of the two files (default: protocad-checkpoint)"""
    private: str | None = arg(None, metavar="FILE")
    """private key file (default NAME.key)"""
    public: str | None = arg(None, metavar="FILE")
    """public key file (default NAME.pub)"""
    force: bool = False
    """replace existing key files"""


@dataclass
class SignSettings:
    """protocad-sign-checkpoint's options."""

    checkpoint: list[str] = arg([], "checkpoint", nargs="+")
    """checkpoint file(s) to sign"""
    key: str | None = arg(None, required=True, metavar="FILE")
    """private key (protocad-keygen)"""
    seq: int | None = None
    """sequence number (default: the time in ms); a node refuses a file whose number is not
    above the one it serves"""


def keygen_parser():
    return settings_parser(
        "protocad-keygen", "Make an Ed25519 key pair for signing checkpoints: NAME.key (private, mode "
        "0600: give it to the checkpoint publisher, -p signing_key:=NAME.key) and NAME.pub (public: give "
        "it to policy nodes, -p trusted_keys:=NAME.pub). See msgs_docs/security.md.", [(None, KeygenSettings)])


def keygen_main(argv: Sequence[str] | None = None) -> int:
    a = build(KeygenSettings, vars(keygen_parser().parse_args(argv)))
    private, public = a.private or f"{a.name}.key", a.public or f"{a.name}.pub"
    try:
        kid = generate_keypair(private, public, force=a.force)
    except (SigningError, OSError) as e:
        print(f"protocad-keygen: {e}", file=sys.stderr)
        return 1
    print(f"key {kid}: private key {private} (keep it secret, mode 0600), public key {public}\n"
          f"  learner: protocad-checkpoint-publisher --ros-args -p checkpoint:=FILE -p signing_key:={private}\n"
          f"  robot:   ros2 run protocad_ros policy --ros-args -p checkpoint_topic:=checkpoint "
          f"-p checkpoint:=FILE -p trusted_keys:={public}")
    return 0


def sign_parser():
    return settings_parser(
        "protocad-sign-checkpoint", "Write FILE.sig, the detached Ed25519 signature of a checkpoint file, "
        "which a policy node with trusted_keys requires to load (or reload) FILE. See msgs_docs/security.md.",
        [(None, SignSettings)])


def sign_main(argv: Sequence[str] | None = None) -> int:
    a = build(SignSettings, vars(sign_parser().parse_args(argv)))
    try:
        key = load_private_key(a.key)
        seq = a.seq
        for path in a.checkpoint:
            m = sign_file(path, key, seq)
            seq = None if a.seq is None else m.seq + 1
            print(f"signed {path} (sha256 {m.sha256[:12]}..., updates={m.updates}, seq={m.seq}, "
                  f"key {m.key_id}): {signature_path(path)}")
    except Exception as e:  # noqa: BLE001 (a key, a file that is not a checkpoint): one line
        print(f"protocad-sign-checkpoint: {e}", file=sys.stderr)
        return 1
    return 0
