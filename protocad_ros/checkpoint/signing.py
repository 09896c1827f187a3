"""Ed25519 signatures of checkpoints (msgs_docs/security.md#checkpoint-authentication).

A learner signs what it publishes with a private key; a policy node that is given the matching
public key(s) (`trusted_keys`) installs only what such a key signed. What is signed is a
`Manifest`: the file's sha256 and size, the per-chunk sha256 hashes of its transfer, the task,
variant, preset and update counter it claims, a sequence number that only grows (no rollback)
and the id of the signing key. The signature covers the manifest's canonical JSON
(`Manifest.signed_bytes`), so both sides agree on the bytes without trusting the transport.

    protocad-keygen learner                    # learner.key (0600) + learner.pub
    protocad-sign-checkpoint --key learner.key runs/x/checkpoints/latest.pt   # latest.pt.sig

Free of ROS: the publisher (trainer/nodes/checkpoint_publisher.py), the receiver
(protocad_ros/node/checkpoint_receiver.py), the file watcher (protocad_ros/node/checkpoint_serving.py)
and the two commands above (trainer/launch/run_key.py) share it.
"""
from __future__ import annotations

import base64
import binascii
import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable, Mapping

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from protocad_ros.atomic import atomic_open
from protocad_ros.checkpoint.files import read_checkpoint_file

__all__ = ["Manifest", "SignatureRejected", "SigningError", "TrustedKeys", "generate_keypair",
           "key_id", "load_private_key", "load_trusted_keys", "next_seq", "sign_manifest",
           "verify_manifest", "signature_path", "write_signature_file", "read_signature_file",
           "verify_file", "sign_file", "sign_bytes"]

MANIFEST_FORMAT = "protocad-ros/checkpoint-manifest/1"
SIGNATURE_FILE_FORMAT = "protocad-ros/checkpoint-signature"
SIG_SUFFIX = ".sig"
#: The top-level fields of FILE.sig: anything else refuses it (a .sig carries nothing unsigned).
SIGNATURE_FILE_FIELDS = frozenset({"format", "manifest", "signature"})
#: Anything longer in a signature file is not one of ours (a manifest with 16384 chunk hashes
#: is about 1.1 MB).
MAX_SIGNATURE_FILE_BYTES = 4 << 20

TrustedKeys = Mapping[str, Ed25519PublicKey]   # key id -> public key


class SigningError(RuntimeError):
    """A key or signature file that cannot be used (missing, unreadable, wrong type)."""


class SignatureRejected(Exception):
    """A checkpoint whose signature does not verify with a trusted key; says why."""


@dataclass(frozen=True)
class Manifest:
    """What a signature vouches for. chunk_size/chunk_sha256 describe a transfer in chunks
    (0/() for a file signed on its own)."""

    sha256: str
    size: int
    task: str = ""
    variant: str = ""
    preset: str = ""
    updates: int = -1
    seq: int = 0
    key_id: str = ""
    chunk_size: int = 0
    chunk_sha256: tuple[str, ...] = field(default_factory=tuple)

    def signed_bytes(self) -> bytes:
        """Canonical JSON (sorted keys, no spaces, ASCII): the same bytes on every machine."""
        d = {"format": MANIFEST_FORMAT, **asdict(self), "chunk_sha256": list(self.chunk_sha256)}
        return json.dumps(d, sort_keys=True, separators=(",", ":"), ensure_ascii=True).encode()

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "chunk_sha256": list(self.chunk_sha256)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Manifest":
        """ValueError when a field is missing or of the wrong type."""
        if not isinstance(d, Mapping):
            raise ValueError("manifest must be an object")
        ints = ("size", "updates", "seq", "chunk_size")
        strs = ("sha256", "task", "variant", "preset", "key_id")
        unknown = sorted(set(d) - {*ints, *strs, "chunk_sha256"}, key=str)
        if unknown:   # what no signer of ours writes: nothing unsigned rides along
            raise ValueError(f"manifest has field(s) this code does not know: {unknown[:5]}")
        for k in ints:
            if type(d.get(k)) is not int:
                raise ValueError(f"manifest {k} must be a whole number, got {d.get(k)!r}")
        for k in strs:
            if not isinstance(d.get(k), str):
                raise ValueError(f"manifest {k} must be a string, got {d.get(k)!r}")
        hashes = d.get("chunk_sha256")
        if not isinstance(hashes, list) or not all(isinstance(h, str) for h in hashes):
            raise ValueError("manifest chunk_sha256 must be a list of strings")
        return cls(**{k: d[k] for k in ints + strs}, chunk_sha256=tuple(hashes))


