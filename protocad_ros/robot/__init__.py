"""The policy node's side that faces a real robot (msgs_docs/robot.md): camera frames in any
common encoding or compressed, commands out in a robot's joint order and units, and the
fail-safe that holds the robot when its input stops (watchdog, enable switch, rate limits).
Parts of the policy node (protocad_ros/node/policy_node.py), each an object of its own.

May import: ROS, protocad_ros.atomic, sim_bridge.contract, sim_bridge.nodekit
"""
