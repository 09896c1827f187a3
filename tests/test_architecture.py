"""The layering, read from the import graph (grimp; every import counts, those inside
functions too): sim_bridge is the bottom floor (the contract, task knowledge, the shared node
plumbing) and imports neither protocad_ros nor trainer; protocad_ros' model files import no ROS
and nothing from trainer, so the agent trains on a machine without ROS; the contract modules
import no other package of the project; no package has an import cycle."""
from __future__ import annotations

import grimp
import pytest

PACKAGES = ("protocad_ros", "sim_bridge", "trainer")
#: protocad_ros' model files (the node, the live view and the ROS helpers are the ROS side).
MODEL_FILES = ("agent", "agent_base", "agents", "augment", "atomic", "behavior", "checkpoint",
               "config", "drq", "networks", "policy", "precision", "prototypes", "rssm")
#: The wire contract, task knowledge and the node plumbing every package builds on.
CONTRACT = ("sim_bridge.topics", "sim_bridge.contexts", "sim_bridge.qos", "sim_bridge.rosnode",
            "sim_bridge.rosbase", "sim_bridge.lifecycle")
ROS = ("rclpy", "rcl_interfaces", "sensor_msgs", "std_msgs", "std_srvs", "diagnostic_msgs",
       "rosgraph_msgs", "lifecycle_msgs", "builtin_interfaces")


@pytest.fixture(scope="module")
def graph():
    return grimp.build_graph(*PACKAGES, *ROS, include_external_packages=True)


def _importers(graph, importer: str, imported: str) -> list[str]:
    return sorted(f"{i['importer']} -> {i['imported']}" for i in graph.find_matching_direct_imports(
        import_expression=f"{importer} -> {imported}"))


@pytest.mark.parametrize("upper", ["protocad_ros", "trainer"])
def test_sim_bridge_imports_no_package_above_it(graph, upper):
    assert _importers(graph, "sim_bridge.**", f"{upper}.**") == []
    assert _importers(graph, f"{upper}.**", "sim_bridge.**") != []   # the graph sees the imports


def test_model_files_import_no_ros_and_nothing_from_trainer(graph):
    bad = []
    for m in MODEL_FILES:
        mod = f"protocad_ros.{m}"
        for imp in sorted(graph.find_modules_directly_imported_by(mod)):
            if imp.split(".")[0] in ROS or imp.startswith("trainer") or imp.startswith(("sim_bridge.ros",
                                                                                           "sim_bridge.node")):
                bad.append(f"{mod} -> {imp}")
    assert bad == []
    assert any(i.split(".")[0] in ROS for i in graph.find_modules_directly_imported_by(
        "protocad_ros.policy_node"))                                    # the check sees ROS imports


def test_contract_imports_no_other_package_of_the_project(graph):
    bad = []
    for mod in CONTRACT:
        for imp in sorted(graph.find_modules_directly_imported_by(mod)):
            if imp.split(".")[0] in PACKAGES and imp not in CONTRACT:
                bad.append(f"{mod} -> {imp}")
    assert bad == []


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycle_inside_a_package(graph, package):
    mods = sorted(graph.find_descendants(package) | {package})
    cycles = [(a, b) for a in mods for b in mods
              if a < b and graph.chain_exists(a, b) and graph.chain_exists(b, a)]
    assert cycles == []
