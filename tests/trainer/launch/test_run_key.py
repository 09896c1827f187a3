"""The run key (trainer/launch/run_key.py): made once with mode 0600, reused on resume, refused
when others may read it; and security.md names only tests that exist."""
from __future__ import annotations

import os
import re
import stat

import pytest
from helpers import ROOT

from protocad_ros.checkpoint.signing import SigningError, load_trusted_keys
from trainer.launch.run_key import key_paths, run_key


def test_the_run_key_is_made_once_private_and_reused(tmp_path):
    made = run_key(tmp_path / "run")
    private, public = key_paths(tmp_path / "run")
    assert made.made and (made.private, made.public) == (private, public)
    assert stat.S_IMODE(private.stat().st_mode) == 0o600
    assert list(load_trusted_keys([public])) == [made.key_id]
    again = run_key(tmp_path / "run")                      # a resume: the same key
    assert not again.made and again.key_id == made.key_id
    public.unlink()                                        # its public half is written anew
    assert run_key(tmp_path / "run").key_id == made.key_id and public.is_file()
    os.chmod(private, 0o644)
    with pytest.raises(SigningError, match="readable by others .*chmod 600"):
        run_key(tmp_path / "run")


def test_security_md_names_only_tests_that_exist():
    doc = (ROOT / "msgs_docs" / "security.md").read_text()
    named = re.findall(r"`(tests/[\w/]+\.py)::(\w+)`", doc)
    short = re.findall(r"`\.\.\.::(\w+)`", doc)
    assert len(named) >= 8, named
    missing = [f"{f}::{t}" for f, t in named if f"def {t}(" not in (ROOT / f).read_text()]
    alltests = "".join((ROOT / f).read_text() for f in {f for f, _ in named})
    missing += [t for t in short if f"def {t}(" not in alltests]
    assert not missing, f"security.md names tests that do not exist: {missing}"
