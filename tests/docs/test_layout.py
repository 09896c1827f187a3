"""msgs_docs/layout.md is the map a newcomer reads first: its file table names every package
module (each .py under protocad_ros/, sim_bridge/ and trainer/, __init__.py aside), every
subpackage has its line in the subpackage table, and nothing listed is gone."""
from __future__ import annotations

import re

from helpers import ROOT

PACKAGES = ("protocad_ros", "sim_bridge", "trainer")
LAYOUT = ROOT / "msgs_docs" / "layout.md"


def section(title: str) -> str:
    text = LAYOUT.read_text()
    start = text.index(f"## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end >= 0 else len(text)]


def table_rows(text: str) -> list[tuple[str, str]]:
    """(first cell, rest) of each body row of the markdown table in `text`."""
    rows = []
    for line in text.splitlines():
        if line.startswith("| `"):
            first, _, rest = line[2:].partition(" | ")
            rows.append((first, rest))
    return rows


def listed_modules() -> set[str]:
    """Every `name.py` the file table names, joined to its row's folder (an `__init__.py` it
    names is commentary: every package has one)."""
    out = set()
    for first, rest in table_rows(section("Files")):
        folder = re.fullmatch(r"`([\w/]+/)`", first)
        if folder:
            out |= {folder.group(1) + name for name in re.findall(r"`([\w./]+\.py)`", rest)
                    if not name.endswith("__init__.py")}
    return out


def package_modules() -> set[str]:
    return {p.relative_to(ROOT).as_posix() for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
            if p.name != "__init__.py"}


def test_the_file_table_names_every_package_module():
    assert sorted(package_modules() - listed_modules()) == []


def test_the_file_table_names_no_module_that_is_gone():
    assert sorted(listed_modules() - package_modules()) == []


def test_the_subpackage_table_has_every_subpackage():
    listed = {first.strip("`") for first, _ in table_rows(section("Subpackages"))}
    subpackages = {p.parent.relative_to(ROOT).as_posix() + "/" for pkg in PACKAGES
                   for p in (ROOT / pkg).rglob("__init__.py") if p.parent.name != pkg}
    assert sorted(subpackages - listed) == []
