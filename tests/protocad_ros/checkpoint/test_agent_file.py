"""Agent checkpoints: round trip (same actions, optimizer state, counters), atomic writes, and
clear CheckpointErrors for truncated, corrupt, foreign and incompatible files."""
from __future__ import annotations

import os
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import torch
from helpers import ROOT

from protocad_ros.checkpoint import agent_file
from protocad_ros.checkpoint.agent_file import load_checkpoint, read_checkpoint, restore_checkpoint, save_checkpoint
from protocad_ros.checkpoint.files import CONFIG_NAME, FORMAT, VERSION, CheckpointError
from protocad_ros.model.agent import Agent
from protocad_ros.model.config import Config, make_config
from protocad_ros.policy import Policy

T = 8


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def tiny(variant="protocad", **kw):
    over = {"world_model.deter": 32, "world_model.hidden": 32, "world_model.stoch": 8,
            "world_model.cnn_depth": 8, "world_model.mlp_layers": 1, "world_model.mlp_units": 32,
            "behavior.actor_layers": 1, "behavior.actor_units": 32, "behavior.critic_layers": 1,
            "behavior.critic_units": 32, "behavior.horizon": 3, "train.batch_size": 2,
            "train.seq_len": T, "context.num_prototypes": 8}
    over.update(kw)
    return make_config("cheetah_run", "small", variant, **over)


@pytest.fixture(scope="module")
def frames():
    """Real cheetah frames (2 sequences x T steps) with the random actions that produced them."""
    from sim_bridge.sim.envs import ContextDMCEnv

    rng = np.random.default_rng(0)
    env = ContextDMCEnv("cheetah_run", seed=1)
    batch = {"image": np.zeros((2, T, 64, 64, 3), np.uint8),
             "action": np.zeros((2, T, 6), np.float32), "reward": np.zeros((2, T), np.float32),
             "discount": np.ones((2, T), np.float32), "is_first": np.zeros((2, T), bool)}
    try:
        for b in range(2):
            obs = env.reset()
            batch["image"][b, 0], batch["is_first"][b, 0] = obs.image, True
            for t in range(1, T):
                a = rng.uniform(-1, 1, 6).astype(np.float32)
                obs = env.step(a)
                batch["image"][b, t], batch["action"][b, t] = obs.image, a
                batch["reward"][b, t] = obs.reward
    finally:
        env.close()
    return batch


@pytest.fixture(scope="module")
def trained(frames):
    agent = Agent(tiny(), action_dim=6)
    for _ in range(2):
        agent.train_step(frames)
    return agent


def _actions(agent, frames, mode="deterministic"):
    policy = Policy(agent, mode=mode, seed=7)
    out = []
    for t in range(T):
        a, f = policy.act(frames["image"][0, t], frames["action"][0, t], t == 0)
        out.append(np.concatenate([a, f.u, f.w, f.e]))
    return np.stack(out)


def test_round_trip_same_actions_and_state(tmp_path, trained, frames):
    path = save_checkpoint(tmp_path / "agent.pt", trained, counters={"env_steps": 1234,
                                                                    "run": "x"})
    assert (tmp_path / CONFIG_NAME).is_file()
    assert Config.load(tmp_path / CONFIG_NAME) == trained.cfg
    agent, counters = load_checkpoint(path)
    assert counters == {"env_steps": 1234, "run": "x"}
    assert agent.counters() == trained.counters() == {"updates": 2}
    for mode in ("deterministic", "sample"):
        assert np.array_equal(_actions(agent, frames, mode), _actions(trained, frames, mode))
    for name, opt in trained.optimizers().items():
        mine, theirs = opt.state_dict(), agent.optimizers()[name].state_dict()
        assert mine["param_groups"] == theirs["param_groups"]
        for k, st in mine["state"].items():
            assert torch.equal(st["exp_avg"], theirs["state"][k]["exp_avg"])
    # Training continues identically from the checkpoint (same RNG, same states).
    torch.manual_seed(5)
    m1 = trained.train_step(frames)
    torch.manual_seed(5)
    m2 = agent.train_step(frames)
    assert m1["wm_loss"] == pytest.approx(m2["wm_loss"], rel=1e-5)
    # Policy.from_checkpoint works on the file too.
    policy = Policy.from_checkpoint(path)
    a, _ = policy.act(frames["image"][0, 0], np.zeros(6), True)
    assert a.shape == (6,)


