"""The sim-bridge node (`ros2 run sim_bridge node`): one task as ROS 2 topics, its parameters and
diagnostics.

May import: ROS, sim_bridge.contract, sim_bridge.nodekit, sim_bridge.sim
"""