# ---------------------------------------------------------------------- keys
def key_id(public_key: Ed25519PublicKey) -> str:
    """16 hex digits of the sha256 of the raw public key: names a key in logs and manifests."""
    raw = public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()[:16]


def _write_new(path: Path, data: bytes, mode: int, force: bool) -> None:
    """Create `path` with permission `mode` from the first byte on (never world-readable for a
    moment); an existing file is an error unless `force`."""
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if force else os.O_EXCL)
    try:
        fd = os.open(path, flags, mode)
    except FileExistsError:
        raise SigningError(f"{path} exists; not overwriting it (--force replaces it)") from None
    with os.fdopen(fd, "wb") as f:
        os.fchmod(f.fileno(), mode)   # an existing file keeps its old mode under O_TRUNC
        f.write(data)


def generate_keypair(private_path: str | os.PathLike, public_path: str | os.PathLike, *,
                     force: bool = False) -> str:
    """A new Ed25519 key pair: the private key (PKCS#8 PEM, 0600) and the public key
    (SubjectPublicKeyInfo PEM, 0644). Returns the key id."""
    private_path, public_path = Path(private_path), Path(public_path)
    if not force:
        for p in (private_path, public_path):
            if p.exists():
                raise SigningError(f"{p} exists; not overwriting it (--force replaces it)")
    key = Ed25519PrivateKey.generate()
    private_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                    serialization.NoEncryption())
    public_pem = key.public_key().public_bytes(serialization.Encoding.PEM,
                                               serialization.PublicFormat.SubjectPublicKeyInfo)
    for p in (private_path, public_path):
        p.parent.mkdir(parents=True, exist_ok=True)
    _write_new(private_path, private_pem, 0o600, force)
    _write_new(public_path, public_pem, 0o644, force)
    return key_id(key.public_key())


def load_private_key(path: str | os.PathLike) -> Ed25519PrivateKey:
    try:
        data = Path(path).read_bytes()
        key = serialization.load_pem_private_key(data, password=None)
    except (OSError, ValueError, TypeError) as e:
        raise SigningError(f"cannot read the private key {path}: {e}") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise SigningError(f"{path} is a {type(key).__name__}, not an Ed25519 private key "
                           "(make one with protocad-keygen)")
    return key


def load_trusted_keys(paths: Iterable[str | os.PathLike]) -> dict[str, Ed25519PublicKey]:
    """Public keys by key id, from PEM files (what protocad-keygen writes as NAME.pub)."""
    keys: dict[str, Ed25519PublicKey] = {}
    for path in paths:
        try:
            key = serialization.load_pem_public_key(Path(path).read_bytes())
        except (OSError, ValueError, TypeError) as e:
            raise SigningError(f"cannot read the public key {path}: {e}") from None
        if not isinstance(key, Ed25519PublicKey):
            raise SigningError(f"{path} is a {type(key).__name__}, not an Ed25519 public key")
        keys[key_id(key)] = key
    return keys


def parse_key_list(text: str) -> list[str]:
    """'a.pub, b.pub' -> ['a.pub', 'b.pub'] (a ROS string parameter holds the list)."""
    return [p.strip() for p in text.split(",") if p.strip()]


