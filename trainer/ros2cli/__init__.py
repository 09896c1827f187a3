"""A `ros2` front-end for environments without ros2cli.

ros2cli and rosbag2 are not installable from PyPI, so this environment ships a stand-in for the
verbs ROS users reach for daily, printing what their ros2cli (Jazzy) counterparts print for the
options supported here (`ros2 VERB --help` lists them):

    ros2 run [--prefix CMD] PKG EXECUTABLE [ARGS...]        ros2 pkg list|executables|prefix
    ros2 topic list|info|echo|hz                            ros2 node list|info
    ros2 param list|get|set|dump|describe                   ros2 service list|type|call
    ros2 lifecycle nodes|get|set|list                       ros2 bag info|record

Graph verbs create a short-lived hidden node (`_ros2cli_<pid>`) and wait `--spin-time` for
discovery, as ros2cli does without its daemon. Anything else says that it needs a full ROS 2
install. Where a real ros2cli exists (importable, or another `ros2` on PATH), every call is
handed to it.

May import: ROS, trainer.runs, trainer.run_config, trainer.torch_setup, trainer.metrics_log, trainer.cli_values, trainer.console, trainer.bag, trainer.nodes
"""
from __future__ import annotations

import argparse
import importlib
import os
import shlex
import sys
from pathlib import Path

COMMANDS = {  # command -> (module, what it is)
    "topic": ("trainer.ros2cli.topic", "Various topic related sub-commands"),
    "node": ("trainer.ros2cli.node", "Various node related sub-commands"),
    "param": ("trainer.ros2cli.param", "Various param related sub-commands"),
    "service": ("trainer.ros2cli.service", "Various service related sub-commands"),
    "lifecycle": ("trainer.ros2cli.lifecycle", "Various lifecycle related sub-commands"),
    "bag": ("trainer.ros2cli.bag", "Various rosbag related sub-commands"),
}
SUBSET = """\
    ros2 run [--prefix CMD] PKG EXECUTABLE [ARGS...]
    ros2 pkg list | executables [PKG] | prefix PKG
    ros2 topic list | info | echo | hz
    ros2 node list | info
    ros2 param list | get | set | dump | describe
    ros2 service list | type | call
    ros2 lifecycle nodes | get | set | list
    ros2 bag info | record
"""
_FRONT_END_MARKERS = ("trainer.ros2cli", "protocad_ros.ros2cli")  # ours, now and in older installs


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
        if not any(m in head for m in _FRONT_END_MARKERS):
            return [str(cand)]
    return None


def _die(msg: str, code: int = 1):
    print(msg, file=sys.stderr)
    sys.exit(code)


#: What this project offers instead of a verb the front-end lacks (first words of the command).
ALTERNATIVES = {
    ("launch",): "protocad-stack FILE.yaml starts the bridge, the policy and the recorder (README "
                 "'Running it as ROS 2 nodes'); with a full ROS 2 install: ros2 launch trainer "
                 "protocad.launch.py",
    ("topic", "pub"): "the nodes publish and read the contract of msgs_docs/topics.md; "
                      "protocad-stack runs them, ros2 service call /protocad/reset resets an episode",
    ("bag", "play"): "the trainers read bags directly: protocad-train --logs BAG (and "
                     "protocad-visualize --logs BAG); `rerun BAG.mcap` shows one",
    ("interface",): "msgs_docs/topics.md lists every topic's type and fields; ros2 topic list -t "
                    "shows the types on the graph",
}


def _unsupported(argv: list[str]):
    hint = next((text for words, text in ALTERNATIVES.items() if tuple(argv[:len(words)]) == words), None)
    _die(f"ros2 {' '.join(argv)}: not supported by this front-end (needs a full ROS 2 install with "
         "ros2cli; this environment has the ROS 2 Python wheels only)."
         + (f"\nInstead: {hint}." if hint else "") + "\nSupported:\n\n" + SUBSET, 2)


# ------------------------------------------------------------------ run / pkg (the ament index)
def _run(args: list[str]) -> tuple[list[str], str, str, list[str]]:
    """`ros2 run`'s words: (prefix command, package, executable, its arguments)."""
    prefix: list[str] = []
    if args[:1] == ["--prefix"]:
        if len(args) < 2:
            _die("ros2 run: --prefix needs a value", 2)
        prefix, args = shlex.split(args[1]), args[2:]
    if len(args) < 2:
        _die("usage: ros2 run [--prefix CMD] PKG EXECUTABLE [ARGS...]", 2)
    return prefix, args[0], args[1], args[2:]


def _pkg(command: str, rest: list[str], argv: list[str]) -> None:
    """`ros2 run` and `ros2 pkg`: the ament index only, no rclpy."""
    if command == "pkg" and not (rest[:1] in (["list"], ["executables"]) or (rest[:1] == ["prefix"] and len(rest) == 2)):
        _unsupported(argv)
    words = _run(rest) if command == "run" else None
    # The ament index only for these two commands (the other verbs' modules are imported as
    # they run, too).
    from trainer.ros2cli import pkg

    try:
        if words is not None:
            pkg.run(*words)
        elif rest[0] == "list":
            pkg.list_packages()
        elif rest[0] == "executables":
            pkg.list_executables(rest[1:2])
        else:
            pkg.prefix(rest[1])
    except RuntimeError as exc:  # ros2cli's convention: the message on stderr, exit 1
        _die(str(exc))


# ------------------------------------------------------------------ graph and bag verbs
def _verb(command: str, rest: list[str], argv: list[str]) -> int:
    module_name, description = COMMANDS[command]
    module = importlib.import_module(module_name)
    parser = argparse.ArgumentParser(prog=f"ros2 {command}", description=description)
    sub = parser.add_subparsers(dest="verb", metavar="Commands")
    module.register(sub)
    if rest and not rest[0].startswith("-") and rest[0] not in sub.choices:
        _unsupported(argv)
    args = parser.parse_args(rest)
    if args.verb is None:
        parser.print_help()
        return 0
    from rclpy.executors import ExternalShutdownException

    try:
        rc = args.func(args)
    except (KeyboardInterrupt, ExternalShutdownException):
        # Ctrl-C: rclpy's handler shuts the context down; a verb caught inside a wait sees it
        # as ExternalShutdownException rather than as rclpy.ok() turning false. Both end cleanly.
        return 0
    except RuntimeError as exc:  # ros2cli's convention: the message on stderr, exit 1
        rc = str(exc)
    if isinstance(rc, str):
        print(rc, file=sys.stderr)
        return 1
    return int(rc or 0)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    real = _real_ros2()
    if real is not None:
        os.execvp(real[0], real + argv)
    try:  # ros2cli's choice too: every printed line reaches a pipe at once (echo, hz)
        sys.stdout.reconfigure(line_buffering=True)
    except AttributeError:
        pass
    if not argv or argv[0] in ("-h", "--help"):
        print("ros2 (protocad-ros front-end; ros2cli is not installed here). Supported:\n\n" + SUBSET)
        return
    command, rest = argv[0], argv[1:]
    if command == "run":
        if rest[:1] in (["-h"], ["--help"]):
            print("usage: ros2 run [--prefix CMD] PKG EXECUTABLE [ARGS...]")
            return
        _pkg(command, rest, argv)
    elif command == "pkg":
        _pkg(command, rest, argv)
    elif command == "bag" and rest[:1] == ["record"]:
        from trainer.nodes.recorder import main as record

        sys.exit(record(rest[1:]))
    elif command in COMMANDS:
        sys.exit(_verb(command, rest, argv))
    else:
        _unsupported(argv)


