"""The GPU campaign script, run as on the GPU machine but on CPU with a tiny budget: no ROS
package, rerun or jsonschema importable (as there), every step inside the deadline, and what
comes back from the device is what it leaves in $OUT: one tar and campaign.json."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile

import pytest
from helpers import HELPERS, ROOT

from trainer.research.results_json import validate

pytestmark = pytest.mark.process

GPU_MACHINE_LACKS = ("rclpy,rosidl_runtime_py,rosidl_parser,ament_index_python,sensor_msgs,std_msgs,"
                     "rosgraph_msgs,builtin_interfaces,diagnostic_msgs,rerun,jsonschema")


def campaign(tmp_path, *args: str, timeout: float = 600) -> tuple[subprocess.CompletedProcess, dict, tarfile.TarFile]:
    out = tmp_path / "out"
    env = {**os.environ, "OUT": str(out), "PROTOCAD_BLOCK_IMPORTS": GPU_MACHINE_LACKS,
           "PYTHONPATH": os.pathsep.join([str(HELPERS / "import_blocker"), str(ROOT)])}
    p = subprocess.run([sys.executable, "scripts/gpu_campaign.py", *args], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=timeout)
    assert sorted(x.name for x in out.iterdir()) == ["campaign.json", "campaign.tar.gz"], p.stdout[-3000:]
    return p, json.loads((out / "campaign.json").read_text()), tarfile.open(out / "campaign.tar.gz")


@pytest.mark.slow
def test_campaign_runs_every_step_without_ros_on_a_tiny_budget(tmp_path):
    p, summary, tar = campaign(tmp_path, "--tiny", "--deadline", "420")
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]
    assert [s["step"] for s in summary["steps"]] == ["preflight_cuda", "preflight_egl", "bench_train_x1",
                                                     "bench_envs", "compare"]
    assert all(s["rc"] == 0 for s in summary["steps"]) and summary["seconds"] <= 420
    read = lambda name: tar.extractfile(name).read().decode()   # noqa: E731
    assert "CPU capability" in read("logs/preflight_cuda.txt")
    assert "rendered (64, 64, 3)" in read("logs/preflight_egl.txt")
    rows = json.loads(read("logs/bench_train_x1.json"))
    assert {r["variant"] for r in rows} == {"protocad", "dreamer"} and all("sec" in r for r in rows)
    assert "walker_walk" in read("logs/bench_envs.txt")
    doc = json.loads(read("compare/results.json"))
    validate(doc)    # jsonschema is importable here, in the test process
    assert sorted(r["label"] for r in doc["runs"]) == ["dreamer", "protocad"]
    assert all(r["status"] == "finished" and r["final"] is not None for r in doc["runs"])
    assert all(r["final_train"] is not None and r["prototype_freeze"] in (None, 0) for r in doc["runs"])
    # the random baseline plays the runs' final evaluation: their 2 contexts, 1 episode each
    rnd = json.loads(read("compare/pendulum_swingup/random.json"))
    assert [c["context"] for c in rnd["per_context"]] == [{"m": 0.2}, {"m": 1.8}] and rnd["episodes"] == 2
    names = tar.getnames()
    assert "compare/curves.png" in names
    assert "rerun: not written (rerun-sdk is not installed)" in read("logs/compare.txt")
    for variant in ("protocad", "dreamer"):
        run = f"compare/pendulum_swingup/{variant}/seed5"
        assert f"{run}/online.log" in names and f"{run}/eval/final.json" in names
        assert not any(n.startswith((f"{run}/checkpoints", f"{run}/bags")) for n in names)


def test_a_machine_without_cuda_stops_at_the_preflight(tmp_path):
    # the real fault: this machine has no GPU, so the campaign proper must not start here
    p, summary, tar = campaign(tmp_path, "--deadline", "120", timeout=300)
    assert p.returncode == 1
    assert [s["step"] for s in summary["steps"]] == ["preflight_cuda", "preflight_egl"]
    assert summary["preflight_ok"] is False and "preflight failed: preflight_cuda" in p.stdout
    assert "logs/preflight_cuda.txt" in tar.getnames()
