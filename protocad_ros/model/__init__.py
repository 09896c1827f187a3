"""The method, as the paper writes it: one config tree with the paper's defaults, networks,
RSSM, prototypes and TC-SwAV, actor-critic in imagination, the agents (ProtoCAD, its ablations
and baselines, DrQ). Free of ROS so it trains on a GPU box without ROS.

May import: protocad_ros.atomic, sim_bridge.contract
"""
