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


def test_a_node_parameter_table_generates_its_options_and_a_library_setting_none():
    """table_settings: one field per Param row (flag, type, default, choices, help from the row,
    unless its form says otherwise; a None form: no option); arg(flag=False): no option."""
    from sim_bridge.nodekit.param_table import Param, with_defaults

    table = (Param("chunk_size", 10, "bytes per chunk"), Param("topics", (), "what to record"),
             Param("compression", "zstd", "how", choices=("zstd", "none")), Param("poll_s", 0.2, "in ms below"))
    cls = settings.table_settings("T", table, {"topics": {"flags": ("topics",), "nargs": "*"},
                                               "compression": {"default": None}, "poll_s": None})

    @dataclass
    class Own:
        shown: int = 1
        """an option"""
        hidden: int = arg(2, flag=False)
        """a library caller's"""

    p = settings.settings_parser("node", "A node.", [(None, cls), (None, Own)])
    a = vars(p.parse_args(["/a", "/b", "--chunk-size", "7"]))
    assert a == {"chunk_size": 7, "topics": ["/a", "/b"], "compression": None, "shown": 1}
    with pytest.raises(SystemExit):
        p.parse_args(["--compression", "lz4"])
    assert "bytes per chunk (default: 10)" in " ".join(p.format_help().split())
    declared = {r.name: r.default for r in with_defaults(table, {"chunk_size": "7", "topics": ["/a"]})}
    assert declared == {"chunk_size": 7, "topics": ("/a",), "compression": "zstd", "poll_s": 0.2}


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
