"""Which code a run names (trainer/provenance.py): an installed copy names the commit setup.py
installed, not the checkout it was started from, and says when that checkout has moved on."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from helpers import ROOT


def _in(lib, code: str, cwd) -> str:
    env = {**os.environ, "PYTHONPATH": str(lib)}
    r = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_an_installed_copy_names_its_installed_commit_and_warns_when_the_checkout_moved_on(tmp_path):
    from trainer.provenance import git_commit

    lib = tmp_path / "lib"
    r = subprocess.run([sys.executable, "setup.py", "-q", "build_py", "--build-lib", str(lib)], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    info = json.loads((lib / "trainer" / "build_info.json").read_text())
    assert info == {"commit": git_commit(ROOT), "source": str(ROOT)}
    ask = "from trainer.provenance import code_version, stale_install; print(code_version()); print(stale_install())"
    assert _in(lib, ask, tmp_path).splitlines() == [info["commit"], "None"]   # installed = checkout

    # An older install (the state after a `git pull` without `scripts/protocad setup`), written
    # by hand: the runs name the installed commit and every start says what to do.
    old = "0123456789abcdef0123456789abcdef01234567"
    (lib / "trainer" / "build_info.json").write_text(json.dumps({**info, "commit": old}))
    version, warning = _in(lib, ask, tmp_path).splitlines()
    assert version == old
    assert old in warning and info["commit"] in warning and "scripts/protocad setup" in warning


def test_a_checkout_names_its_own_commit_wherever_the_command_starts(tmp_path):
    code = "from trainer.provenance import code_version, stale_install; print(code_version()); print(stale_install())"
    from trainer.provenance import git_commit

    assert _in(ROOT, code, tmp_path).splitlines() == [git_commit(ROOT), "None"]
