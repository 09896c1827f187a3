"""The ProtoCAD agent and its policy node (ROS package `protocad_ros`).

  model/       the method: config, networks, RSSM, prototypes, behaviour, the agents (no ROS)
  checkpoint/  the checkpoint format, its limits and signatures (torch only in agent_file.py)
  node/        the policy as a ROS 2 node: parameters, checkpoint serving and receiving
  (here)       what both sides share, free of ROS: atomic files, `Policy` (an agent acting step
               by step), the live rerun view

May import: protocad_ros.model, protocad_ros.checkpoint, sim_bridge.contract
"""
