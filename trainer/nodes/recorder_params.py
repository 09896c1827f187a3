"""The recorder's ROS parameters, each declared once: RecorderNode declares this table (with
its command line's values as the defaults: a `--ros-args -p` override wins), recorder_cli.py
generates the command line's options from it, and msgs_docs/recorder.md's table is checked
against it (tests/docs/test_commands.py). No ROS here."""
from __future__ import annotations

from sim_bridge.contract import topics as T
from sim_bridge.nodekit.param_table import Param
from trainer.bag.writer import DEFAULT_CHUNK_SIZE
from trainer.nodes.record_budget import (
    DEFAULT_FLOOD_FACTOR,
    DEFAULT_MIN_FREE_DISK,
    DIAGNOSTICS_BYTE_BUDGET,
    DIAGNOSTICS_MESSAGE_BYTES,
    DIAGNOSTICS_RATE_LIMIT_HZ,
    IMAGE_BYTES_PER_S,
    IMAGE_MESSAGE_BYTES,
    STEP_TOPIC_RATE_HZ,
)
from trainer.nodes.recorder_topics import DEFAULT_QUEUE_DEPTH


def _row(name: str, default: bool | int | float | str | tuple[str, ...], description: str,
         choices: tuple[str, ...] | None = None) -> Param:
    # Settable at run time as far as ROS goes (the descriptors the node always had), though it
    # reads them once, at start.
    return Param(name, default, description, read_only=False, choices=choices)


PARAMS: tuple[Param, ...] = (
    # What `ros2 bag record` of Jazzy also has, with its meaning.
    _row("output", "", "bag directory to create (default: rosbag2_YYYY_MM_DD-HH_MM_SS)"),
    _row("topics", (), "topics to record (default, with no topic, -a or -e: the contract topics image, "
                       "step_info, context, action, context_features in --namespace, and /clock)"),
    _row("all_topics", False, "record every topic (hidden ones excluded)"),
    _row("regex", "", "record only topics matching this regular expression (re.search); -a overrides it"),
    _row("exclude_regex", "", "do not record topics matching this regular expression; works on top of "
                              "-a, --topics and -e"),
    _row("exclude_topics", (), "topics not to record; works on top of -a, --topics and -e"),
    _row("include_hidden_topics", False, "with -a or -e: hidden topics too"),
    _row("no_discovery", False, "record only topics present at start-up"),
    _row("discovery_interval", 0.2, "seconds between graph polls for topics that appear late "
                                    "(the command line's -p/--polling-interval, in ms)"),
    _row("max_bagfile_size", 0, "split the bag at this file size in bytes (0: no split; >= 1024)"),
    _row("max_bagfile_duration", 0.0, "split the bag after this many seconds (0: no split)"),
    # This recorder's own.
    _row("namespace", T.DEFAULT_NAMESPACE, "namespace of the default contract topics (default /protocad)"),
    _row("compression", "zstd", "MCAP chunk compression (default zstd)", choices=("zstd", "lz4", "none")),
    _row("chunk_size", DEFAULT_CHUNK_SIZE,
         f"uncompressed chunk size in bytes (smaller: less lost on SIGKILL; default {DEFAULT_CHUNK_SIZE})"),
    _row("flush_interval", 1.0, "write the open chunk at least every this many seconds (0: only by "
                                "size); bounds what a SIGKILL loses (default 1.0)"),
    _row("queue_depth", DEFAULT_QUEUE_DEPTH,
         "history of the subscriptions: 0 = KEEP_ALL (default: a backlog of any size holds KEEP_ALL "
         "writers back instead of being dropped), N > 0 = KEEP_LAST(N) (never holds a writer back; "
         "drops the oldest of a deeper backlog, counted)"),
    _row("status_interval", 0.0, "log message counts every this many seconds (0: off)"),
    # The disk budget (record_budget.py): a flood from any participant must not fill the disk.
    _row("max_topic_rate", 0.0, "record at most this many messages per second of each topic (2 s of "
                                "burst); the rest are dropped and counted (0: no limit beyond the "
                                "contract topics' defaults; default 0)"),
    _row("rate_limits", (), "TOPIC=HZ: a rate limit for one topic, over --max-topic-rate and its default "
                            f"(contract topics: {STEP_TOPIC_RATE_HZ:g} msg/s, /diagnostics "
                            f"{DIAGNOSTICS_RATE_LIMIT_HZ:g}); 0 turns it off (with a WARNING)"),
    _row("max_topic_bytes", 0, "stop recording a topic once it has this many bytes in the bag (counted; "
                               "0: no limit; default 0)"),
    _row("byte_budgets", (), "TOPIC=BYTES: a byte budget for one topic, over --max-topic-bytes and its "
                             f"default (/diagnostics {DIAGNOSTICS_BYTE_BUDGET}); 0 turns it off (with a "
                             "WARNING)"),
    _row("byte_rate_limits", (), "TOPIC=BYTES_PER_S: a byte-rate limit for one topic, over its default "
                                 f"(image {IMAGE_BYTES_PER_S}, the other contract topics less); 0 turns "
                                 "it off (with a WARNING)"),
    _row("message_limits", (), "TOPIC=BYTES: the largest message recorded on one topic, over its default "
                               f"(image {IMAGE_MESSAGE_BYTES}, /diagnostics {DIAGNOSTICS_MESSAGE_BYTES}, "
                               "...); larger ones are dropped and counted; 0 turns it off (with a WARNING)"),
    _row("max_total_bytes", 0, "end the recording (closed, valid bag; exit 4) once the bag holds this "
                               "many message bytes (0: no limit; default 0)"),
    _row("min_free_disk", DEFAULT_MIN_FREE_DISK,
         "end the recording (closed, valid bag; exit 4) when the disk under the bag has less free "
         f"space than this (0: off; default {DEFAULT_MIN_FREE_DISK})"),
    _row("flood_factor", DEFAULT_FLOOD_FACTOR,
         "flag a topic whose rate or byte rate over a second is X times its recent figure (and at "
         "least 100 msg/s or 10 MB/s), or above what its bounds let through (unbounded: 5000 msg/s "
         "or 64 MiB/s), in the bag's metadata (protocad_floods) and on /diagnostics (0: off; "
         f"default {DEFAULT_FLOOD_FACTOR:g})"),
)
