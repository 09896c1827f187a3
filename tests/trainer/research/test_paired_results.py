"""The paired ProtoCAD-vs-Dreamer grid of issue 42, as committed: every finished run follows the
protocol results.md fixed before the runs, and results.md's table of the grid shows exactly the
finished runs with the figures their results file holds. Read from the committed files, so a
stop that adds seeds to one without the other fails here."""
from __future__ import annotations

import json
import re

from helpers import ROOT

from trainer.research.probe_report import read_json, summary_markdown
from trainer.research.statistics import paired_difference, unseen_train_ratio

RESULTS = ROOT / "msgs_docs" / "results" / "walker_paired_small.json"
RESULTS_MD = ROOT / "msgs_docs" / "results.md"
PROBES = ROOT / "msgs_docs" / "results" / "walker_paired_probes"
ARMS = {"protocad": "ProtoCAD", "dreamer": "Dreamer"}


def finished_rows() -> list[dict]:
    doc = json.loads(RESULTS.read_text())
    return [r for r in doc["runs"] if r["status"] == "finished"]


def grid_table() -> dict[tuple[int, str], tuple[float, float]]:
    """results.md's table of the paired grid: (seed, arm) -> (unseen, training) final returns."""
    text = RESULTS_MD.read_text()
    header = text.index("| seed | arm | unseen (64 x 5) | training (25 x 5) |")
    rows = {}
    for line in text[header:].splitlines()[2:]:
        if not line.startswith("|"):
            break
        seed, arm, unseen, train = (cell.strip() for cell in line.strip("|").split("|")[:4])
        rows[(int(seed), arm)] = (float(unseen), float(train))
    return rows


def test_every_finished_paired_run_follows_the_fixed_protocol():
    rows = finished_rows()
    assert rows, "the grid has finished runs committed"
    for r in rows:
        where = f"{r['label']} seed {r['seed']}"
        assert r["task"] == "walker_walk" and r["label"] in ARMS, where
        assert (r["preset"], r["render_quality"], r["reference"]) == ("small", "fast", "dreamerv2"), where
        assert (r["env_steps"], r["updates"], r["collect_interval"]) == (30000, 2900, 100), where
        # final evaluation: all 64 unseen and all 25 training contexts, 5 episodes each
        assert (len(r["final"]["per_context"]), r["final"]["episodes"]) == (64, 320), where
        assert (len(r["final_train"]["per_context"]), r["final_train"]["episodes"]) == (25, 125), where
        if r["label"] == "protocad":   # prototypes trained for at least three quarters of the run
            assert 0 < r["prototype_freeze"] <= 0.25 * r["updates"], where
    # both arms met the same contexts: the same unseen and training grids, for every seed
    assert len({tuple(sorted(r["final"]["per_context"])) for r in rows}) == 1
    assert len({tuple(sorted(r["final_train"]["per_context"])) for r in rows}) == 1


def test_results_md_shows_exactly_the_finished_paired_runs():
    table = grid_table()
    from_file = {(r["seed"], ARMS[r["label"]]): (r["final"]["mean_return"], r["final_train"]["mean_return"])
                 for r in finished_rows()}
    assert set(table) == set(from_file)
    for key, (unseen, train) in from_file.items():
        assert table[key] == (round(unseen, 1), round(train, 1)), key


def test_results_md_names_how_many_seed_pairs_the_grid_has():
    seeds = {r["seed"] for r in finished_rows() if r["label"] == "protocad"} & \
            {r["seed"] for r in finished_rows() if r["label"] == "dreamer"}
    stands = re.search(r"#### (?:Where the paired grid stands|The result) \([^)]*?(\d) of 5 seed pairs",
                       RESULTS_MD.read_text())
    assert stands and int(stands.group(1)) == len(seeds)


def test_the_primary_metric_is_reported_as_it_was_fixed_on_five_paired_seeds():
    """results.md fixed the primary metric before the runs: the mean paired difference on unseen
    contexts with its 95% t-interval, and the unseen/train ratio per arm. It states them as the
    committed file gives them, over at least 5 seeds that both arms finished, with the verdict
    the plan's rule gives."""
    doc = json.loads(RESULTS.read_text())
    paired = paired_difference(doc, "walker_walk")
    assert paired is not None and len(paired["seeds"]) >= 5
    text = RESULTS_MD.read_text()
    low, high = paired["ci"]
    assert f"{paired['mean']:+.1f} [95% t-interval {low:+.1f}, {high:+.1f}]" in text
    verdict = ("ProtoCAD is ahead" if low > 0 else "ProtoCAD is behind" if high < 0
               else "No difference shown at this budget")
    result = text[text.index("#### The result"):]
    assert verdict in result[:result.index("| seed |")]
    for label in ARMS:
        ratio = unseen_train_ratio(doc, "walker_walk", label)
        assert ratio["n"] >= 5 and f"{ARMS[label]} {ratio['mean']:.2f}" in text, label
    readme = (ROOT / "README.md").read_text()   # the front page's row says the same
    assert f"{paired['mean']:+.1f} [95% t-interval {low:+.1f}, {high:+.1f}]: {verdict}".lower() in readme.lower()
    assert doc["random"]["walker_walk"]["episodes"] == 320
    assert f"Random policy** on the same 64 x 5: {doc['random']['walker_walk']['mean_return']:.1f}" in text


def test_the_probe_tables_in_results_md_are_those_of_both_arms_committed_probes():
    """Both arms' probes of every finished run are committed, and results.md shows their summary
    as `protocad-probe --summarize` prints it from those files."""
    probes = sorted(PROBES.glob("*_seed*.json"))
    assert {p.stem for p in probes} == {f"{r['label']}_seed{r['seed']}" for r in finished_rows()}
    assert summary_markdown([read_json(p) for p in probes]) in RESULTS_MD.read_text()
