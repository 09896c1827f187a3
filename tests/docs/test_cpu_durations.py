"""`--cpu-durations=N` (tests/conftest.py), the figure msgs_docs/benchmarks.md's suite section
quotes: a test is charged its own CPU and that of the child processes it reaped, also when
pytest-xdist runs it in a worker and the controller prints the table."""
from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from helpers import ROOT

pytestmark = pytest.mark.process

PROBE = '''
import subprocess, sys, time

def test_a_child_burns_a_second():
    burn = "import time\\nt = time.process_time()\\nwhile time.process_time() - t < 1.0: pass"
    subprocess.run([sys.executable, "-c", burn], check=True)

def test_sleeps_a_second():
    time.sleep(1.0)
'''


def test_a_test_is_charged_the_cpu_of_the_children_it_reaped_not_its_waits(tmp_path):
    (tmp_path / "test_probe.py").write_text(PROBE)
    # the project's conftest as a plugin, for a test file of its own outside the suite
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), str(ROOT)])}
    r = subprocess.run([sys.executable, "-m", "pytest", "-p", "conftest", "-p", "no:cacheprovider", "-n", "2",
                        "--cpu-durations=0", "test_probe.py"], cwd=tmp_path, capture_output=True, text=True,
                       timeout=300, env=env)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    rows = dict((name, float(s)) for s, name in re.findall(r"^\s+([\d.]+)s\s+test_probe\.py::(\w+)$", r.stdout, re.M))
    assert set(rows) == {"test_a_child_burns_a_second", "test_sleeps_a_second"}, r.stdout
    assert rows["test_a_child_burns_a_second"] >= 1.0 > rows["test_sleeps_a_second"] + 0.5, rows
    total = float(re.search(r"CPU seconds, all \(all tests: (\d+) s\)", r.stdout).group(1))
    assert abs(total - sum(rows.values())) <= 1, (total, rows)

