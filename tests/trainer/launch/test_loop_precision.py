"""Precision is resolved on the machine that trains: a policy whose config was written on a
bf16 machine asking for `train.precision: bfloat16`, used for --init-policy or resumed on a CPU
without bf16 arithmetic, trains in float32, says so and records it; the shipped policy's `auto`
is float32 there without a word; only --precision bfloat16 on the
command line keeps the emulated path, with a warning. The capability check is overridden
(`cpu_flags`), so this runs on any machine; the loop's trainer is built as `run()` builds it,
without the ROS nodes."""
from __future__ import annotations

import json

import pytest
import torch
import yaml
from helpers.agents import bf16_request_policy

from protocad_ros.model import precision as P
from protocad_ros.policy import shipped_policy
from trainer.launch.loop import Loop, LoopSettings
from trainer.settings import ModelChoice

AVX2_ONLY = {"fpu", "sse4_2", "avx", "avx2", "fma"}


@pytest.fixture
def no_bf16(monkeypatch, one_torch_thread):
    """This CPU, seen as an AVX2-only one (bf16 emulated)."""
    monkeypatch.setattr(P, "cpu_flags", lambda: set(AVX2_ONLY))


def compute_dtype(agent) -> torch.dtype:
    """The dtype a layer computes in inside the agent's training autocast."""
    layer = next(m for m in agent.modules() if isinstance(m, torch.nn.Linear))
    with agent._autocast():
        return layer(torch.zeros(1, layer.in_features, device=agent.device)).dtype


def open_loop(s: LoopSettings, model: ModelChoice = ModelChoice()) -> Loop:
    loop = Loop(s, model)
    loop._setup()
    loop._open_trainer()
    return loop


def test_the_shipped_policy_asks_for_auto_and_trains_in_float32_without_bf16(no_bf16, tmp_path, capsys):
    policy = shipped_policy("walker_walk")
    if policy is None:
        pytest.skip("the package ships no walker_walk policy")
    loop = open_loop(LoopSettings(init_policy=str(policy), run_dir=str(tmp_path / "run"), start_eval_episodes=0))
    assert loop.cfg.train.precision == "auto"
    assert loop.trainer.agent.precision.precision == "float32" and compute_dtype(loop.trainer.agent) == torch.float32
    assert "emulate" not in capsys.readouterr().out
    loop.trainer.close()


def test_init_policy_and_resume_of_a_bf16_config_train_in_float32_without_bf16(no_bf16, tmp_path, capsys):
    policy = bf16_request_policy(tmp_path / "bf16.pt")
    if policy is None:
        pytest.skip("the package ships no walker_walk policy")
    run = tmp_path / "run"
    loop = open_loop(LoopSettings(init_policy=str(policy), run_dir=str(run), start_eval_episodes=0))
    assert loop.cfg.train.precision == "bfloat16"   # the policy's config asks ...
    agent = loop.trainer.agent
    assert agent.precision.precision == "float32" and compute_dtype(agent) == torch.float32   # ... this CPU says no
    # the shipped bf16 weights loaded into float32 parameters, values kept
    shipped = torch.load(policy, map_location="cpu", weights_only=True)["modules"]
    name = "wm.encoder.convs.0.weight"
    assert agent.state_dict()[name].dtype == torch.float32
    assert torch.equal(agent.state_dict()[name], shipped[name].float())
    out = capsys.readouterr().out
    assert "[loop] precision float32: the config asks for bfloat16, which cpu would emulate" in out, out
    recorded = json.loads((run / "run.json").read_text())["precision"]
    assert (recorded["precision"], recorded["requested"], recorded["explicit"], recorded["emulated"]) == (
        "float32", "bfloat16", False, True)
    # config.yaml keeps the request (a bf16 machine resuming this run trains in bf16) and says,
    # on the same line, what it ran in here; so does the checkpoint's
    assert yaml.safe_load((run / "config.yaml").read_text())["train"]["precision"] == "bfloat16"
    ran_here = "  precision: bfloat16  # ran in float32 here (cpu, CPU capability "
    assert ran_here in (run / "config.yaml").read_text()
    loop.trainer.save()
    loop.trainer.close()
    assert ran_here in (run / "checkpoints" / "config.yaml").read_text()

    # --resume of that run (its config and checkpoint say bfloat16): float32 again
    resumed = open_loop(LoopSettings(run_dir=str(run), resume=True))
    assert resumed.trainer.agent.precision.precision == "float32"
    assert compute_dtype(resumed.trainer.agent) == torch.float32
    assert "precision float32: the config asks for bfloat16" in capsys.readouterr().out
    assert json.loads((run / "run.json").read_text())["precision"]["precision"] == "float32"
    resumed.trainer.close()


def test_an_explicit_precision_bfloat16_is_kept_and_warned_about(no_bf16, tmp_path, capsys):
    policy = bf16_request_policy(tmp_path / "bf16.pt")
    if policy is None:
        pytest.skip("the package ships no walker_walk policy")
    run = tmp_path / "run"
    loop = open_loop(LoopSettings(init_policy=str(policy), run_dir=str(run), start_eval_episodes=0),
                     ModelChoice(precision="bfloat16"))
    assert loop.trainer.agent.precision.precision == "bfloat16"
    assert compute_dtype(loop.trainer.agent) == torch.bfloat16
    out = capsys.readouterr().out
    assert "[loop] warning: precision bfloat16 as --precision asked, but cpu emulates it" in out, out
    recorded = json.loads((run / "run.json").read_text())["precision"]
    assert (recorded["precision"], recorded["explicit"], recorded["emulated"]) == ("bfloat16", True, True)
    assert "no bf16 arithmetic" in recorded["capability"]
    loop.trainer.close()
    # the same run resumed without the flag: the config's bfloat16 is a request again
    assert open_loop(LoopSettings(run_dir=str(run), resume=True)).trainer.agent.precision.precision == "float32"


def test_auto_in_a_config_resolves_on_each_machine(monkeypatch, tmp_path):
    """A config saying 'auto' (what --precision auto stores) is bfloat16 on a bf16 CPU and
    float32 on an AVX2-only one: the same file, two machines."""
    from protocad_ros.model.agent import make_agent
    from protocad_ros.model.config import make_config

    cfg = make_config("pendulum_swingup", "small", **{"train.precision": "auto"})
    monkeypatch.setattr(P, "cpu_flags", lambda: AVX2_ONLY | {"avx512_bf16"})
    assert make_agent(cfg, 1).precision.precision == "bfloat16"
    monkeypatch.setattr(P, "cpu_flags", lambda: set(AVX2_ONLY))
    assert make_agent(cfg, 1).precision.precision == "float32"
