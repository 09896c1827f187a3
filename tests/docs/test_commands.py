"""One way to declare a command or a node parameter (issue 52): every console script's options
are generated from settings dataclasses (trainer.settings.settings_parser), every node's ROS
parameters are declared from its Param table (sim_bridge.nodekit.rosnode.declare_all), and
nothing else in the package code builds argparse by hand or declares a parameter on its own.
A hand-built command or parameter added later fails here."""
from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib
import re
from pathlib import Path

import pytest
from helpers import ROOT

PACKAGES = ("protocad_ros", "sim_bridge", "trainer")

#: Console scripts whose command line is not generated from settings, and why.
HAND_BUILT_SCRIPTS = {
    # ros2's own verbs, subcommands and flags, spelled as the real ros2cli declares them.
    "ros2",
}
#: Package files that may build argparse by hand, and why.
HAND_BUILT_FILES = {
    "trainer/settings.py",              # the generator itself
    "sim_bridge/nodekit/rosnode.py",    # a node's --help, printed from its Param table
    "trainer/nodes/recorder_cli.py",    # `ros2 bag record`'s options the recorder refuses, with the reason
    "trainer/data/dataset.py",          # `python -m trainer.data.dataset`: trainer.data may not import trainer.settings
}
HAND_BUILT_FOLDERS = ("trainer/ros2cli/",)   # ros2 (above)
#: The nodes, by class: each declares its ROS parameters from a Param table.
NODES = {"PolicyNode", "SimBridgeNode", "RecorderNode", "CheckpointPublisherNode", "RandomActorNode"}
NODE_BASES = {"ProtocadNode", "ManagedNode"}


