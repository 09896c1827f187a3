"""The walker policy the package ships (the demo's start, `protocad-loop --init-policy`) is what
README and results.md say it is: a ProtoCAD run whose prototypes trained for most of its updates
and moved, scoring at least max(150, 3 x random) on all 64 unseen contexts. Read from the
committed files themselves, so shipping another policy without its evaluation fails here."""
from __future__ import annotations

import json

from helpers import ROOT

from protocad_ros.atomic import file_sha256
from protocad_ros.checkpoint.agent_file import load_checkpoint
from trainer.research.probe import prototype_drift

POLICY = ROOT / "protocad_ros" / "policies" / "walker_walk.pt"
RESULTS = ROOT / "msgs_docs" / "results"


def test_the_shipped_walker_policy_trained_its_prototypes():
    provenance = json.loads(POLICY.with_suffix(".json").read_text())["provenance"]
    entry = provenance["results_entry"]
    assert entry["variant"] == "protocad" and entry["task"] == "walker_walk"
    # trained for at least three quarters of its updates, the freeze recorded where it ran
    assert 0 < entry["prototype_freeze"] <= 0.25 * entry["updates"]
    agent, counters = load_checkpoint(POLICY, restore_rng=False, optimizer_states=False)
    moved = prototype_drift(agent, counters.get("prototype_freeze"))
    assert moved["cos_to_initial_mean"] < 0.99          # 1.000: never trained (the policy it replaced)
    probe = json.loads((RESULTS / "walker_shipped_probe.json").read_text())
    assert abs(probe["prototypes"]["cos_to_initial_mean"] - moved["cos_to_initial_mean"]) < 1e-3


def test_the_shipped_walker_policy_clears_the_bar_on_unseen_contexts():
    doc = json.loads((RESULTS / "walker_shipped_unseen.json").read_text())
    (mine,), (random,) = doc["results"], doc["random"]
    assert mine["policy"] == "protocad_ros/policies/walker_walk.pt" and random["policy"] == "random"
    assert mine["episodes"] == random["episodes"] == 64 * 5
    assert mine["mean_return"] >= max(150.0, 3 * random["mean_return"])
    assert mine["sha256"] == file_sha256(POLICY)        # measured on this very file, not the one before
