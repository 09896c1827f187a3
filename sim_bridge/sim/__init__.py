"""The paper's eight context-randomized DMC tasks rendered at 64x64, a vector of them in worker
processes, and the rollouts that run any policy in it. No ROS.

May import: sim_bridge.contract
"""