def console_scripts() -> dict[str, str]:
    """{script: "module:function"} from setup.py's entry_points."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and key.value == "console_scripts":
                    entries = [e.value for e in value.elts]
                    return dict(tuple(x.strip() for x in e.split("=")) for e in entries)
    raise AssertionError("setup.py has no console_scripts")


def package_files():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            yield path.relative_to(ROOT).as_posix(), ast.parse(path.read_text())


def called(tree: ast.AST, names: set[str]) -> list[int]:
    """Lines of the calls of these functions or methods."""
    return [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Call)
            and (getattr(n.func, "attr", None) in names or getattr(n.func, "id", None) in names)]


def test_the_console_scripts_are_the_ones_this_test_knows():
    scripts = console_scripts()
    assert len(scripts) == 16 and HAND_BUILT_SCRIPTS <= set(scripts)


@pytest.mark.parametrize("script", sorted(set(console_scripts()) - HAND_BUILT_SCRIPTS))
def test_every_console_script_is_generated_from_settings_or_a_param_table(script):
    """Its parser comes from settings_parser and every option it has is a field of its settings
    classes; or it is a node whose --help is its Param table (run_node(params=PARAMS))."""
    module_name, func = console_scripts()[script].split(":")
    module = importlib.import_module(module_name)
    main = next(n for n in ast.walk(ast.parse(Path(module.__file__).read_text()))
                if isinstance(n, ast.FunctionDef) and n.name == func)
    delegate = [c.func.value.id for c in ast.walk(main) if isinstance(c, ast.Call)
                and isinstance(c.func, ast.Attribute) and c.func.attr == "main" and isinstance(c.func.value, ast.Name)]
    if not hasattr(module, "build_parser") and delegate and hasattr(getattr(module, delegate[0], None), "build_parser"):
        # an entry point that hands the command line of another module a part of its own
        # (protocad-evaluate: trainer.launch.ros_evaluate gives trainer.learn.evaluate its ROS evaluator)
        module = getattr(module, delegate[0])
    # A module of one command has build_parser; one of several, NAME_parser beside NAME_main.
    builder = func.removesuffix("_main") + "_parser" if func.endswith("_main") else "build_parser"
    if not hasattr(module, builder):
        runs = [c for c in ast.walk(main) if isinstance(c, ast.Call) and getattr(c.func, "id", None) == "run_node"]
        assert runs and any(k.arg == "params" for k in runs[0].keywords), \
            f"{script}: neither a settings_parser command ({builder}) nor a node run on its Param table"
        from sim_bridge.nodekit.param_table import Param
        assert module.PARAMS and all(isinstance(p, Param) for p in module.PARAMS)
        return
    parser = getattr(module, builder)()
    classes = getattr(parser, "settings_classes", None)
    assert classes, f"{script}: {builder} does not come from trainer.settings.settings_parser"
    fields = {f.name for cls in classes for f in dataclasses.fields(cls)}
    from trainer.nodes.recorder_cli import UNSUPPORTED_OPTIONS
    own = [a for a in parser._actions if not isinstance(a, argparse._HelpAction)
           and not set(a.option_strings) <= set(UNSUPPORTED_OPTIONS) | {None}]
    assert own and not [a.option_strings or a.dest for a in own if a.dest not in fields], \
        f"{script}: options that are no settings field"
    assert called(ast.parse(Path(module.__file__).read_text()), {builder}), \
        f"{script}: {func} does not parse with {builder}()"


def test_no_package_code_builds_argparse_by_hand():
    hand_built = {rel: lines for rel, tree in package_files()
                  if rel not in HAND_BUILT_FILES and not rel.startswith(HAND_BUILT_FOLDERS)
                  and (lines := called(tree, {"ArgumentParser", "add_argument", "add_parser"}))}
    assert hand_built == {}, "declare the options as a settings dataclass (trainer.settings.settings_parser)"


def test_every_node_declares_its_parameters_from_a_param_table():
    """No node declares a ROS parameter on its own: declare_all over a Param table, the one
    place that calls declare_parameter."""
    direct = {rel: lines for rel, tree in package_files()
              if rel != "sim_bridge/nodekit/rosnode.py" and (lines := called(tree, {"declare_parameter",
                                                                                      "declare_parameters"}))}
    assert direct == {}
    nodes = {}
    for rel, tree in package_files():
        for cls in (n for n in tree.body if isinstance(n, ast.ClassDef)):
            if {getattr(b, "id", None) for b in cls.bases} & NODE_BASES and not rel.startswith("sim_bridge/nodekit/"):
                nodes[cls.name] = (rel, cls)
    assert set(nodes) == NODES
    from sim_bridge.nodekit.param_table import Param
    for name, (rel, cls) in nodes.items():
        calls = [c for c in ast.walk(cls) if isinstance(c, ast.Call) and getattr(c.func, "id", None) == "declare_all"]
        assert calls, f"{rel}: {name} declares no Param table"
        table = {n.id for n in ast.walk(calls[0].args[1]) if isinstance(n, ast.Name)} & {"PARAMS"}
        assert table, f"{rel}: {name} declares something else than its module's PARAMS"
        module = importlib.import_module(rel[:-3].replace("/", "."))
        assert module.PARAMS and all(isinstance(p, Param) for p in module.PARAMS), rel


def doc_rows(path: Path, heading: str) -> list[list[str]]:
    """The cells of the table under `heading` (its header and rule left out)."""
    text = path.read_text().split(heading, 1)[1].split("\n## ", 1)[0]
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
            if line.startswith("|")]
    return rows[2:]


def test_the_recorder_docs_table_is_its_param_table():
    """msgs_docs/recorder.md's parameters are recorder_params.PARAMS: each name, its default and
    the option the command line gives it (generated from the table: recorder_cli.RECORD_FORMS)."""
    from trainer.nodes.recorder_cli import RECORD_FORMS, build_parser
    from trainer.nodes.recorder_params import PARAMS

    rows = {re.sub(r"`", "", r[0]): r for r in doc_rows(ROOT / "msgs_docs" / "recorder.md", "## Parameters")
            if r[0].startswith("`")}
    assert set(rows) == {p.name for p in PARAMS}
    flags = {a.dest: set(a.option_strings) for a in build_parser()._actions}
    for p in PARAMS:
        option, default = rows[p.name][1], re.findall(r"`([^`]*)`", rows[p.name][2])[0]
        if RECORD_FORMS.get(p.name, {}) is not None:
            documented = set(re.findall(r"(?<![\w-])(--?[a-z][a-z-]*)", option))
            also = {"--topics"} if p.name == "topics" else set()   # the positional's option form
            assert documented and documented <= flags[p.name] | also, p.name
        if p.name == "output":
            continue   # the declared default is the time-stamped name the node makes
        if isinstance(p.default, bool):
            assert default == str(p.default).lower(), p.name
        elif isinstance(p.default, tuple):
            assert default == "[]" and p.default == (), p.name
        elif isinstance(p.default, str):
            assert default in (p.default, f'"{p.default}"'), p.name
        else:
            assert float(default) == p.default, p.name
