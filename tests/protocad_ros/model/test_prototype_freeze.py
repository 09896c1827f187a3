"""The prototype freeze is a share of the run it belongs to: every committed walker ProtoCAD run
once kept DreamerPro's 10,000 updates and made 2,900, so its prototypes never trained."""
from __future__ import annotations

import pytest

from protocad_ros.model.config import MAX_FREEZE_SHARE, Config, ConfigError, make_config, plan_prototype_freeze
from trainer.learn.schedule import Schedule


def _walker(**overrides):
    return make_config("walker_walk", "small", "protocad", reference="dreamerv2", **overrides)


def test_a_30k_env_step_plan_with_default_settings_trains_the_prototypes_for_most_of_it():
    cfg = _walker()
    planned = Schedule(N=cfg.train.prefill_episodes, C=cfg.train.collect_interval).planned_updates(
        30_000, cfg.train.time_limit)
    assert planned == 2_900                     # the comparison's runs: 28 collected episodes x 100 + 100
    freeze = plan_prototype_freeze(cfg, 0, planned)
    assert freeze == 290
    assert (planned - freeze) / planned >= 0.75
    # the same default for a paper-length run keeps DreamerPro's own share: 10k of 100k
    assert plan_prototype_freeze(cfg, 0, 100_000) == 10_000


def test_a_plan_frozen_past_a_quarter_is_refused_in_one_line_unless_asked_for():
    cfg = _walker(**{"context.freeze_prototypes_updates": 10_000})
    with pytest.raises(ConfigError) as err:
        plan_prototype_freeze(cfg, 0, 2_900)
    message = str(err.value)
    assert "\n" not in message and "2,900 of this run's 2,900 updates" in message
    assert "context.allow_long_freeze=true" in message and "-1 (auto" in message
    allowed = _walker(**{"context.freeze_prototypes_updates": 10_000, "context.allow_long_freeze": True})
    assert plan_prototype_freeze(allowed, 0, 2_900) == 10_000
    # exactly a quarter is still a run that trains its prototypes
    quarter = _walker(**{"context.freeze_prototypes_updates": int(MAX_FREEZE_SHARE * 2_900)})
    assert plan_prototype_freeze(quarter, 0, 2_900) == 725


def test_a_continued_run_counts_only_its_own_updates():
    # a policy trained to 5,900 updates and continued to 6,000: a 600-update freeze is behind it
    assert plan_prototype_freeze(_walker(), 5_900, 6_000) == 600
    explicit = _walker(**{"context.freeze_prototypes_updates": 5_990})
    with pytest.raises(ConfigError, match="90 of this run's 100 updates"):
        plan_prototype_freeze(explicit, 5_900, 6_000)


def test_variants_without_prototypes_have_no_freeze():
    assert plan_prototype_freeze(make_config("walker_walk", "small", "dreamer"), 0, 2_900) is None
    assert plan_prototype_freeze(make_config("walker_walk", "small", "dreamerpro"), 0, 2_900) == 290


def test_configs_written_before_the_scaled_freeze_read_its_old_default_as_auto():
    old = _walker().to_dict()
    del old["context"]["freeze_prototypes_fraction"], old["context"]["allow_long_freeze"]
    old["context"]["freeze_prototypes_updates"] = 10_000
    assert Config.from_dict(old).context.freeze_prototypes_updates == -1
    chosen = dict(old, context={**old["context"], "freeze_prototypes_updates": 50})
    assert Config.from_dict(chosen).context.freeze_prototypes_updates == 50
