"""A small `ros2` front-end for environments without ros2cli.

ros2cli and rosbag2 are not installable from PyPI, so this environment ships a stand-in that
supports exactly this subset, resolved through the same ament index the real tool uses
(AMENT_PREFIX_PATH):

    ros2 run [--prefix CMD] PKG EXECUTABLE [ARGS...]
    ros2 pkg list
    ros2 pkg executables [PKG]
    ros2 pkg prefix PKG

Where a real ros2cli exists (importable, or another `ros2` on PATH), every call is handed to it.
"""
from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path

SUBSET = """\
    ros2 run [--prefix CMD] PKG EXECUTABLE [ARGS...]
    ros2 pkg list
    ros2 pkg executables [PKG]
    ros2 pkg prefix PKG
"""


def _real_ros2() -> list[str] | None:
    """Command line of a real ros2cli, if there is one."""
    try:
        import ros2cli.cli  # noqa: F401  (present in a full ROS 2 install)

        return [sys.executable, "-c", "import sys; from ros2cli.cli import main; sys.exit(main())"]
    except ImportError:
        pass
    me = Path(sys.argv[0]).resolve()
    for d in os.environ.get("PATH", "").split(os.pathsep):
        cand = Path(d, "ros2")
        if not (cand.is_file() and os.access(cand, os.X_OK)) or cand.resolve() == me:
            continue
        try:
            head = cand.read_text(errors="replace")[:2000]
        except OSError:
            continue
        if "protocad_ros.ros2cli" not in head:
            return [str(cand)]
    return None


def _packages() -> dict[str, str]:
    from ament_index_python.packages import get_packages_with_prefixes

    return get_packages_with_prefixes()


def _executables(pkg: str) -> list[str]:
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        libdir = Path(get_package_prefix(pkg), "lib", pkg)
    except PackageNotFoundError:
        _die(f"Package '{pkg}' not found (AMENT_PREFIX_PATH={os.environ.get('AMENT_PREFIX_PATH', '')!r})")
    if not libdir.is_dir():
        return []
    return sorted(p.name for p in libdir.iterdir() if p.is_file() and os.access(p, os.X_OK))


def _die(msg: str, code: int = 1):
    print(msg, file=sys.stderr)
    sys.exit(code)


def _run(args: list[str]) -> None:
    prefix: list[str] = []
    if args[:1] == ["--prefix"]:
        if len(args) < 2:
            _die("ros2 run: --prefix needs a value", 2)
        prefix, args = shlex.split(args[1]), args[2:]
    if len(args) < 2:
        _die("usage: ros2 run [--prefix CMD] PKG EXECUTABLE [ARGS...]", 2)
    pkg, exe, rest = args[0], args[1], args[2:]
    if exe not in _executables(pkg):
        _die(f"No executable found: '{exe}' in package '{pkg}' (has: {', '.join(_executables(pkg)) or 'none'})")
    from ament_index_python.packages import get_package_prefix

    path = Path(get_package_prefix(pkg), "lib", pkg, exe)
    # Python launchers run on this interpreter, so an unactivated venv still works.
    head = path.read_bytes()[:128]
    cmd = [sys.executable, str(path)] if head.startswith(b"#!") and b"python" in head.split(b"\n")[0] else [str(path)]
    cmd = prefix + cmd + rest
    os.execvp(cmd[0], cmd)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    real = _real_ros2()
    if real is not None:
        os.execvp(real[0], real + argv)
    if not argv or argv[0] in ("-h", "--help"):
        print("ros2 (protocad-ros front-end; ros2cli is not installed here). Supported:\n\n" + SUBSET)
        return
    verb, rest = argv[0], argv[1:]
    if verb == "run":
        if rest[:1] in (["-h"], ["--help"]):
            print("usage: ros2 run [--prefix CMD] PKG EXECUTABLE [ARGS...]")
            return
        _run(rest)
    elif verb == "pkg" and rest[:1] == ["list"]:
        print("\n".join(sorted(_packages())))
    elif verb == "pkg" and rest[:1] == ["executables"]:
        pkgs = rest[1:2] or sorted(_packages())
        for p in pkgs:
            for e in _executables(p):
                print(p, e)
    elif verb == "pkg" and rest[:1] == ["prefix"] and len(rest) == 2:
        from ament_index_python.packages import PackageNotFoundError, get_package_prefix

        try:
            print(get_package_prefix(rest[1]))
        except PackageNotFoundError:
            _die(f"Package not found: {rest[1]}")
    else:
        _die(
            f"ros2 {' '.join(argv)}: not supported by this front-end (real ros2cli not installed).\n"
            "Supported:\n\n" + SUBSET,
            2,
        )


if __name__ == "__main__":
    main()
