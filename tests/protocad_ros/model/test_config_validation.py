"""Configs are refused before anything is built: values out of range, non-finite numbers, sizes
beyond what one process can hold, a --config that is missing, a directory or broken YAML."""
from __future__ import annotations

import subprocess
import sys

import pytest

from protocad_ros.model.config import ConfigError, check_train_memory, estimate_train_memory, make_config
from protocad_ros.model.hyperparameters import PRESETS


@pytest.mark.parametrize("key,value,says", [
    ("world_model.mlp_layers", -1, "out of range"),
    ("world_model.cnn_depth", 0, "out of range"),
    ("behavior.actor_units", -8, "out of range"),
    ("behavior.horizon", 100_000_000, "out of range"),
    ("train.batch_size", 100_000_000, "out of range"),
    ("context.num_prototypes", 2_000_000_000, "out of range"),
    ("behavior.discount", 5, "(0, 1]"),
    ("behavior.discount", 0, "(0, 1]"),
    ("world_model.kl_balance", 1.5, "[0, 1]"),
    ("behavior.grad_clip", -1, "out of range"),
    ("world_model.kl_free", float("nan"), "finite"),
    ("world_model.lr", float("inf"), "finite"),
    ("world_model.eps", 0, "out of range"),
    ("drq.discount", 1.5, "out of range"),
])
def test_values_out_of_range_are_refused_with_the_key(key, value, says):
    with pytest.raises(ConfigError) as err:
        make_config("walker_walk", "small", "protocad", **{key: value})
    assert key in str(err.value) and says in str(err.value)


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_fits_a_16_gb_machine(preset):
    for variant in ("protocad", "dreamer", "dreamerpro"):
        cfg = make_config("walker_walk", preset, variant, **{"train.memory_limit_gb": 16})
        check_train_memory(cfg)


def test_a_config_too_large_to_train_is_refused_before_allocating_and_the_limit_is_settable():
    big = make_config("walker_walk", "small", "protocad", **{"behavior.horizon": 1000, "train.batch_size": 4096,
                                                              "train.memory_limit_gb": 16})
    assert estimate_train_memory(big) > 100 * 2**30
    with pytest.raises(ConfigError, match="train.memory_limit_gb"):
        check_train_memory(big)
    check_train_memory(big.replace(**{"train.memory_limit_gb": 1e5}))   # the override


@pytest.mark.process
@pytest.mark.parametrize("config,says", [("missing.yaml", "No such file"), (".", "Is a directory"),
                                         ("bad.yaml", "not valid YAML (line 2")])
def test_a_bad_config_file_is_one_line_and_exit_2(tmp_path, config, says):
    (tmp_path / "bad.yaml").write_text("train: [1\n")
    r = subprocess.run([sys.executable, "-m", "trainer.learn.train", "--config", str(tmp_path / config),
                        "--logs", str(tmp_path), "--run-dir", str(tmp_path / "run")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    err = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(err) == 1 and says in err[0] and "Traceback" not in r.stderr, r.stderr
