"""The policy node (`ros2 run protocad_ros policy`): its parameters, the checkpoint it serves
and reloads, the checkpoint stream it receives over DDS.

May import: ROS, protocad_ros, sim_bridge.contract, sim_bridge.nodekit
"""
