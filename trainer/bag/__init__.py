"""rosbag2-layout MCAP bags: the writer, the reader that recovers every complete message of a
cut file, the ROS 2 message definitions and CDR (de)serialisation. No ROS.

May import: protocad_ros.atomic
"""
