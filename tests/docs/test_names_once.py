"""Each fact once: no name is defined at the top level of two package modules (a function, a
class, or a name assigned there) unless it is listed below with the reason it repeats. A second
definition is how facts drift apart (MetricsCallback was defined five times, MAX_SEARCH_DEPTH
twice in one module); a name that is one fact lives in one module and the others import it."""
from __future__ import annotations

import ast
from collections import defaultdict

from helpers import ROOT
from helpers.source import defined_names

PACKAGES = ("protocad_ros", "sim_bridge", "trainer")

#: name -> why several modules define it (each module its own thing under a shared convention).
REPEATED_ON_PURPOSE = {
    # conventions: one per module that has one
    "__all__": "each module's own public names",
    "main": "each command's and node's entry point (setup.py and libexec name module:main)",
    "build_parser": "each command's own options (the docs' --help tests call it per module)",
    "run": "each command's body behind main (its settings in, exit code out)",
    "register": "each ros2 verb's module adds its subcommand (trainer/ros2cli/__init__.py calls them)",
    "cmd_list": "the ros2 verbs' subcommands, named as ros2cli names them",
    "cmd_info": "the ros2 verbs' subcommands, named as ros2cli names them",
    "cmd_get": "the ros2 verbs' subcommands, named as ros2cli names them",
    "cmd_set": "the ros2 verbs' subcommands, named as ros2cli names them",
    "NODE_NAME": "each node's own default name",
    "PARAMS": "each node's own parameter table (run_node reads it)",
    "COUNTERS": "each node's own diagnostics counters",
    "PROTOCOL_KEYS": "each driver's own protocol settings kept in run.json (loop, online)",
    "SCHEMA_ID": "each JSON document's own schema id (results.json, probe.json)",
    "_NUM": "a JSON Schema fragment each schema module spells out beside its schema",
    "_INT": "a JSON Schema fragment each schema module spells out beside its schema",
    "validate": "each JSON document's own schema check (results.json, probe.json)",
    "gather": "each report's own collection of its runs (the compare grid, the study grid)",
    "run_grid": "each grid's own runner (the compare grid of online runs, the study's world models)",
    # the same word for different things, each clear in its module
    "CONTEXT_FEATURES": "the topic's name (contract) and the probe's feature names (u, w, e)",
    "MODES": "the live view's modes and the bridge's stepping modes",
    "DEFAULT_CHUNK_SIZE": "a checkpoint transfer's chunk (contract) and an MCAP file's chunk (bag writer)",
    "ConfigError": "a bad model config (model) and a bad node parameter (nodekit): two error types",
    "describe": "a QoS profile in one line (contract) and a run key in one line (launch)",
    "transitions": "DrQ's (o, a, r, d, o') windows and a lifecycle node's available transitions",
    "_call": "a private helper of each ros2 verb (a service call with its own request)",
    "_count": "a private helper of each module (a JointState field, a results row)",
    "_digest": "a private helper of each module (rank states, the study dataset's files)",
    "_message_class": "a private helper: the bag's type support and ros2 topic's rclpy class",
    "_node_args": "a private helper: rclpy's node arguments and ros2 param's target node",
    "_scalar": "a private helper: yaml-cpp's scalar spelling and a metric's JSON value",
    # a stand-in for a name another module defines, where importing it would be a cycle
    "LoopSettings": "trainer/launch/loop.py's settings; loop_rundir.py, which loop.py imports, names "
                    "it as an alias of Any for its annotations",
}


def definitions() -> dict[str, set[str]]:
    where: dict[str, set[str]] = defaultdict(set)
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            for name in defined_names(ast.parse(path.read_text()).body):
                where[name].add(path.relative_to(ROOT).as_posix())
    return where


def test_no_name_is_defined_in_two_package_modules_unless_listed():
    twice = {name: sorted(mods) for name, mods in definitions().items()
             if len(mods) > 1 and name not in REPEATED_ON_PURPOSE}
    assert twice == {}


def test_every_listed_name_still_repeats():
    """A name that no longer repeats leaves the list (so the list stays the truth)."""
    where = definitions()
    assert sorted(n for n in REPEATED_ON_PURPOSE if len(where.get(n, ())) < 2) == []
