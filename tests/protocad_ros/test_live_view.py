"""The policy's live rerun stream (protocad_ros/live_view.py): real .rrd files read back with
rerun's own reader, a real rerun gRPC server for 'connect', a real tiny agent's features."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys

import helpers
import numpy as np
import pytest

from protocad_ros.live_view import DEFAULT_URL, PARAMETERS, LiveView, check_mode
from trainer.viz.rerun_log import read_recording

ROOT = str(helpers.ROOT)
STEP_PATHS = ["/policy/image", "/policy/features/u", "/policy/features/e", "/policy/assignment",
              "/policy/assignment_top", "/policy/assignment_entropy", "/policy/action",
              "/policy/reward"]


def _rerun_env(tmp_path):
    # The rerun CLI keeps its analytics settings in XDG_CONFIG_HOME: a private, disabled one.
    cfg = tmp_path / "xdg" / "rerun"
    cfg.mkdir(parents=True, exist_ok=True)
    (cfg / "analytics.json").write_text('{"analytics_enabled": false}')
    return {**os.environ, "XDG_CONFIG_HOME": str(tmp_path / "xdg")}


def _rerun_cli():
    return os.path.join(os.path.dirname(sys.executable), "rerun")


@pytest.fixture(scope="module")
def tiny_policy():
    """A real (random-weight) ProtoCAD agent behind protocad_ros.policy.Policy."""
    import torch

    from protocad_ros.model.agent import Agent
    from protocad_ros.model.config import make_config
    from protocad_ros.policy import Policy

    torch.set_num_threads(1)
    cfg = make_config("pendulum_swingup", "small", **{
        "world_model.deter": 32, "world_model.hidden": 32, "world_model.stoch": 8,
        "world_model.cnn_depth": 4, "world_model.mlp_units": 32, "behavior.actor_units": 32,
        "behavior.critic_units": 32, "context.num_prototypes": 6, "context.proto_dim": 8})
    return Policy(Agent(cfg, 1))


def _steps(policy, n=12):
    rng = np.random.default_rng(0)
    prev = np.zeros(1, np.float32)
    for t in range(n):
        image = rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)
        action, feats = policy.act(image, prev, t == 0)
        yield t, image, action, feats
        prev = action


@pytest.mark.process
def test_save_mode_writes_documented_paths_on_sim_time(tmp_path, tiny_policy):
    path = tmp_path / "live" / "policy.rrd"
    view = LiveView("save", path=path, action_names=["torque"])
    stamps = []
    for t, image, action, feats in _steps(tiny_policy):
        stamps.append(1_000_000_000 + t * 20_000_000)   # control_dt 20 ms
        view.log_step(stamps[-1], image, u=feats.u, w=feats.w, e=feats.e, action=action, reward=0.5 * t,
                      is_first=t == 0, context={"m": 0.75})
    assert view.steps == 12
    view.close()
    view.close()  # idempotent

    rec = read_recording(path)
    for p in STEP_PATHS + ["/policy/context/m", "/policy/episode_start"]:
        assert p in rec, f"{p} missing; have {sorted(rec)}"
    for p in STEP_PATHS:
        assert "sim_time" in rec[p]["timelines"], p
    img = rec["/policy/image"]
    assert img["rows"] == 12
    assert sorted(img["columns"]["sim_time"]) == stamps  # exact nanoseconds
    bars = rec["/policy/assignment"]["columns"]["BarChart:values"]
    assert len(bars) == 12 and bars[0][0]["shape"] == [6]  # K prototypes
    u = rec["/policy/features/u"]["columns"]["BarChart:values"][0][0]
    assert u["shape"] == [len(tiny_policy.act(np.zeros((64, 64, 3), np.uint8),
                                              np.zeros(1, np.float32), True)[1].u)]
    rewards = [r[0] for r in rec["/policy/reward"]["columns"]["Scalars:scalars"]]
    assert sorted(rewards) == [0.5 * t for t in range(12)]
    names = rec["/policy/action"]["columns"]["SeriesLines:names"]
    assert ["torque"] in names
    assert rec["/policy/episode_start"]["rows"] == 1
    assert rec["__blueprints"]["rows"] == 1

    out = subprocess.run([_rerun_cli(), "rrd", "verify", str(path)], capture_output=True,
                         text=True, env=_rerun_env(tmp_path), timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr


def test_on_act_takes_the_policy_nodes_act_event(tmp_path, tiny_policy):
    from protocad_ros.node.policy_node import ActEvent
    from sim_bridge.contract.topics import StepInfo

    path = tmp_path / "node.rrd"
    with LiveView.from_params(rerun_mode="save", rerun_url="", rerun_path=str(path)) as view:
        for t, image, action, feats in _steps(tiny_policy, 5):
            info = StepInfo(reward=1.0, discount=1.0, is_first=t == 0, is_last=False,
                            is_terminal=False, episode=0, step=t)
            view.on_act(ActEvent(t * 1000, info, image, action, feats, 0.001, -1))
    rec = read_recording(path)
    assert rec["/policy/image"]["rows"] == 5
    assert rec["/policy/assignment"]["rows"] == 5
    assert rec["/policy/episode_start"]["rows"] == 1


def test_variant_without_context_features_logs_the_rest(tmp_path):
    path = tmp_path / "dreamer.rrd"
    view = LiveView("save", path=path)
    empty = np.zeros(0, np.float32)
    view.log_step(0, np.zeros((64, 64, 3), np.uint8), u=empty, w=empty, e=empty, action=[0.1, -0.2], reward=0.0)
    view.close()
    rec = read_recording(path)
    assert "/policy/image" in rec and "/policy/action" in rec
    assert "/policy/assignment" not in rec and "/policy/features/u" not in rec


@pytest.mark.process
def test_off_mode_is_free_and_imports_no_rerun():
    code = ("import sys, numpy as np\n"
            "from protocad_ros.live_view import LiveView\n"
            "v = LiveView()\n"
            "v.log_step(0, np.zeros((64, 64, 3), np.uint8), u=[1.0], w=[1.0], e=[1.0], action=[0.0], reward=1.0)\n"
            "v.close()\n"
            "assert not v.enabled and v.steps == 0\n"
            "assert 'rerun' not in sys.modules, 'rerun imported in off mode'\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr


@pytest.mark.process
def test_bad_arguments_are_clear_errors(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="valid modes"):
        LiveView("stream")
    with pytest.raises(ValueError, match="needs a path"):
        LiveView("save")
    with pytest.raises(ValueError, match=r"\.rrd"):
        LiveView("save", path=tmp_path / "x.txt")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(ValueError, match="needs a display"):
        LiveView("spawn")
    view = LiveView("save", path=tmp_path / "bad.rrd")
    with pytest.raises(ValueError, match="uint8"):
        view.log_step(0, np.zeros((64, 64, 3), np.float32))
    with pytest.raises(ValueError, match=">= 0"):
        view.log_step(-1, None)
    view.close()
    assert check_mode(" Save ") == "save"
    assert PARAMETERS == {"rerun_mode": "off", "rerun_url": "", "rerun_path": ""}
    assert DEFAULT_URL.startswith("rerun+http://127.0.0.1:")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.process
@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # a server's stream file
def test_connect_mode_streams_to_a_rerun_server(tmp_path, tiny_policy):
    """A headless rerun gRPC server on loopback saves what it receives; what LiveView sent in
    'connect' mode must be in that file."""
    port = _free_port()
    saved = tmp_path / "server.rrd"
    server = subprocess.Popen([_rerun_cli(), "--bind", "127.0.0.1", "--port", str(port),
                               "--save", str(saved)], env=_rerun_env(tmp_path),
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              start_new_session=True)
    try:
        def listening() -> bool:
            with socket.socket() as s:
                return s.connect_ex(("127.0.0.1", port)) == 0

        helpers.wait_until(listening, 20, "the rerun server to listen", 0.1)
        view = LiveView.from_params("connect", f"rerun+http://127.0.0.1:{port}/proxy", "")
        for t, image, action, feats in _steps(tiny_policy, 6):
            view.log_step(t * 20_000_000, image, u=feats.u, w=feats.w, e=feats.e, action=action, reward=1.0)
        view.close()
        def six_steps() -> dict:
            if not (saved.exists() and saved.stat().st_size > 0):
                return {}
            try:
                rec = read_recording(saved)
            except Exception:  # noqa: BLE001 - mid-write
                return {}
            # Every entity checked below: the server writes chunks as they arrive, so its file
            # can hold the 6th image before the 6th assignment.
            whole = all(rec.get(e, {}).get("rows") == 6 for e in ("/policy/image", "/policy/assignment"))
            return rec if whole else {}

        rec = helpers.wait_until(six_steps, 20, "the server's recording of 6 images and assignments", 0.2)
    finally:
        # The whole group: `rerun` is a Python wrapper whose child, the native server, would
        # outlive a signal to the wrapper alone (each run of this test left one behind).
        os.killpg(server.pid, signal.SIGINT)
        try:
            server.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
    assert rec.get("/policy/image", {}).get("rows") == 6, sorted(rec)
    assert rec["/policy/assignment"]["rows"] == 6
