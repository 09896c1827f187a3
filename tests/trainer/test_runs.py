"""trainer.runs' CPU runtime set-up: freed memory stays with the process (glibc)."""
from __future__ import annotations

import subprocess
import sys

import pytest
from helpers import ROOT

# Fills and frees a 24 MB tensor (an update's activations are such blocks) and prints how much
# of it the process still holds after the free, in MB, from /proc/self/statm's resident pages.
_HELD_AFTER_FREE = """
import os, sys, torch
from trainer import runs, torch_setup
if sys.argv[1] == "retain":
    print(torch_setup.retain_freed_memory())
page = os.sysconf("SC_PAGE_SIZE")
resident = lambda: int(open("/proc/self/statm").read().split()[1]) * page
y = torch.empty(1 << 10); y.fill_(1.0); del y   # fill's code pages, loaded once, are not the block
before = resident()
x = torch.empty(6 << 20); x.fill_(1.0); del x
print(round((resident() - before) / 1e6))
"""


def _run(mode: str) -> list[str]:
    r = subprocess.run([sys.executable, "-c", _HELD_AFTER_FREE, mode], capture_output=True,
                       text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout.split()


@pytest.mark.process
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_activations_stay_with_the_process_for_the_next_update():
    """What the trainers call retain_freed_memory for: a freed 24 MB block stays in the heap,
    so the next update reuses its pages instead of faulting fresh zeroed ones in; glibc's
    default gives it back to the kernel at once."""
    taken, held = _run("retain")
    assert taken == "True"
    assert int(held) >= 20, f"only {held} MB of the freed 24 MB block stayed"
    # (a few MB of anything else the process touches may come and go; the 24 MB block may not)
    assert int(_run("default")[0]) <= 12, "glibc's default kept the block: the test shows nothing"
