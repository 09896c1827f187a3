"""Every class owns its state: no class in package code reads `self.X` unless it or one of its
declared bases sets X (in a method, `self.X = ...`; or in the class body: a method, a class
attribute, a dataclass field). A mixin that reads what its host sets, and nobody declares, is
what this catches: the node parts are composed objects, handed what they need when built.

Bases outside the project (rclpy's Node, threading.Thread, Exception, ...) are imported and
read the same way (their source where Python has it, `dir()` always)."""
from __future__ import annotations

import ast
import importlib
import inspect
import textwrap
from functools import lru_cache
from pathlib import Path

import pytest
from helpers import ROOT
from helpers.source import defined_names

PACKAGES = ("protocad_ros", "sim_bridge", "trainer")


def module_files() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = path
    return out


FILES = module_files()


@lru_cache(maxsize=None)
def parsed(module: str) -> ast.Module:
    return ast.parse(FILES[module].read_text())


def imported_names(tree: ast.Module, module: str) -> dict[str, str]:
    """name -> dotted origin, for the module's top-level imports."""
    out = {}
    package = module if FILES[module].name == "__init__.py" else module.rpartition(".")[0]
    for node in tree.body:
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
            for alias in node.names:
                out[alias.asname or alias.name] = f"{base}.{alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                out[alias.asname or alias.name.split(".")[0]] = alias.asname and alias.name or alias.name.split(".")[0]
    return out


def methods(cls: ast.ClassDef) -> list[ast.FunctionDef | ast.AsyncFunctionDef]:
    return [f for f in cls.body if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))]


def self_name(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> str | None:
    if any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in fn.decorator_list):
        return None
    args = fn.args.posonlyargs + fn.args.args
    return args[0].arg if args else None


def attribute_uses(cls: ast.ClassDef) -> tuple[dict[str, int], set[str]]:
    """({attribute read: first line}, attributes set) through the methods' `self`."""
    reads: dict[str, int] = {}
    sets: set[str] = set()
    for fn in methods(cls):
        me = self_name(fn)
        if me is None:
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == me:
                if isinstance(node.ctx, ast.Load):
                    reads.setdefault(node.attr, node.lineno)
                else:
                    sets.add(node.attr)
            elif isinstance(node, ast.Call) and sets_by_name(node, me):
                sets.add(node.args[1 if isinstance(node.func, ast.Name) else 0].value)
    return reads, sets


def sets_by_name(call: ast.Call, me: str) -> bool:
    """`setattr(self, "x", v)`, or torch's `self.register_buffer("x", t)` and friends."""
    f, args = call.func, call.args
    if isinstance(f, ast.Name) and f.id == "setattr":
        return (len(args) >= 2 and isinstance(args[0], ast.Name) and args[0].id == me
                and isinstance(args[1], ast.Constant))
    return (isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id == me
            and f.attr in ("register_buffer", "register_parameter", "add_module") and bool(args)
            and isinstance(args[0], ast.Constant))


def class_body_names(cls: ast.ClassDef) -> set[str]:
    return defined_names(cls.body, bare_annotations=is_record(cls))


def is_record(cls: ast.ClassDef) -> bool:
    marks = {ast.unparse(d).split("(")[0].split(".")[-1] for d in cls.decorator_list}
    bases = {ast.unparse(b).split("[")[0].split(".")[-1] for b in cls.bases}
    return bool(marks & {"dataclass"} or bases & {"NamedTuple", "TypedDict", "Protocol"})


def project_class(module: str, name: str) -> ast.ClassDef | None:
    for node in parsed(module).body:
        if isinstance(node, ast.ClassDef) and node.name == name:
            return node
    return None


def foreign_names(dotted: str) -> set[str]:
    """What a class from outside the project provides its subclasses: `dir()`, and what its
    methods (and those of its bases) set on `self`, where Python has their source."""
    module, _, name = dotted.rpartition(".")
    obj = importlib.import_module(module)
    for part in name.split("."):
        obj = getattr(obj, part)
    names = set(dir(obj))
    for klass in inspect.getmro(obj) if isinstance(obj, type) else ():   # typing.NamedTuple is a function
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                names |= attribute_uses(node)[1]
    return names


