"""The recorder's command line (`ros2 run trainer record`, built in trainer/nodes/recorder.py's
start_recorder), generated: its ROS parameters' options from their table (recorder_params.py,
`RECORD_FORMS` naming the flags `ros2 bag record` of Jazzy gives them), the options of the
command line alone from `RecordCommand`, and `ros2 bag record`'s options it refuses, with the
reason; the option values that need parsing (--custom-data, --qos-profile-overrides-path).
No ROS here."""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any, Sequence

import yaml

from trainer.nodes.recorder_loss import DEFAULT_LEASE_S
from trainer.nodes.recorder_params import PARAMS
from trainer.settings import arg, settings_parser, table_settings

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


OWN = "this recorder's own options"
BUDGET = "the disk budget (a flood from any participant must not fill the disk)"

#: How the command line gives the ROS parameters whose option is not `--name-with-dashes`
#: (`ros2 bag record`'s names), and their help groups (trainer.settings.table_settings).
RECORD_FORMS: dict[str, dict[str, Any] | None] = {
    "output": {"flags": ("-o", "--output"), "default": None},
    "topics": {"flags": ("topics",), "nargs": "*"},
    "all_topics": {"flags": ("-a", "--all", "--all-topics")},
    "regex": {"flags": ("-e", "--regex")},
    "exclude_topics": {"metavar": "TOPIC"},
    "discovery_interval": None,   # given in ms: --polling-interval
    "max_bagfile_size": {"flags": ("-b", "--max-bag-size")},
    "max_bagfile_duration": {"flags": ("-d", "--max-bag-duration")},
    **{k: {"group": OWN} for k in ("namespace", "chunk_size", "flush_interval", "queue_depth", "status_interval")},
    "compression": {"group": OWN, "default": None},   # unset: --storage-preset-profile's
    "max_topic_rate": {"group": BUDGET, "metavar": "HZ"},
    "rate_limits": {"group": BUDGET, "flags": ("--rate-limit",), "metavar": "TOPIC=HZ"},
    "max_topic_bytes": {"group": BUDGET, "metavar": "BYTES"},
    "byte_budgets": {"group": BUDGET, "flags": ("--byte-budget",), "metavar": "TOPIC=BYTES"},
    "byte_rate_limits": {"group": BUDGET, "flags": ("--byte-rate-limit",), "metavar": "TOPIC=BYTES_PER_S"},
    "message_limits": {"group": BUDGET, "flags": ("--max-message-bytes",), "metavar": "TOPIC=BYTES"},
    "max_total_bytes": {"group": BUDGET, "metavar": "BYTES"},
    "min_free_disk": {"group": BUDGET, "metavar": "BYTES"},
    "flood_factor": {"group": BUDGET, "metavar": "X"},
}
RecorderParams = table_settings("RecorderParams", PARAMS, RECORD_FORMS)


@dataclass
class RecordCommand:
    """The options of the command line alone (not ROS parameters): how the node starts, and
    `ros2 bag record`'s that only have one value here."""

    storage: str = arg("mcap", "-s", "--storage", choices=("mcap",))
    """storage identifier (only mcap; default mcap)"""
    topics_opt: list[str] = arg([], "--topics", metavar="TOPIC")
    """space-delimited list of topics to record (as the positional ones)"""
    polling_interval: int = arg(200, "-p", "--polling-interval", metavar="MS")
    """milliseconds between graph polls for topics that appear late (default 200): the
    discovery_interval parameter"""
    qos_profile_overrides_path: Any = arg(None, type=argparse.FileType("r"), metavar="YAML")
    """QoS for specific topics, as ros2 bag record: {/topic: {reliability: reliable|best_effort,
    durability: volatile|transient_local, history: keep_last|keep_all, depth: N}}"""
    serialization_format: str = arg("cdr", "-f", "--serialization-format", choices=("cdr",))
    """serialization format (only cdr, what every rmw here uses)"""
    storage_preset_profile: str | None = arg(None, choices=sorted(STORAGE_PRESETS))
    """rosbag2's MCAP presets, as chunk compression: fastwrite = none, zstd_fast / zstd_small /
    none = zstd"""
    custom_data: list[str] = arg([], nargs="*", metavar="KEY=VALUE")
    """stored under custom_data in metadata.yaml (as ros2 bag record)"""
    node_name: str = "recorder"
    """ROS node name (default recorder)"""
    log_level: str = arg("info", choices=("debug", "info", "warn", "error", "fatal"))
    """the node's log level"""
    disable_keyboard_controls: bool = False
    """accepted for compatibility: this recorder has no keyboard controls"""
    lease_duration: float = arg(DEFAULT_LEASE_S, metavar="S", group=OWN)
    """the DDS participant lease the recorder announces: a stall (SIGSTOP, a debugger, an
    overloaded machine) shorter than this loses nothing, since reliable KEEP_ALL writers (a
    lock-step bridge) keep what it has not acknowledged (and pause after 5,000 samples); a
    longer one makes the writers drop it and its backlog, which the recorder counts as LOST when
    the next sample comes; the stall itself is reported (STALLED, metadata
    protocad_stalls_past_lease). A recorder killed outright stays in the graph this long. 0: Fast
    DDS's own (20 s, or the profile's). Command line only: it must be known before the node
    exists"""


class _Unsupported(argparse.Action):
    def __init__(self, option_strings, dest, **kw):
        kw.setdefault("nargs", "*")
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string}: {UNSUPPORTED_OPTIONS[option_string]} (this recorder follows "
                     "`ros2 bag record` of Jazzy for the options it has)")


def build_parser() -> argparse.ArgumentParser:
    ap = settings_parser(
        "ros2 run trainer record",
        "Record ROS 2 topics into a rosbag2-compatible MCAP bag directory "
        "(NAME/NAME_0.mcap ... + metadata.yaml). Options follow `ros2 bag record` of "
        "Jazzy (same names, same meanings: -e/--regex includes, --exclude-regex "
        "excludes); its options this recorder lacks are refused with the reason. Every "
        "option that sets a ROS parameter (recorder_params.PARAMS) can also be given as one "
        "(--ros-args -p name:=value, which wins). SIGINT/SIGTERM close the bag cleanly; a "
        "write error (disk full) closes it and exits 3.",
        [(None, RecordCommand), (None, RecorderParams)])
    add_refused_options(ap)
    return ap


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
