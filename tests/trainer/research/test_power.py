"""Sizing a paired comparison (trainer/research/statistics.py, `protocad-compare --power`): the
paired t-test's power is the one a simulation of the test gives, the detectable effect and the
pairs needed answer each other, DreamerV2's curves are read only where they have a point, and the
committed table and results.md's figures are what the code computes now."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
from helpers import ROOT

from trainer.research import compare
from trainer.research.report import power_lines, power_markdown
from trainer.research.statistics import (
    WALKER_GRID_DIFFS,
    detectable_effect,
    dreamerv2_curve,
    paired_difference,
    pairs_needed,
    power_of,
    power_table,
)

TABLE = ROOT / "msgs_docs" / "results" / "power_table.json"
RESULTS_MD = ROOT / "msgs_docs" / "results.md"
WALKER_GRID = ROOT / "msgs_docs" / "results" / "walker_paired_small.json"


@pytest.mark.parametrize("pair_sd,effect", [(49.2, 5.2), (49.2, 60.0), (11.5, 9.0), (82.3, 94.4), (1.0, 3.0)])
def test_pairs_needed_is_the_fewest_pairs_that_reach_the_power(pair_sd, effect):
    n = pairs_needed(effect, pair_sd)
    assert n >= 2 and power_of(effect, pair_sd, n) >= 0.8
    assert n == 2 or power_of(effect, pair_sd, n - 1) < 0.8


@pytest.mark.parametrize("pair_sd,n", [(49.2, 2), (49.2, 5), (11.5, 15), (30.0, 40)])
def test_detectable_effect_and_pairs_needed_answer_each_other(pair_sd, n):
    effect = detectable_effect(pair_sd, n)
    assert power_of(effect, pair_sd, n) == pytest.approx(0.8, abs=1e-6)
    assert pairs_needed(effect * 1.0001, pair_sd) == n       # just above it: n pairs suffice
    assert pairs_needed(effect * 0.9999, pair_sd) == n + 1   # just below: they do not
    assert power_of(-effect, pair_sd, n) == power_of(effect, pair_sd, n)   # two-sided


def test_the_power_is_the_paired_t_tests_as_simulated_not_the_normal_approximation():
    """4,000 simulated grids of 6 pairs (differences normal, mean 30, SD 40), each tested with the
    two-sided paired t-test at 0.05: the share that rejects is power_of's figure, within 4
    standard errors; the normal approximation (0.45) is far outside that."""
    from scipy import stats

    effect, sd, n, trials = 30.0, 40.0, 6, 4000
    diffs = np.random.default_rng(0).normal(effect, sd, size=(trials, n))
    t = diffs.mean(1) / (diffs.std(1, ddof=1) / np.sqrt(n))
    simulated = float(np.mean(np.abs(t) > stats.t.ppf(0.975, n - 1)))
    tolerance = 4 * np.sqrt(simulated * (1 - simulated) / trials)
    assert power_of(effect, sd, n) == pytest.approx(simulated, abs=tolerance)
    normal = stats.norm.cdf(effect / sd * np.sqrt(n) - stats.norm.ppf(0.975))
    assert abs(normal - simulated) > 3 * tolerance


def test_power_of_no_effect_is_alpha_and_no_effect_needs_no_finite_grid():
    assert power_of(0.0, 49.2, 5) == pytest.approx(0.05, abs=1e-9)
    with pytest.raises(ValueError, match="more than 100 pairs"):
        pairs_needed(0.0, 49.2, max_pairs=100)
    with pytest.raises(ValueError, match="at least 2 pairs"):
        power_of(10.0, 49.2, 1)
    with pytest.raises(ValueError, match="pair_sd"):
        detectable_effect(0.0, 5)


def test_dreamerv2_curve_reads_its_points_and_refuses_others():
    mean, sd = dreamerv2_curve("walker_walk", 30_000)   # 88.43 85.08 83.09 152.57 238.76
    assert (round(mean, 1), round(sd, 1)) == (129.6, 67.6)
    with pytest.raises(ValueError, match="no point at 45,000 env steps"):
        dreamerv2_curve("walker_walk", 45_000)
    with pytest.raises(ValueError, match="no task 'cartpole_swingup'"):
        dreamerv2_curve("cartpole_swingup", 30_000)


def test_the_walker_grid_constants_are_its_committed_paired_differences():
    paired = paired_difference(json.loads(WALKER_GRID.read_text()), "walker_walk")
    assert [round(d, 1) for d in paired["diffs"]] == list(WALKER_GRID_DIFFS)


def test_the_committed_power_table_is_what_the_code_computes():
    assert json.loads(TABLE.read_text()) == power_table()


def test_results_md_states_the_walker_grids_power_and_the_table_as_computed():
    """The paragraph beside the walker grid's result and the sizing section's table carry the
    committed table's figures, so the page cannot drift from the code."""
    table = json.loads(TABLE.read_text())
    walker = table["walker_grid"]
    text = " ".join(RESULTS_MD.read_text().split())   # line breaks as spaces
    result = text[text.index("#### The result (2026-12-07"):text.index("**The mechanism, measured**")]
    stated = re.search(r"detect with 80% power is a mean paired difference of \*\*([0-9.]+)\*\*", result)
    assert stated, "results.md states the walker grid's detectable effect"
    assert float(stated.group(1)) == round(detectable_effect(np.std(WALKER_GRID_DIFFS, ddof=1), 5), 1)
    assert float(stated.group(1)) == walker["detectable_effect"]
    assert f"power {100 * walker['power_for_paper_effect']:.1f}%" in result
    assert f"({walker['paper_effect']:.1f} points)" in result
    page = RESULTS_MD.read_text()
    assert power_markdown(table) in page[page.index("### Sizing the next RL comparison (issue 51, point 4)"):]


def test_protocad_compare_power_prints_and_writes_the_table(tmp_path, capsys):
    out = tmp_path / "power.json"
    assert compare.main(["--power", "--power-json", str(out)]) == 0
    printed = capsys.readouterr().out
    table = json.loads(out.read_text())
    assert table == json.loads(TABLE.read_text())
    assert power_markdown(table) in printed and all(line in printed for line in power_lines(table))
    out.unlink()
    assert compare.main(["--power-json", str(out)]) == 0   # the JSON alone asks for the table too
    assert json.loads(out.read_text()) == table
