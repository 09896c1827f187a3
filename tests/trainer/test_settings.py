"""Typed settings and the command lines generated from them (trainer/settings.py): flags,
help from field docstrings, what a resume keeps, and the config's order of precedence."""
from __future__ import annotations

from dataclasses import dataclass

import pytest

from trainer import settings
from trainer.settings import arg


@dataclass
class Example:
    """A command's settings."""

    env_steps: int = 1000
    """budget in env steps"""
    names: list[str] | None = arg(None, metavar="NAME")
    """some names"""
    fast: bool = False
    """go fast"""
    limit: float | None = arg(None, "--limit", "--cap", group="limits")
    """an upper bound"""


def parser():
    return settings.settings_parser("example", "An example.", [(None, Example)])


def test_flags_types_and_help_come_from_the_fields():
    p = settings.parse(parser(), ["--env-steps", "5", "--names", "a", "b", "--fast", "--cap", "2.5"],
                       config_help=False)
    assert p.get(Example) == Example(env_steps=5, names=["a", "b"], fast=True, limit=2.5)
    assert p.given == {"env_steps": 5, "names": ["a", "b"], "fast": True, "limit": 2.5}
    text = " ".join(parser().format_help().split())
    assert "budget in env steps (default: 1000)" in text and "limits:" in text and "--limit LIMIT, --cap LIMIT" in text
    with pytest.raises(SystemExit):
        settings.parse(parser(), ["--env-steps", "many"], config_help=False)


def test_a_resume_keeps_the_saved_settings_unless_given_again():
    p = settings.parse(parser(), ["--fast"], config_help=False)
    saved = {"env_steps": 7, "names": ["x"], "fast": False, "limit": 1.0}
    assert settings.resumed(Example, saved, p, parser()) == Example(env_steps=7, names=["x"], fast=True, limit=1.0)
    # a run saved before settings were: its command line
    old = settings.resumed(Example, None, p, parser(), ["--env-steps", "9"])
    assert old == Example(env_steps=9, fast=True)


def test_config_precedence_file_then_set_then_shortcuts_then_config_options(tmp_path):
    (tmp_path / "c.yaml").write_text("train: {batch_size: 4, seq_len: 20}\nworld_model: {deter: 40}\n")
    model = settings.ModelChoice(config=str(tmp_path / "c.yaml"), set=["train.batch_size=6", "world_model.deter=44"],
                                 seq_len=12)
    cfg = model.to_config(["--world_model.deter", "48"])
    assert (cfg.train.batch_size, cfg.train.seq_len, cfg.world_model.deter) == (6, 12, 48)
    assert "order of precedence" in settings.settings_parser(
        "x", "", [(None, settings.ModelChoice)]).format_help()