# ---------------------------------------------------------------------- sign and verify
def next_seq(previous: int = 0) -> int:
    """A sequence number above `previous` that also grows across restarts of the signer: the
    wall clock in milliseconds (a clock set back is outrun by previous + 1 while running)."""
    return max(int(previous) + 1, time.time_ns() // 1_000_000)


def sign_manifest(manifest: Manifest, key: Ed25519PrivateKey) -> tuple[Manifest, str]:
    """(the manifest with the key's id, base64 signature of its signed_bytes)."""
    m = replace(manifest, key_id=key_id(key.public_key()))
    return m, base64.b64encode(key.sign(m.signed_bytes())).decode("ascii")


def verify_manifest(manifest: Manifest, signature: str, trusted: TrustedKeys) -> None:
    """SignatureRejected unless `signature` is a trusted key's signature of `manifest`."""
    if not signature:
        raise SignatureRejected("unsigned (this node accepts only checkpoints signed by "
                                f"trusted key(s) {', '.join(sorted(trusted))})")
    key = trusted.get(manifest.key_id)
    if key is None:
        raise SignatureRejected(f"signed by key {manifest.key_id or '?'!s}, which is not trusted "
                                f"here (trusted: {', '.join(sorted(trusted))})")
    try:
        raw = base64.b64decode(signature.encode("ascii"), validate=True)
        key.verify(raw, manifest.signed_bytes())
    except (InvalidSignature, binascii.Error, UnicodeEncodeError, ValueError):
        raise SignatureRejected(f"bad signature: it does not verify with key {manifest.key_id}"
                                ) from None


def chunk_hashes(data: bytes | memoryview, chunk_size: int) -> tuple[str, ...]:
    view = memoryview(data)
    return tuple(hashlib.sha256(view[i:i + chunk_size]).hexdigest()
                 for i in range(0, len(view), chunk_size))


# ---------------------------------------------------------------------- signature files
def signature_path(checkpoint: str | os.PathLike) -> Path:
    """FILE.sig beside FILE: the detached signature the file-reload path checks."""
    p = Path(checkpoint)
    return p.with_name(p.name + SIG_SUFFIX)


def write_signature_file(checkpoint: str | os.PathLike, manifest: Manifest, signature: str) -> Path:
    path = signature_path(checkpoint)
    text = json.dumps({"format": SIGNATURE_FILE_FORMAT, "manifest": manifest.to_dict(),
                       "signature": signature}, sort_keys=True, indent=1)
    with atomic_open(path, "w") as f:
        f.write(text + "\n")
    return path


def read_signature_file(checkpoint: str | os.PathLike) -> tuple[Manifest, str]:
    """(manifest, signature) of FILE.sig; SignatureRejected when it is missing or not ours."""
    path = signature_path(checkpoint)
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_SIGNATURE_FILE_BYTES + 1)
    except FileNotFoundError:
        raise SignatureRejected(f"unsigned: no signature file {path.name} beside it "
                                "(protocad-sign-checkpoint writes one)") from None
    except OSError as e:
        raise SignatureRejected(f"cannot read {path}: {e}") from None
    try:
        if len(data) > MAX_SIGNATURE_FILE_BYTES:
            raise ValueError(f"larger than {MAX_SIGNATURE_FILE_BYTES} bytes")
        d = json.loads(data)
        if not isinstance(d, dict) or d.get("format") != SIGNATURE_FILE_FORMAT:
            raise ValueError(f"format is not {SIGNATURE_FILE_FORMAT!r}")
        unknown = sorted(set(d) - SIGNATURE_FILE_FIELDS, key=str)
        if unknown:
            raise ValueError(f"field(s) this code does not know: {unknown[:5]}")
        signature = d.get("signature")
        if not isinstance(signature, str):
            raise ValueError("signature must be a string")
        return Manifest.from_dict(d.get("manifest")), signature
    except ValueError as e:
        raise SignatureRejected(f"{path.name} is not a signature file: {e}") from None


def verify_file(checkpoint: str | os.PathLike, sha256: str, size: int,
                trusted: TrustedKeys) -> Manifest:
    """The verified manifest of FILE (whose bytes have `sha256` and `size`) from FILE.sig;
    SignatureRejected when it is missing, for other bytes, or not a trusted key's."""
    manifest, signature = read_signature_file(checkpoint)
    if (manifest.sha256, manifest.size) != (sha256, size):
        raise SignatureRejected(f"{signature_path(checkpoint).name} is for other bytes (sha256 "
                                f"{manifest.sha256[:12]}..., this file {sha256[:12]}...)")
    verify_manifest(manifest, signature, trusted)
    return manifest


def sign_file(checkpoint: str | os.PathLike, key: Ed25519PrivateKey, seq: int | None = None) -> Manifest:
    """Write FILE.sig for a checkpoint file (its task, variant, preset, updates from the file)."""
    checkpoint = Path(checkpoint)   # the one bounded read every checkpoint reader makes
    return sign_bytes(checkpoint, read_checkpoint_file(checkpoint), key, seq)


def sign_bytes(checkpoint: str | os.PathLike, data: bytes, key: Ed25519PrivateKey,
               seq: int | None = None) -> Manifest:
    """Write FILE.sig for `data`, the bytes of the checkpoint FILE (read once by the caller)."""
    from protocad_ros.checkpoint.agent_file import read_checkpoint

    # never vouch for something that is not a checkpoint: the same bytes are checked
    payload = read_checkpoint(checkpoint, data=data)
    cfg = payload.get("config", {})
    manifest = Manifest(hashlib.sha256(data).hexdigest(), len(data), str(cfg.get("task", "")),
                        str(cfg.get("variant", "")), str(cfg.get("preset", "")),
                        int(payload.get("agent_counters", {}).get("updates", -1)),
                        next_seq() if seq is None else int(seq))
    manifest, signature = sign_manifest(manifest, key)
    write_signature_file(checkpoint, manifest, signature)
    return manifest
