"""The plumbing every node of the project shares: the base node (callbacks that never kill a
node), lifecycle, parameter tables, `run_node` with its shutdown watchdog, the publisher and
type watches of the contract topics.

May import: ROS, sim_bridge.contract
"""
