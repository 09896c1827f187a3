"""The trainer's ROS 2 nodes: the recorder (MCAP bags), the random actor and the checkpoint
publisher.

May import: ROS, protocad_ros, sim_bridge.contract, sim_bridge.nodekit, trainer.runs, trainer.settings, trainer.bag, trainer.data
"""
