"""`ros2 bag info` (rosbag2's Jazzy table, from metadata.yaml or, for a bare or truncated .mcap,
from the file itself) and `ros2 bag record` (the project's recorder, trainer/nodes/recorder.py)."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from trainer.bag.reader import BagReader, read_bag_metadata

INDENT = 19  # rosbag2: the longest label ("Topic information: ") plus nothing


def _is_service_event(name: str, msgtype: str) -> bool:
    return "/srv/" in msgtype and msgtype.endswith("_Event") and name.endswith("/_service_event")


def format_file_size(size: int) -> str:
    value, units, i = float(size), ("B", "KiB", "MiB", "GiB", "TiB"), 0
    while value >= 1024 and i < 4:
        value /= 1024
        i += 1
    return f"{value:.{0 if i == 0 else 1}f} {units[i]}"


def _seconds(ns: int) -> str:
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def format_time_point(ns: int) -> str:
    t = time.localtime(ns // 1_000_000_000)
    date = time.strftime("%b ", t) + f"{t.tm_mday:2d}" + time.strftime(" %Y", t)
    return f"{date} {time.strftime('%H:%M:%S', t)}.{ns % 1_000_000_000:09d} ({_seconds(ns)})"


def format_bag_metadata(info: dict[str, Any], bag_size: int) -> str:
    """rosbag2_py's format_bag_meta_data, for the rosbag2_bagfile_information mapping."""
    pad = " " * INDENT
    topics = info.get("topics_with_message_count") or []
    plain = [t for t in topics if not _is_service_event(t["topic_metadata"]["name"], t["topic_metadata"]["type"])]
    services = [t for t in topics if t not in plain]
    start = int(info["starting_time"]["nanoseconds_since_epoch"])
    duration = int(info["duration"]["nanoseconds"])
    files = [str(p) for p in info.get("relative_file_paths") or []]
    out = ["", "Files:             " + ("\n".join([files[0], *(pad + f for f in files[1:])]) if files else ""),
           f"Bag size:          {format_file_size(bag_size)}",
           f"Storage id:        {info.get('storage_identifier', '')}",
           f"ROS Distro:        {info.get('ros_distro') or 'unknown'}",
           f"Duration:          {_seconds(duration)}s",
           f"Start:             {format_time_point(start)}",
           f"End:               {format_time_point(start + duration)}",
           f"Messages:          {int(info['message_count']) - sum(int(t['message_count']) for t in services)}"]

    def topic_line(t: dict) -> str:
        m = t["topic_metadata"]
        return (f"Topic: {m['name']} | Type: {m['type']} | Count: {t['message_count']} | "
                f"Serialization Format: {m.get('serialization_format', 'cdr')}")

    out.append("Topic information: " + "\n".join([topic_line(plain[0]), *(pad + topic_line(t) for t in plain[1:])])
               if plain else "Topic information: ")
    out.append(f"Service:           {len(services)}")
    lines = [f"Service: {t['topic_metadata']['name'][:-len('/_service_event')]} | "
             f"Type: {t['topic_metadata']['type'][:-len('_Event')]} | Event Count: {t['message_count']} | "
             f"Serialization Format: {t['topic_metadata'].get('serialization_format', 'cdr')}" for t in services]
    out.append("Service information: " + "\n".join([lines[0], *(" " * (INDENT + 2) + x for x in lines[1:])])
               if lines else "Service information: ")
    return "\n".join(out)


