"""The recorder's command line (`ros2 run trainer record`, built in trainer/nodes/recorder.py's
start_recorder): `ros2 bag record`'s options of Jazzy that it has, its own, the disk budget's
(recorder_guard.py), and those it refuses with the reason; the option values that need parsing
(--custom-data, --qos-profile-overrides-path). No ROS here."""
from __future__ import annotations

import argparse
from typing import Any, Sequence

import yaml

from sim_bridge.contract import topics as T
from trainer.bag import mcap_io
from trainer.nodes.recorder_guard import add_budget_options
from trainer.nodes.recorder_loss import DEFAULT_LEASE_S
from trainer.nodes.recorder_topics import DEFAULT_QUEUE_DEPTH

#: `ros2 bag record` (Jazzy) options this recorder does not have, and why (each is refused
#: with that reason rather than silently ignored).
UNSUPPORTED_OPTIONS: dict[str, str] = {
    "--services": "service recording (service event topics) is not supported",
    "--all-services": "service recording (service event topics) is not supported",
    "--exclude-services": "service recording (service event topics) is not supported",
    "--topic-types": "selecting topics by type is not supported: name them, or use --regex",
    "--exclude-topic-types": "excluding topics by type is not supported: use --exclude-regex",
    "--include-unpublished-topics": "a topic is recorded once a publisher offers its QoS (as the "
                                    "default ros2 bag record does)",
    "--ignore-leaf-topics": "not supported",
    "--use-sim-time": "messages are stamped with receive and source times, never /clock",
    "--snapshot-mode": "snapshot mode is not supported",
    "--start-paused": "pausing is not supported",
    "--max-cache-size": "there is no write cache: each message is handed to the MCAP writer "
                        "as it arrives (chunking is --chunk-size)",
    "--compression-mode": "rosbag2's file/message compression is not supported: MCAP chunks are "
                          "compressed instead (--compression zstd|lz4|none, "
                          "or --storage-preset-profile)",
    "--compression-format": "see --compression-mode",
    "--compression-queue-size": "see --compression-mode",
    "--compression-threads": "see --compression-mode",
    "--storage-config-file": "MCAP writer options are --chunk-size and --compression",
    "--static-topics-path": "not supported",
}
#: MCAP storage presets of rosbag2 (`--storage-preset-profile`) as our chunk compression.
STORAGE_PRESETS = {"none": "zstd", "fastwrite": "none", "zstd_fast": "zstd", "zstd_small": "zstd"}