def test_an_agent_that_only_acts_builds_no_optimizers(tmp_path, trained, frames):
    """Serving or evaluating a training checkpoint skips its optimizer states: they are never
    built, and training from the same agent later starts them fresh."""
    path = save_checkpoint(tmp_path / "agent.pt", trained)
    agent, _ = load_checkpoint(path, restore_rng=False, optimizer_states=False)
    policy = Policy(agent, seed=7)
    policy.act(frames["image"][0, 0], np.zeros(6), True)
    assert agent._optimizers is None
    assert all(not opt.state for opt in agent.optimizers().values())
    assert np.isfinite(agent.train_step(frames)["wm_loss"])


def test_serving_a_policy_imports_no_compiler():
    """Loading a policy (every policy-node and evaluator start) imports neither torch's compiler
    nor sympy: the optimizers it does not need and the meta-device shape check both did, ~1.3
    CPU-s per start."""
    code = ("import sys; from protocad_ros.policy import Policy; "
            f"Policy.from_checkpoint({str(ROOT / 'protocad_ros/policies/walker_walk.pt')!r}); "
            "print(sorted(m for m in ('torch._dynamo', 'sympy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_file_is_weights_only_loadable(tmp_path, trained):
    path = save_checkpoint(tmp_path / "a.pt", trained, rng_state=True)
    payload = torch.load(path, weights_only=True)
    assert payload["format"] == FORMAT and payload["version"] == VERSION
    assert payload["action_dim"] == 6 and payload["config"]["variant"] == "protocad"
    assert set(payload["optimizers"]) == {"world_model", "actor", "critic"}
    assert "torch_rng" in payload


def test_failed_write_leaves_old_file_intact(tmp_path, trained, monkeypatch, frames):
    path = save_checkpoint(tmp_path / "agent.pt", trained, counters={"v": 1})
    old = path.read_bytes()

    def broken_save(obj, f, *a, **kw):
        f.write(b"PK\x03\x04 half a checkpoint")
        raise OSError("disk full")

    monkeypatch.setattr(agent_file.torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, trained, counters={"v": 2})
    monkeypatch.undo()
    assert path.read_bytes() == old
    assert sorted(os.listdir(tmp_path)) == sorted([CONFIG_NAME, "agent.pt"])  # no temp file
    assert load_checkpoint(path)[1] == {"v": 1}


def test_truncated_and_corrupt_files(tmp_path, trained):
    path = save_checkpoint(tmp_path / "agent.pt", trained)
    data = path.read_bytes()
    for n in (0, 10, len(data) // 2, len(data) - 100):
        bad = tmp_path / f"trunc{n}.pt"
        bad.write_bytes(data[:n])
        with pytest.raises(CheckpointError, match=r"trunc\d+\.pt: (empty|truncated|corrupt)"):
            load_checkpoint(bad)
    # A complete archive whose pickle is damaged.
    bad = tmp_path / "corrupt.pt"
    with zipfile.ZipFile(path) as zin, zipfile.ZipFile(bad, "w") as zout:
        for item in zin.infolist():
            blob = zin.read(item.filename)
            if item.filename.endswith("data.pkl"):
                blob = b"\x80\x02garbage" + blob[10:]
            zout.writestr(item, blob)
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(bad)
    with pytest.raises(CheckpointError, match="no such"):
        load_checkpoint(tmp_path / "missing.pt")


def test_foreign_files(tmp_path):
    text = tmp_path / "notes.pt"
    text.write_text("hello, not a checkpoint\n")
    with pytest.raises(CheckpointError, match="not a checkpoint"):
        load_checkpoint(text)
    other = tmp_path / "other.pt"
    torch.save({"state_dict": {"w": torch.zeros(3)}}, other)
    with pytest.raises(CheckpointError, match="not a protocad-ros agent checkpoint"):
        load_checkpoint(other)
    tensor = tmp_path / "tensor.pt"
    torch.save(torch.zeros(3), tensor)
    with pytest.raises(CheckpointError, match="not a protocad-ros agent checkpoint"):
        load_checkpoint(tensor)

    class Evil:  # a pickle that would run code: refused by weights_only loading
        def __reduce__(self):
            return (os.system, ("true",))

    evil = tmp_path / "evil.pt"
    torch.save({"format": FORMAT, "x": Evil()}, evil)
    with pytest.raises(CheckpointError, match="weights_only"):
        load_checkpoint(evil)


def test_incompatible_checkpoints(tmp_path, trained):
    path = save_checkpoint(tmp_path / "agent.pt", trained)
    with pytest.raises(CheckpointError, match="action_dim=6.*action_dim=1"):
        load_checkpoint(path, action_dim=1)
    payload = read_checkpoint(path)
    future = dict(payload, version=VERSION + 1)
    torch.save(future, tmp_path / "future.pt")
    with pytest.raises(CheckpointError, match="version"):
        load_checkpoint(tmp_path / "future.pt")
    bad_cfg = dict(payload, config={**payload["config"], "variant": "dreamerv9"})
    torch.save(bad_cfg, tmp_path / "badcfg.pt")
    with pytest.raises(CheckpointError, match="incompatible config.*dreamerv9"):
        load_checkpoint(tmp_path / "badcfg.pt")
    unknown = dict(payload, config={**payload["config"], "extra_section": {}})
    torch.save(unknown, tmp_path / "unknown.pt")
    with pytest.raises(CheckpointError, match="extra_section"):
        load_checkpoint(tmp_path / "unknown.pt")
    # Weights that do not fit the config they claim.
    lying = dict(payload, config={**payload["config"],
                                  "world_model": {**payload["config"]["world_model"], "deter": 48}})
    torch.save(lying, tmp_path / "lying.pt")
    with pytest.raises(CheckpointError, match="weights do not fit"):
        load_checkpoint(tmp_path / "lying.pt")
    # Restoring into an agent of another size or variant says what differs.
    with pytest.raises(CheckpointError, match="deter"):
        restore_checkpoint(path, Agent(tiny(**{"world_model.deter": 16}), action_dim=6))
    with pytest.raises(CheckpointError, match="variant"):
        restore_checkpoint(path, Agent(tiny("dreamer"), action_dim=6))
    # what the projector reads sets its input width: another network too
    with pytest.raises(CheckpointError, match="context.projector_input: 's' != 'h'"):
        restore_checkpoint(path, Agent(tiny(**{"context.projector_input": "s"}), action_dim=6))
    with pytest.raises(CheckpointError, match="action_dim"):
        restore_checkpoint(path, Agent(tiny(), action_dim=2))


def test_a_file_whose_config_claims_huge_networks_is_refused_before_they_are_built(tmp_path, trained):
    """The shapes are compared on the meta device: a 16384-wide GRU (3 GB of weights if built)
    and an action size of a billion cost nothing; a caller's `fits` refuses before that."""
    import resource

    from protocad_ros.checkpoint.files import CheckpointMismatch

    payload = read_checkpoint(save_checkpoint(tmp_path / "agent.pt", trained))
    wm = payload["config"]["world_model"]
    for name, bad in [("deter", dict(payload, config={**payload["config"], "world_model": {**wm, "deter": 16384}})),
                      ("dim", dict(payload, action_dim=10**9))]:
        torch.save(bad, tmp_path / f"{name}.pt")
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        with pytest.raises(CheckpointError, match="weights do not fit the file's own config"):
            load_checkpoint(tmp_path / f"{name}.pt")
        assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak < 500_000   # KiB

    def only_walker(cfg, action_dim):
        if cfg.task != "walker_walk":
            raise CheckpointMismatch(f"it is for {cfg.task}")

    built = []
    with pytest.raises(CheckpointMismatch, match="it is for cheetah_run"):
        load_checkpoint(tmp_path / "agent.pt", fits=lambda c, d: (built.append(1), only_walker(c, d)))
    assert built == [1]


def test_only_the_trainers_resume_takes_the_files_rng_state(tmp_path, trained):
    path = save_checkpoint(tmp_path / "agent.pt", trained, rng_state=True)
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    load_checkpoint(path, restore_rng=False)
    Policy.from_checkpoint(path)
    assert torch.equal(torch.rand(3), expected)          # serving never reseeds the process
    torch.manual_seed(123)
    load_checkpoint(path)                                # the trainer's exact resume does
    assert not torch.equal(torch.rand(3), expected)


def test_restore_into_running_agent(tmp_path, trained, frames):
    path = save_checkpoint(tmp_path / "agent.pt", trained, counters={"episodes": 3})
    fresh = Agent(tiny(**{"world_model.lr": 1e-3}), action_dim=6)  # training-only field differs
    assert restore_checkpoint(path, fresh) == {"episodes": 3}
    assert np.array_equal(_actions(fresh, frames), _actions(trained, frames))


@pytest.mark.process
def test_interrupted_write_leftovers_are_removed_at_the_next_start(tmp_path):
    """A checkpoint write killed mid-way (SIGKILL: no cleanup) leaves .latest.pt.PID.*.tmp; the
    next Trainer on that run directory removes it, and never a live writer's file."""
    import subprocess
    import sys

    from protocad_ros.atomic import remove_stale_temporaries
    from protocad_ros.model.config import make_config
    from trainer.learn.trainer import Trainer

    ckpt = tmp_path / "checkpoints" / "latest.pt"
    code = ("import os, signal, sys; from protocad_ros.atomic import atomic_open\n"
            f"with atomic_open({str(ckpt)!r}) as f:\n"
            "    f.write(b'x' * 100000); f.flush(); os.kill(os.getpid(), signal.SIGKILL)\n")
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT)
    assert p.returncode == -9
    left = list(ckpt.parent.glob(".latest.pt.*.tmp"))
    assert len(left) == 1 and left[0].stat().st_size == 100000
    mine = ckpt.parent / f".latest.pt.{os.getpid()}.inprogress.tmp"
    live = ckpt.parent / ".latest.pt.1.inprogress.tmp"          # pid 1 is alive
    mine.write_bytes(b"")
    live.write_bytes(b"")
    Trainer(make_config("pendulum_swingup", "small", "dreamer"), tmp_path, None, action_dim=1)
    assert not left[0].exists() and mine.exists() and live.exists()
    assert remove_stale_temporaries(ckpt) == []


def test_full_disk_checkpoint_write_is_a_clear_error_and_the_last_good_one_stays(tmp_path):
    import subprocess

    from protocad_ros.checkpoint.agent_file import load_checkpoint
    from protocad_ros.model.config import make_config
    from trainer.learn.trainer import CheckpointWriteError, Trainer

    mnt = tmp_path / "disk"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=40m", "tmpfs", str(mnt)]).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        tr = Trainer(make_config("pendulum_swingup", "small", "dreamer"), mnt / "run", None, action_dim=1)
        first = tr.save()
        size = first.stat().st_size
        free = os.statvfs(mnt).f_bavail * os.statvfs(mnt).f_frsize
        (mnt / "filler").write_bytes(bytes(max(0, free - size // 2)))   # room for half a checkpoint
        tr.agent.updates += 7
        with pytest.raises(CheckpointWriteError, match=r"update 7 failed: No space left on device; the "
                                                       r"last good checkpoint there is intact \(update 0\)"):
            tr.save()
        agent, _ = load_checkpoint(first)
        assert int(agent.counters()["updates"]) == 0
        assert not list(first.parent.glob(".*.tmp"))
        tr.close()
    finally:
        subprocess.run(["umount", "-l", str(mnt)])


def test_the_torch_free_checkpoint_modules_import_without_torch():
    """Node-side and CLI code imports these at its top: a node's --help, its parameter and
    signature checks and a checkpoint's receipt must not pay for torch (agent_file.py does)."""
    import subprocess
    import sys

    code = ("import sys; import protocad_ros.checkpoint.files, protocad_ros.checkpoint.limits, "
            "protocad_ros.checkpoint.signing; print(sorted(m for m in sys.modules if m.split('.')[0] == 'torch'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
