"""The GPU campaign script, run as on the GPU machine but on CPU with a tiny budget: no ROS
package, rerun or jsonschema importable (as there), every step inside the deadline, results
and logs under $OUT, checkpoints and bags removed."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from helpers import HELPERS, ROOT
from trainer.research import results as R

pytestmark = pytest.mark.process

GPU_MACHINE_LACKS = ("rclpy,rosidl_runtime_py,rosidl_parser,ament_index_python,sensor_msgs,std_msgs,"
                     "rosgraph_msgs,builtin_interfaces,diagnostic_msgs,rerun,jsonschema")


@pytest.mark.slow
def test_campaign_runs_every_step_without_ros_on_a_tiny_budget(tmp_path):
    out = tmp_path / "out"
    env = {**os.environ, "OUT": str(out), "PROTOCAD_BLOCK_IMPORTS": GPU_MACHINE_LACKS,
           "PYTHONPATH": os.pathsep.join([str(HELPERS / "import_blocker"), str(ROOT)])}
    p = subprocess.run([sys.executable, "scripts/gpu_campaign.py", "--tiny", "--deadline", "420"],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]
    summary = json.loads((out / "campaign.json").read_text())
    assert [s["step"] for s in summary["steps"]] == ["machine", "bench_train", "bench_envs", "compare"]
    assert all(s["rc"] == 0 for s in summary["steps"]) and summary["seconds"] <= 420
    assert "CPU capability" in (out / "machine.txt").read_text()
    rows = json.loads((out / "bench_train.json").read_text())
    assert {r["variant"] for r in rows} == {"protocad", "dreamer"} and all("sec" in r for r in rows)
    assert "pendulum_swingup" in (out / "bench_envs.txt").read_text()
    doc = json.loads((out / "compare" / "results.json").read_text())
    R.validate(doc)    # jsonschema is importable here, in the test process
    assert sorted(r["label"] for r in doc["runs"]) == ["dreamer", "protocad"]
    assert all(r["status"] == "finished" and r["final"] is not None for r in doc["runs"])
    assert (out / "compare" / "curves.png").stat().st_size > 0
    assert "rerun: not written (rerun-sdk is not installed)" in p.stdout
    for run in (out / "compare" / "pendulum_swingup").glob("*/seed0"):
        assert (run / "online.log").exists() and (run / "eval" / "final.json").exists()
        assert not (run / "checkpoints").exists() and not (run / "bags").exists()