class _Unsupported(argparse.Action):
    def __init__(self, option_strings, dest, **kw):
        kw.setdefault("nargs", "*")
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string}: {UNSUPPORTED_OPTIONS[option_string]} (this recorder follows "
                     "`ros2 bag record` of Jazzy for the options it has)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="ros2 run trainer record",
        description="Record ROS 2 topics into a rosbag2-compatible MCAP bag directory "
                    "(NAME/NAME_0.mcap ... + metadata.yaml). Options follow `ros2 bag record` of "
                    "Jazzy (same names, same meanings: -e/--regex includes, --exclude-regex "
                    "excludes); its options this recorder lacks are refused with the reason. Every "
                    "option is also a ROS parameter (--ros-args -p name:=value), except "
                    "--lease-duration (needed before the node exists). SIGINT/SIGTERM close "
                    "the bag cleanly; a write error (disk full) closes it and exits 3.",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    add_rosbag2_options(ap)
    add_own_options(ap)
    add_budget_options(ap)
    add_refused_options(ap)
    return ap


def add_rosbag2_options(ap: argparse.ArgumentParser) -> None:
    """The options `ros2 bag record` of Jazzy has, with its names and meanings."""
    ap.add_argument("-o", "--output", default=None,
                    help="bag directory to create (default: rosbag2_YYYY_MM_DD-HH_MM_SS)")
    ap.add_argument("-s", "--storage", default="mcap", choices=("mcap",),
                    help="storage identifier (only mcap; default mcap)")
    ap.add_argument("topics", nargs="*", default=[],
                    help="topics to record (default, with no topic, -a or -e: the contract topics "
                         "image, step_info, context, action, context_features in --namespace, and /clock)")
    ap.add_argument("--topics", dest="topics_opt", nargs="+", default=[], metavar="TOPIC",
                    help="space-delimited list of topics to record (as the positional ones)")
    ap.add_argument("-a", "--all", dest="all_topics", action="store_true",
                    help="record every topic (hidden ones excluded)")
    ap.add_argument("--all-topics", dest="all_topics", action="store_true", help="same as -a")
    ap.add_argument("-e", "--regex", default="",
                    help="record only topics matching this regular expression (re.search); "
                         "-a overrides it")
    ap.add_argument("--exclude-regex", default="",
                    help="do not record topics matching this regular expression; works on top of "
                         "-a, --topics and -e")
    ap.add_argument("--exclude-topics", nargs="+", default=[], metavar="TOPIC",
                    help="topics not to record; works on top of -a, --topics and -e")
    ap.add_argument("--include-hidden-topics", action="store_true",
                    help="with -a or -e: hidden topics too")
    ap.add_argument("--no-discovery", action="store_true",
                    help="record only topics present at start-up")
    ap.add_argument("-p", "--polling-interval", type=int, default=200, metavar="MS",
                    help="milliseconds between graph polls for topics that appear late (default 200)")
    ap.add_argument("--qos-profile-overrides-path", type=argparse.FileType("r"), default=None,
                    metavar="YAML", help="QoS for specific topics, as ros2 bag record: "
                    "{/topic: {reliability: reliable|best_effort, durability: volatile|transient_local, "
                    "history: keep_last|keep_all, depth: N}}")
    ap.add_argument("-f", "--serialization-format", default="cdr", choices=("cdr",),
                    help="serialization format (only cdr, what every rmw here uses)")
    ap.add_argument("-b", "--max-bag-size", dest="max_bagfile_size", type=int, default=0,
                    help="split the bag at this file size in bytes (0: no split; >= 1024)")
    ap.add_argument("-d", "--max-bag-duration", dest="max_bagfile_duration", type=float,
                    default=0.0, help="split the bag after this many seconds (0: no split)")
    ap.add_argument("--storage-preset-profile", choices=sorted(STORAGE_PRESETS), default=None,
                    help="rosbag2's MCAP presets, as chunk compression: fastwrite = none, "
                         "zstd_fast / zstd_small / none = zstd")
    ap.add_argument("--custom-data", nargs="*", default=[], metavar="KEY=VALUE",
                    help="stored under custom_data in metadata.yaml (as ros2 bag record)")
    ap.add_argument("--node-name", default="recorder", help="ROS node name (default recorder)")
    ap.add_argument("--log-level", choices=("debug", "info", "warn", "error", "fatal"), default="info")
    ap.add_argument("--disable-keyboard-controls", action="store_true",
                    help="accepted for compatibility: this recorder has no keyboard controls")


def add_own_options(ap: argparse.ArgumentParser) -> None:
    """Options `ros2 bag record` does not have: the contract's namespace, the MCAP chunks, the
    subscriptions' history, the status log and the DDS lease."""
    g = ap.add_argument_group("this recorder's own options")
    g.add_argument("--namespace", default=T.DEFAULT_NAMESPACE,
                   help="namespace of the default contract topics (default /protocad)")
    g.add_argument("--compression", choices=("zstd", "lz4", "none"), default=None,
                   help="MCAP chunk compression (default zstd)")
    g.add_argument("--chunk-size", type=int, default=mcap_io.DEFAULT_CHUNK_SIZE,
                   help=f"uncompressed chunk size in bytes (smaller: less lost on SIGKILL; default "
                        f"{mcap_io.DEFAULT_CHUNK_SIZE})")
    g.add_argument("--flush-interval", type=float, default=1.0,
                   help="write the open chunk at least every this many seconds (0: only by "
                        "size); bounds what a SIGKILL loses (default 1.0)")
    g.add_argument("--queue-depth", type=int, default=DEFAULT_QUEUE_DEPTH,
                   help="history of the subscriptions: 0 = KEEP_ALL (default: a backlog of any size "
                        "holds KEEP_ALL writers back instead of being dropped), N > 0 = KEEP_LAST(N) "
                        "(never holds a writer back; drops the oldest of a deeper backlog, counted)")
    g.add_argument("--status-interval", type=float, default=0.0,
                   help="log message counts every this many seconds (0: off)")
    g.add_argument("--lease-duration", type=float, default=DEFAULT_LEASE_S, metavar="S",
                   help="the DDS participant lease the recorder announces: a stall (SIGSTOP, a "
                        "debugger, an overloaded machine) shorter than this loses nothing, since "
                        "reliable KEEP_ALL writers (a lock-step bridge) keep what it has not "
                        "acknowledged (and pause after 5,000 samples); a longer one makes the "
                        "writers drop it and its backlog, which the recorder counts as LOST when "
                        "the next sample comes; the stall itself is reported (STALLED, metadata "
                        "protocad_stalls_past_lease). A recorder killed outright stays in the graph "
                        "this long. 0: Fast DDS's own (20 s, or the profile's). Command line "
                        f"only: it must be known before the node exists (default {DEFAULT_LEASE_S:g})")


def add_refused_options(ap: argparse.ArgumentParser) -> None:
    """`ros2 bag record`'s options this recorder lacks: each exits 2 with the reason (hidden
    from --help)."""
    g = ap.add_argument_group("`ros2 bag record` options this recorder does not have (refused, "
                              "with the reason)")
    for opt in UNSUPPORTED_OPTIONS:
        g.add_argument(opt, action=_Unsupported, help=argparse.SUPPRESS)


def parse_custom_data(items: Sequence[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--custom-data expects KEY=VALUE, got {item!r}")
        out[key] = value
    return out


def load_qos_overrides(stream: Any) -> dict[str, dict[str, Any]]:
    """The YAML of --qos-profile-overrides-path: {topic: {policy: value}} (ValueError if malformed)."""
    data = yaml.safe_load(stream) or {}
    if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
        raise ValueError("--qos-profile-overrides-path: expected a mapping of topic -> QoS policies")
    allowed = {"reliability", "durability", "history", "depth"}
    for topic, policies in data.items():
        bad = set(policies) - allowed
        if bad:
            raise ValueError(f"--qos-profile-overrides-path: {topic}: unknown policies {sorted(bad)}; "
                             f"supported: {sorted(allowed)}")
    return {str(k): dict(v) for k, v in data.items()}
