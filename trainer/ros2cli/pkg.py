"""`ros2 run` and `ros2 pkg list|executables|prefix`, from the ament index (AMENT_PREFIX_PATH), as
ros2cli (Jazzy) answers them. Its errors are RuntimeErrors, whose message the front-end prints
(exit 1, ros2cli's convention)."""
from __future__ import annotations

import os
import sys
from pathlib import Path

from ament_index_python.packages import PackageNotFoundError, get_package_prefix, get_packages_with_prefixes


def executables(pkg: str) -> list[str]:
    try:
        libdir = Path(get_package_prefix(pkg), "lib", pkg)
    except PackageNotFoundError:
        raise RuntimeError(f"Package '{pkg}' not found "
                           f"(AMENT_PREFIX_PATH={os.environ.get('AMENT_PREFIX_PATH', '')!r})") from None
    if not libdir.is_dir():
        return []
    return sorted(p.name for p in libdir.iterdir() if p.is_file() and os.access(p, os.X_OK))


def run(prefix: list[str], pkg: str, exe: str, rest: list[str]) -> None:
    """Replaces this process with `exe` of `pkg` (after `prefix`, e.g. a debugger)."""
    if exe not in executables(pkg):
        raise RuntimeError(f"No executable found: '{exe}' in package '{pkg}' "
                           f"(has: {', '.join(executables(pkg)) or 'none'})")
    path = Path(get_package_prefix(pkg), "lib", pkg, exe)
    # Python launchers run on this interpreter, so an unactivated venv still works.
    head = path.read_bytes()[:128]
    cmd = [sys.executable, str(path)] if head.startswith(b"#!") and b"python" in head.split(b"\n")[0] else [str(path)]
    cmd = prefix + cmd + rest
    os.execvp(cmd[0], cmd)


def list_packages() -> None:
    print("\n".join(sorted(get_packages_with_prefixes())))


def list_executables(pkgs: list[str]) -> None:
    for p in pkgs or sorted(get_packages_with_prefixes()):
        for e in executables(p):
            print(p, e)


def prefix(pkg: str) -> None:
    try:
        print(get_package_prefix(pkg))
    except PackageNotFoundError:
        raise RuntimeError(f"Package not found: {pkg}") from None
