"""The package code as the docs tests read it: names a block of statements defines."""
from __future__ import annotations

import ast
from typing import Iterable


def defined_names(statements: Iterable[ast.stmt], *, bare_annotations: bool = True) -> set[str]:
    """Functions, classes and assigned names (tuple targets too) of a module's or a class's
    body. `bare_annotations`: whether `x: T` with no value counts (a dataclass field does;
    elsewhere it declares nothing)."""
    names = set()
    for node in statements:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names |= {n.id for t in node.targets for n in ast.walk(t) if isinstance(n, ast.Name)}
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            if node.value is not None or bare_annotations:
                names.add(node.target.id)
    return names