def _metadata_from_files(path: Path) -> tuple[dict[str, Any], int, list[str]]:
    """What metadata.yaml would say, read from the .mcap file(s) themselves."""
    reader = BagReader(path)
    first = last = None
    for raw in reader.messages():
        first = raw.log_time_ns if first is None else min(first, raw.log_time_ns)
        last = raw.log_time_ns if last is None else max(last, raw.log_time_ns)
    rep = reader.report
    notes = [f"{p}: truncated ({why}); listing every complete message" for p, why in rep.truncated.items()]
    notes += [f"{p}: {why}" for p, why in rep.errors.items()]
    notes += [f"refused: {line}" for line in rep.refused]
    info = {
        "storage_identifier": "mcap", "ros_distro": "",
        "starting_time": {"nanoseconds_since_epoch": first or 0},
        "duration": {"nanoseconds": (last - first) if first is not None else 0},
        "message_count": rep.message_count,
        "relative_file_paths": [Path(f).name if path.is_dir() else f for f in rep.files],
        "topics_with_message_count": [
            {"topic_metadata": {"name": t, "type": rep.topic_types.get(t, ""), "serialization_format": "cdr"},
             "message_count": n} for t, n in rep.counts.items()],
    }
    return info, sum(Path(f).stat().st_size for f in rep.files), notes


def sub_bags(path: Path) -> list[Path]:
    """The bags inside a folder that is not a bag itself (runs/X/bags, which the trainers take)."""
    if not path.is_dir() or (path / "metadata.yaml").exists() or any(path.glob("*.mcap")):
        return []
    return sorted(d for d in path.iterdir()
                  if d.is_dir() and ((d / "metadata.yaml").exists() or any(d.glob("*.mcap"))))


def read_info(bag: str | Path) -> tuple[dict[str, Any], int, list[str]]:
    """(bag info mapping, bag size in bytes, notes for stderr) of a bag directory or .mcap file."""
    path = Path(bag)
    if not path.exists():
        raise FileNotFoundError(f"No such file or directory: {bag}")
    if path.is_dir() and not (path / "metadata.yaml").exists() and not any(path.glob("*.mcap")):
        raise ValueError(f"{bag} is not a bag: no metadata.yaml and no .mcap file in it")
    if path.is_dir() and (path / "metadata.yaml").exists():
        info = read_bag_metadata(path)
        size = sum((path / Path(str(f)).name).stat().st_size for f in info.get("relative_file_paths") or []
                   if (path / Path(str(f)).name).exists())
        return info, size, []
    return _metadata_from_files(path)


def cmd_info(args) -> int | str | None:
    if args.storage not in (None, "mcap"):
        return f"storage {args.storage!r} is not supported here (only mcap)"
    bags = sub_bags(Path(args.bag_path))
    if bags:   # a folder of bags: each one, as `ros2 bag info` would print it
        failed = []
        for i, bag in enumerate(bags):
            print(("\n" if i else "") + f"{bag}:")
            args.bag_path = str(bag)
            why = cmd_info(args)
            if why is not None:
                print(why, file=sys.stderr)
                failed.append(bag.name)
        return f"could not read {', '.join(failed)}" if failed else None
    try:
        info, size, notes = read_info(args.bag_path)
        table = format_bag_metadata(info, size)
    except (OSError, ValueError, KeyError, TypeError, yaml.YAMLError) as exc:
        return f"Could not read metadata for {args.bag_path}: {type(exc).__name__}: {exc}"
    for n in notes:
        print(n, file=sys.stderr)
    if args.topic_name and args.verbose:
        print("Warning! You have set both the '-t' and '-v' parameters. The '-t' parameter will be ignored.")
    if args.topic_name and not args.verbose:
        for t in info.get("topics_with_message_count") or []:
            m = t["topic_metadata"]
            if not _is_service_event(m["name"], m["type"]):
                print(m["name"])
    else:
        print(table)
    return None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="Print information about a bag to the screen")
    p.add_argument("bag_path", help="Bag to open (a bag directory, or one .mcap file)")
    p.add_argument("-s", "--storage", default=None, help="Storage implementation of bag (only mcap here)")
    p.add_argument("-t", "--topic-name", action="store_true", help="Only display topic names.")
    p.add_argument("-v", "--verbose", action="store_true", help="Display request/response information for services")
    p.set_defaults(func=cmd_info)
    # `record` is dispatched before argparse (all its options belong to the recorder).
    sub.add_parser("record", help="Record ROS data to a bag (the project's recorder; see `ros2 bag record --help`)",
                   add_help=False)
