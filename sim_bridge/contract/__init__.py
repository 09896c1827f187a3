"""The wire contract and task knowledge: topic names and types with their fill/read helpers,
QoS profiles, the paper's tasks and their train/test contexts. Everything else builds on it.

May import: ROS
"""