def provided(module: str, cls: ast.ClassDef, seen: frozenset = frozenset()) -> set[str]:
    """Every attribute the class or its declared bases set or define."""
    names = class_body_names(cls) | attribute_uses(cls)[1]
    origins = imported_names(parsed(module), module)
    for base in cls.bases:
        text = ast.unparse(base).split("[")[0]
        head, _, rest = text.partition(".")
        if text in ("object",):
            continue
        if head in origins:
            dotted = origins[head] + (f".{rest}" if rest else "")
        elif project_class(module, text) is not None:
            dotted = f"{module}.{text}"
        else:
            dotted = f"builtins.{text}"
        owner, _, name = dotted.rpartition(".")
        if owner in FILES and (klass := project_class(owner, name)) is not None and dotted not in seen:
            names |= provided(owner, klass, seen | {dotted})
        else:
            names |= foreign_names(dotted)
    return names


def project_classes() -> list[tuple[str, ast.ClassDef]]:
    return [(module, node) for module in sorted(FILES) for node in ast.walk(parsed(module))
            if isinstance(node, ast.ClassDef)]


def unowned_reads(module: str, cls: ast.ClassDef) -> list[str]:
    reads, _ = attribute_uses(cls)
    have = provided(module, cls) | {"__class__", "__dict__"}
    return [f"self.{name} (line {line})" for name, line in sorted(reads.items(), key=lambda kv: kv[1])
            if name not in have]


@pytest.mark.parametrize("module,cls", project_classes(), ids=lambda v: v if isinstance(v, str) else v.name)
def test_a_class_reads_only_what_it_or_a_declared_base_sets(module, cls):
    missing = unowned_reads(module, cls)
    assert not missing, (f"{FILES[module].relative_to(ROOT)}: {cls.name} reads attributes that neither it nor "
                         f"a declared base sets: {', '.join(missing)}. Give the class what it needs when it is "
                         "built (a part of a node takes the node, its parameters and its publishers), or set it.")


#: The three nodes built of parts, and the packages their parts live in.
NODES_OF_PARTS = {
    ("protocad_ros.node.policy_node", "PolicyNode"): ("protocad_ros.node", "protocad_ros.robot"),
    ("sim_bridge.bridge.node", "SimBridgeNode"): ("sim_bridge.bridge",),
    ("trainer.nodes.recorder", "RecorderNode"): ("trainer.nodes",),
}


def snake(name: str) -> str:
    return "".join(f"_{c.lower()}" if c.isupper() else c for c in name).lstrip("_")


@pytest.mark.parametrize("node", sorted(NODES_OF_PARTS), ids=lambda n: n[1])
def test_a_node_holds_each_part_under_its_module_name(node):
    """One naming scheme (msgs_docs/layout.md, "A node and its parts"): a part built by the node
    from its own packages is a class named like its module (snake_case) and is held in the
    attribute of that name: `self.stepping = Stepping(...)` from stepping.py."""
    module, name = node
    cls = project_class(module, name)
    origins = imported_names(parsed(module), module)
    parts, wrong = [], []
    for fn in methods(cls):
        for stmt in ast.walk(fn):
            if not (isinstance(stmt, ast.Assign) and isinstance(stmt.value, ast.Call)
                    and isinstance(stmt.value.func, ast.Name) and stmt.value.func.id in origins):
                continue
            owner, _, cls_name = origins[stmt.value.func.id].rpartition(".")
            if not owner.startswith(NODES_OF_PARTS[node]) or project_class(owner, cls_name) is None:
                continue
            for target in stmt.targets:
                if isinstance(target, ast.Attribute) and isinstance(target.value, ast.Name) and target.value.id == "self":
                    parts.append(target.attr)
                    stem = owner.rpartition(".")[2]
                    if not (target.attr == stem == snake(cls_name)):
                        wrong.append(f"self.{target.attr} = {cls_name}(...) from {owner}")
    assert len(parts) >= 4, f"{name} builds {parts}: fewer parts than it has"
    assert not wrong, f"{name}: parts off the naming scheme: {wrong}"
