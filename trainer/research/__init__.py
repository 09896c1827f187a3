"""Research runs without ROS: online runs in one process (Algorithm 1 over vector envs), grids of
them across variants and seeds, their results and statistics, and the context probe of a
checkpoint (protocad-probe). No ROS.

May import: protocad_ros, sim_bridge.contract, sim_bridge.sim, trainer.runs, trainer.run_input, trainer.run_config, trainer.torch_setup, trainer.metrics_log, trainer.cli_values, trainer.console, trainer.settings, trainer.provenance, trainer.bag, trainer.data, trainer.learn, trainer.viz
"""
