"""rosbag2-compatible MCAP logs without ROS: type support, BagWriter, BagReader.

No rclpy import here: the ROS-free research path (vectorized envs -> agent -> trainer) and the
recorder node (trainer/nodes/recorder.py) write the same bags through this module, and the trainer
reads them back. msgs_docs/mcap_layout.md describes the layout; in short it is what rosbag2's
MCAP storage plugin (ROS 2 Jazzy) writes:

* a bag directory ``NAME/`` with ``NAME_0.mcap``, ``NAME_1.mcap``, ... (split by size and/or
  duration) and ``metadata.yaml`` (``rosbag2_bagfile_information`` version 9) written at close;
* MCAP profile ``ros2``; one schema per type named ``pkg/msg/Type`` with encoding ``ros2msg``
  whose data is the .msg text followed by every dependency after a line of 80 ``=`` and
  ``MSG: pkg/Type`` (rosbag2's LocalMessageDefinitionSource, byte for byte);
* channels with message encoding ``cdr`` and metadata ``offered_qos_profiles`` (the YAML
  rosbag2 writes) and ``topic_type_hash`` (RIHS01);
* a metadata record ``rosbag2`` with ``serialized_metadata`` (the bag info YAML) written when a
  file is opened and again when it is closed, as rosbag2's SequentialWriter does;
* message ``log_time`` = receive time, ``publish_time`` = source (send) time;
* zstd (default), lz4 or uncompressed chunks with CRCs; a file whose writer was killed has no
  footer/summary and BagReader recovers every complete chunk.

Type support comes from the ament index (``share/<pkg>/msg/<Type>.msg`` and ``.json`` installed
by the ROS wheels): message_definition, type_hash, new_message, encode, decode.

The work is split by job: trainer/bag/rosmsg.py (type support, hashes, message objects, CDR),
trainer/bag/yamlcpp.py (the yaml-cpp emitter), trainer/bag/writer.py (BagWriter, QoS profiles) and
trainer/bag/reader.py (BagReader, recovery of cut files); this module is the one name to import.
"""
from __future__ import annotations

from trainer.bag.reader import BagReader, BagReadError, BagReport, RawMessage, read_bag_metadata
from trainer.bag.rosmsg import (
                                TypeSupportError,
                                decode,
                                decoder_for,
                                encode,
                                encoder_for,
                                message_definition,
                                message_definition_with_encoding,
                                new_message,
                                normalize_type,
                                to_plain,
                                type_hash,
)
from trainer.bag.writer import (
                                DEFAULT_CHUNK_SIZE,
                                DEFAULT_OFFERED_QOS,
                                METADATA_VERSION,
                                MIN_SPLIT_SIZE,
                                ROS_DISTRO_DEFAULT,
                                BagWriteError,
                                BagWriter,
                                qos_profile,
                                qos_yaml,
)
from trainer.bag.yamlcpp import yaml_cpp_dump

__all__ = [
    "TypeSupportError", "BagWriteError", "BagReadError",
    "normalize_type", "message_definition", "message_definition_with_encoding", "type_hash",
    "new_message", "encode", "decode", "decoder_for", "encoder_for", "to_plain",
    "qos_profile", "qos_yaml", "yaml_cpp_dump", "DEFAULT_OFFERED_QOS",
    "BagWriter", "BagReader", "BagReport", "RawMessage", "read_bag_metadata",
    "METADATA_VERSION", "ROS_DISTRO_DEFAULT", "MIN_SPLIT_SIZE", "DEFAULT_CHUNK_SIZE",
]
