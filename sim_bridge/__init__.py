"""The context-randomized DeepMind Control suite and the sim-bridge node (ROS package
`sim_bridge`), the bottom floor every other package builds on.

  contract/  topics, message fill/read helpers, QoS, the task and context tables
  nodekit/   the node plumbing all nodes share: base node, lifecycle, run_node, publisher watch
  sim/       the environments, the vector env and policy rollouts (no ROS)
  bridge/    the sim-bridge node, its parameters and diagnostics

May import: (its own subpackages only: nothing of protocad_ros or trainer)
"""
