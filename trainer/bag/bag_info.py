"""What a rosbag2 (Jazzy) bag says about itself: offered QoS profiles in rosbag2's v9 form, the
per-topic and per-file records, and the metadata both metadata.yaml and each file's `rosbag2`
metadata record carry (msgs_docs/mcap_layout.md)."""
from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _pkg_version
from typing import Any, Mapping, Sequence

import yaml

from trainer.bag.rosmsg import TypeSupportError, _try_type_hash, message_definition_with_encoding, normalize_type
from trainer.bag.yamlcpp import yaml_cpp_dump

METADATA_VERSION = 9            # rosbag2 Jazzy's rosbag2_bagfile_information version
INT64_MAX = 2**63 - 1           # rosbag2's "no time yet" (std::chrono::nanoseconds::max())
INFINITE_NS = INT64_MAX  # RMW_DURATION_INFINITE = {9223372036, 854775807}


def _duration(ns: int) -> dict[str, int]:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def qos_profile(*, history: str = "unknown", depth: int = 0, reliability: str = "reliable",
                durability: str = "volatile", deadline_ns: int = INFINITE_NS,
                lifespan_ns: int = INFINITE_NS, liveliness: str = "automatic",
                liveliness_lease_duration_ns: int = INFINITE_NS,
                avoid_ros_namespace_conventions: bool = False) -> dict[str, Any]:
    """One offered QoS profile in rosbag2's v9 form. Defaults = what the ROS graph reports for a
    reliable, volatile publisher (DDS does not propagate history: 'unknown', depth 0)."""
    return {
        "history": history, "depth": int(depth), "reliability": reliability,
        "durability": durability, "deadline": _duration(deadline_ns),
        "lifespan": _duration(lifespan_ns), "liveliness": liveliness,
        "liveliness_lease_duration": _duration(liveliness_lease_duration_ns),
        "avoid_ros_namespace_conventions": bool(avoid_ros_namespace_conventions),
    }


DEFAULT_OFFERED_QOS = (qos_profile(),)


def qos_yaml(profiles: Sequence[Mapping[str, Any]]) -> str:
    """The channel metadata value rosbag2 writes (serialize_rclcpp_qos_vector)."""
    return yaml_cpp_dump(list(profiles))


def parse_qos(qos: Any) -> list[dict[str, Any]]:
    if qos is None:
        return []
    if isinstance(qos, str):
        loaded = yaml.safe_load(qos) if qos.strip() else []
        if not isinstance(loaded, list):
            raise ValueError(f"offered_qos_profiles YAML must be a list, got {type(loaded)}")
        return [dict(x) for x in loaded]
    if isinstance(qos, Mapping):
        return [dict(qos)]
    return [dict(x) for x in qos]


def library_string() -> str:
    def ver(name: str) -> str:
        try:
            return _pkg_version(name)
        except PackageNotFoundError:
            return "unknown"
    return f"protocad-ros {ver('protocad-ros')} trainer.bag; mcap-python {ver('mcap')}"


@dataclass
class TopicInfo:
    name: str
    msgtype: str
    serialization_format: str
    qos: list[dict[str, Any]]
    type_hash: str
    encoding: str
    definition: str
    message_count: int = 0

    def metadata(self) -> dict[str, Any]:
        return {"topic_metadata": {
            "name": self.name, "type": self.msgtype,
            "serialization_format": self.serialization_format,
            "offered_qos_profiles": self.qos, "type_description_hash": self.type_hash},
            "message_count": self.message_count}


@dataclass
class FileInfo:
    path: str
    starting_time: int = INT64_MAX
    end_time: int = 0
    message_count: int = 0

    def count(self, t_ns: int) -> None:
        """One more message, logged at t_ns."""
        self.starting_time = min(self.starting_time, t_ns)
        self.end_time = max(self.end_time, t_ns)
        self.message_count += 1

    def metadata(self) -> dict[str, Any]:
        dur = self.end_time - self.starting_time if self.message_count else 0
        return {"path": self.path, "starting_time": {"nanoseconds_since_epoch": self.starting_time},
                "duration": {"nanoseconds": dur}, "message_count": self.message_count}



def plain_type(msgtype: str) -> str:
    """'pkg/msg/Type' for any spelling of an installed type; an unknown one as given."""
    try:
        return normalize_type(msgtype)
    except TypeSupportError:
        return msgtype


def topic_info(name: str, msgtype: str, qos: Any = None, *, type_hash: str | None = None,
               serialization_format: str = "cdr", definition: tuple[str, str] | None = None) -> TopicInfo:
    """A topic's record: offered QoS as rosbag2's YAML, a list of qos_profile() dicts or None
    ('[]'); the type hash and (encoding, text) definition from the local ament index where not
    given (as rosbag2 does; ('unknown', '') when the type is not installed)."""
    if definition is None:
        try:
            definition = message_definition_with_encoding(msgtype)
        except TypeSupportError:
            definition = ("unknown", "")  # MessageDefinition::empty_message_definition_for
    return TopicInfo(name=name, msgtype=msgtype, serialization_format=serialization_format, qos=parse_qos(qos),
                     type_hash=_try_type_hash(msgtype) if type_hash is None else type_hash,
                     encoding=definition[0], definition=definition[1])


def bag_metadata(topics: Sequence[TopicInfo], files: Sequence[FileInfo], *, start: int, end: int,
                 count: int, custom_data: Mapping[str, str] | None, ros_distro: str) -> dict[str, Any]:
    """The bag info (the dict under rosbag2_bagfile_information)."""
    return {
        "version": METADATA_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": end - start if count else 0},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [t.metadata() for t in topics],
        "compression_format": "",  # chunk compression is internal to the MCAP storage
        "compression_mode": "",
        "relative_file_paths": [f.path for f in files],
        "files": [f.metadata() for f in files],
        "custom_data": custom_data,
        "ros_distro": ros_distro,
    }
