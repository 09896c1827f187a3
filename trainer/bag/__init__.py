"""rosbag2-layout MCAP bags: the writer, the reader that recovers every complete message of a
cut file, the ROS 2 message definitions and CDR (de)serialisation. No ROS.

No rclpy import here: the ROS-free research path (vectorized envs -> agent -> trainer) and the
recorder node (trainer/nodes/recorder.py) write the same bags through this package, and the trainer
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

Each job has its module, imported by name: rosmsg.py (type support, hashes, message objects,
CDR), yamlcpp.py (the yaml-cpp emitter), writer.py (BagWriter, QoS profiles, with bag_info.py and
disk_safety.py) and reader.py (BagReader, recovery of cut files).

May import: protocad_ros.atomic
"""
