"""Research runs without ROS: online runs in one process (Algorithm 1 over vector envs), grids of
them across variants and seeds, and their results and statistics. No ROS.

May import: protocad_ros, sim_bridge.contract, sim_bridge.sim, trainer.runs, trainer.settings, trainer.provenance, trainer.bag, trainer.data, trainer.learn, trainer.viz
"""
