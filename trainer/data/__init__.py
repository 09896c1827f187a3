"""The dataset over recorded bags: a cached store of episodes, sequence batches for training,
what it reads and the reports it gives. No ROS.

May import: protocad_ros.model.agent_base (the batch an agent trains on), sim_bridge.contract, trainer.bag
"""
