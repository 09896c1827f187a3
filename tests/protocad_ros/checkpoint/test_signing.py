"""Checkpoint signatures without ROS (protocad_ros/checkpoint/signing.py, msgs_docs/security.md):
key pairs from the command line (trainer/launch/run_key.py), manifests signed and verified, detached FILE.sig files."""
from __future__ import annotations

import dataclasses
import os
import stat
import subprocess
import sys

import pytest

from protocad_ros.checkpoint.signing import (
    Manifest,
    SignatureRejected,
    SigningError,
    generate_keypair,
    load_private_key,
    load_trusted_keys,
    next_seq,
    sign_manifest,
    signature_path,
    verify_file,
    verify_manifest,
)
from trainer.launch.run_key import keygen_main, sign_main


@pytest.fixture
def pair(tmp_path):
    kid = generate_keypair(tmp_path / "learner.key", tmp_path / "learner.pub")
    return kid, load_private_key(tmp_path / "learner.key"), load_trusted_keys([tmp_path / "learner.pub"])


@pytest.mark.process
def test_keygen_writes_a_private_key_only_its_owner_reads_and_never_overwrites(tmp_path, capsys):
    assert keygen_main([str(tmp_path / "k")]) == 0
    key, pub = tmp_path / "k.key", tmp_path / "k.pub"
    assert stat.S_IMODE(key.stat().st_mode) == 0o600 and stat.S_IMODE(pub.stat().st_mode) == 0o644
    assert "PRIVATE KEY" in key.read_text() and "PUBLIC KEY" in pub.read_text()
    kid = next(iter(load_trusted_keys([pub])))
    assert f"key {kid}" in capsys.readouterr().out
    before = key.read_bytes()
    assert keygen_main([str(tmp_path / "k")]) == 1
    assert "exists; not overwriting" in capsys.readouterr().err and key.read_bytes() == before
    os.chmod(key, 0o644)
    assert keygen_main([str(tmp_path / "k"), "--force"]) == 0
    assert key.read_bytes() != before and stat.S_IMODE(key.stat().st_mode) == 0o600
    out = subprocess.run([sys.executable, "-c", "from trainer.launch.run_key import keygen_main; "
                          "keygen_main()", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "--force" in out.stdout and "0600" in out.stdout


def test_a_manifest_verifies_only_unaltered_and_with_a_trusted_key(tmp_path, pair):
    kid, key, trusted = pair
    m = Manifest("a" * 64, 10, "walker_walk", "protocad", "small", 7, next_seq(), "", 4096, ("b" * 64,))
    signed, signature = sign_manifest(m, key)
    assert signed.key_id == kid
    verify_manifest(signed, signature, trusted)
    for field, value in [("sha256", "c" * 64), ("size", 11), ("task", "cheetah_run"), ("updates", 8),
                         ("seq", signed.seq + 1), ("chunk_sha256", ("d" * 64,)), ("preset", "paper")]:
        with pytest.raises(SignatureRejected, match="bad signature"):
            verify_manifest(dataclasses.replace(signed, **{field: value}), signature, trusted)
    with pytest.raises(SignatureRejected, match="unsigned"):
        verify_manifest(signed, "", trusted)
    with pytest.raises(SignatureRejected, match="bad signature"):
        verify_manifest(signed, "not base64!", trusted)
    generate_keypair(tmp_path / "other.key", tmp_path / "other.pub")
    other, other_sig = sign_manifest(m, load_private_key(tmp_path / "other.key"))
    with pytest.raises(SignatureRejected, match="not trusted"):
        verify_manifest(other, other_sig, trusted)
    # The other key's signature under the trusted key's id is no better.
    with pytest.raises(SignatureRejected, match="bad signature"):
        verify_manifest(dataclasses.replace(other, key_id=kid), other_sig, trusted)
    assert next_seq(10**15) == 10**15 + 1 and next_seq() > 1_700_000_000_000


def test_keys_that_are_not_ed25519_or_not_keys_are_refused(tmp_path):
    (tmp_path / "junk.pub").write_text("not a key\n")
    with pytest.raises(SigningError, match="cannot read the public key"):
        load_trusted_keys([tmp_path / "junk.pub"])
    with pytest.raises(SigningError, match="cannot read the private key"):
        load_private_key(tmp_path / "missing.key")
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    pem = ec.generate_private_key(ec.SECP256R1()).public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
    (tmp_path / "ec.pub").write_bytes(pem)
    with pytest.raises(SigningError, match="not an Ed25519 public key"):
        load_trusted_keys([tmp_path / "ec.pub"])


def test_a_signed_file_verifies_and_its_signature_does_not_carry_to_other_bytes(tmp_path, pair, capsys):
    from protocad_ros.checkpoint.agent_file import save_checkpoint
    from protocad_ros.model.agent import make_agent
    from protocad_ros.model.config import make_config

    kid, _, trusted = pair
    agent = make_agent(make_config("pendulum_swingup", "small"), 1)
    agent.updates.fill_(3)
    path = save_checkpoint(tmp_path / "agent.pt", agent)
    with pytest.raises(SignatureRejected, match="unsigned: no signature file agent.pt.sig"):
        verify_file(path, "0" * 64, path.stat().st_size, trusted)
    assert sign_main(["--key", str(tmp_path / "learner.key"), "--seq", "41", str(path)]) == 0
    assert "agent.pt.sig" in capsys.readouterr().out
    import hashlib

    sha = hashlib.sha256(path.read_bytes()).hexdigest()
    m = verify_file(path, sha, path.stat().st_size, trusted)
    assert (m.seq, m.updates, m.task, m.key_id) == (41, 3, "pendulum_swingup", kid)
    with pytest.raises(SignatureRejected, match="is for other bytes"):
        verify_file(path, "1" * 64, path.stat().st_size, trusted)
    signature_path(path).write_text("{}")
    with pytest.raises(SignatureRejected, match="not a signature file"):
        verify_file(path, sha, path.stat().st_size, trusted)
    (tmp_path / "notes.pt").write_text("hello")
    assert sign_main(["--key", str(tmp_path / "learner.key"), str(tmp_path / "notes.pt")]) == 1
    assert "not a checkpoint" in capsys.readouterr().err
    assert not signature_path(tmp_path / "notes.pt").exists()
