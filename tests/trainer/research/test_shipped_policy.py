"""The walker policy the package ships (the demo's start, `protocad-loop --init-policy`) is what
README and results.md say it is: a ProtoCAD run at the context settings the study chose (the
defaults), whose prototypes trained for most of its updates and moved from where its run
started, whose module the probe does not find collapsed, scoring at least max(150, 3 x random)
on all 64 unseen contexts. Read from the committed files themselves, so shipping another policy
without its evaluation and probe fails here."""
from __future__ import annotations

import json

from helpers import ROOT

from protocad_ros.atomic import file_sha256
from protocad_ros.model.hyperparameters import PAPER_CONTEXT_SETTINGS, ContextConfig

POLICY = ROOT / "protocad_ros" / "policies" / "walker_walk.pt"
RESULTS = ROOT / "msgs_docs" / "results"


def test_the_shipped_walker_policy_trained_its_prototypes():
    provenance = json.loads(POLICY.with_suffix(".json").read_text())["provenance"]
    entry = provenance["results_entry"]
    assert entry["variant"] == "protocad" and entry["task"] == "walker_walk"
    # trained for at least three quarters of its updates, the freeze recorded where it ran
    assert 0 < entry["prototype_freeze"] <= 0.25 * entry["updates"]
    probe = json.loads((RESULTS / "walker_shipped_probe.json").read_text())
    assert probe["prototypes"]["cos_to_initial_mean"] < 0.99   # 1.000: never trained
    # measured from where its run started (--init-policy): the policy shipped before it, the
    # file whose evaluation is kept beside it
    before = json.loads((RESULTS / "walker_paper_settings_policy_unseen.json").read_text())["results"][0]
    assert probe["prototypes"]["start"]["sha256"] == before["sha256"]


def test_the_shipped_walker_policy_follows_the_chosen_context_settings_and_its_module_is_alive():
    # issue 51 point 5: the demo's policy trained its context module at the defaults the study
    # chose, not at the paper's collapsing ones, and the probe does not find it collapsed
    context = json.loads(POLICY.with_suffix(".json").read_text())["config"]["context"]
    chosen = ContextConfig()
    for key in PAPER_CONTEXT_SETTINGS:
        name = key.removeprefix("context.")
        assert context[name] == getattr(chosen, name), name
    probe = json.loads((RESULTS / "walker_shipped_probe.json").read_text())
    assert probe["health"] and probe["collapsed"] is None


def test_the_shipped_walker_policy_clears_the_bar_on_unseen_contexts():
    doc = json.loads((RESULTS / "walker_shipped_unseen.json").read_text())
    (mine,), (random,) = doc["results"], doc["random"]
    assert mine["policy"] == "protocad_ros/policies/walker_walk.pt" and random["policy"] == "random"
    assert mine["episodes"] == random["episodes"] == 64 * 5
    assert mine["mean_return"] >= max(150.0, 3 * random["mean_return"])
    assert mine["sha256"] == file_sha256(POLICY)        # measured on this very file, not the one before
