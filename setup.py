"""One setup.py for the three ROS 2 packages of protocad-ros.

Besides the Python packages it installs, for each ROS package, the ament_python layout
that the real ros2cli resolves (AMENT_PREFIX_PATH = the install prefix):
  share/ament_index/resource_index/packages/<pkg>   (empty marker)
  share/<pkg>/package.xml
  lib/<pkg>/<executable>                            (kept executable by pip)
"""
import importlib.util
import json
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

ROS_PACKAGES = ("sim_bridge", "protocad_ros", "trainer")


def ament_data_files():
    files = []
    for pkg in ROS_PACKAGES:
        files.append(("share/ament_index/resource_index/packages", [f"{pkg}/resource/{pkg}"]))
        files.append((f"share/{pkg}", [f"{pkg}/package.xml"]))
        exes = sorted(str(p) for p in Path(pkg, "libexec").iterdir() if p.is_file())
        files.append((f"lib/{pkg}", exes))
    files.append(("share/sim_bridge", ["sim_bridge/fastdds_discovery.xml"]))   # scripts/env.sh
    files.append(("share/trainer/launch", ["trainer/ros_launch/protocad.launch.py"]))   # ros2 launch
    return files


def _provenance():
    spec = importlib.util.spec_from_file_location("provenance", Path(__file__).parent / "trainer" / "provenance.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class BuildPyRecordingTheCommit(build_py):
    """Writes trainer/build_info.json: the install is not editable, so a run's provenance must
    name the commit that was installed, not the one its checkout has moved on to since."""

    def run(self):
        super().run()
        root = Path(__file__).resolve().parent
        provenance = _provenance()
        info = {"commit": provenance.git_commit(root), "source": str(root)}
        Path(self.build_lib, "trainer", provenance.BUILD_INFO).write_text(json.dumps(info) + "\n")


# Exact pins where the platform demands them (msgs_docs/environment.md): an unpinned torch
# pulls GBs of CUDA wheels, mujoco 4.x breaks dm-control, rerun recordings are only N+1
# compatible. The ROS wheels come as one consistent Jazzy set.
INSTALL_REQUIRES = [
    "torch==2.13.0",
    "mujoco==3.17.0",
    "dm-control==1.0.50",
    "numpy>=1.26,<3",
    "ros-jazzy-rclpy==7.1.6",
    "ros-jazzy-common-interfaces==5.3.6",
    "ros-jazzy-rmw-fastrtps-cpp==8.4.3",
    "mcap==1.6.0",
    # Decodes real ROS 2 schemas leniently (FastCDR's trailing padding, which rosbags rejects).
    "mcap-ros2-support==0.6.0",
    "rerun-sdk==0.41.0",
    "pyarrow>=14",  # rerun's dataframe API, used directly to read recordings back
    "pyyaml>=6.0",
    "tqdm>=4.66",
    "scikit-learn>=1.4",
    "scipy>=1.11",        # trim_mean (IQM) in trainer/research/statistics.py, imported directly
    "pillow>=10.1",
    "matplotlib>=3.8",    # protocad-compare's learning-curve PNG
    "jsonschema>=4.20",   # results.json is checked against its schema on save and load
    "tyro==1.0.17",       # the config options of the CLIs, generated from the config tree (flag names pinned)
    "tensorboard==2.21.0",   # event files beside metrics.jsonl (torch.utils.tensorboard writes them)
    "cryptography==50.0.2",   # Ed25519 signatures of checkpoints (protocad_ros/checkpoint/signing.py)
]

setup(
    name="protocad-ros",
    version="0.1.0",
    description="ProtoCAD (ICLR 2023) context-aware world models as a ROS 2 Jazzy stack",
    packages=find_packages(include=["protocad_ros*", "sim_bridge*", "trainer*"]),
    # DreamerV2's published curves, the anchor's reference (trainer/research/report.py plots them)
    package_data={"trainer.research": ["dreamerv2_dmc_vision.json"],
                  "protocad_ros": ["policies/*.pt", "policies/*.json"]},   # shipped policies
    python_requires=">=3.11,<3.12",
    install_requires=INSTALL_REQUIRES,
    extras_require={"test": ["pytest==9.2.0", "pytest-timeout==2.4.0",
                             "pytest-xdist==3.8.0",   # scripts/protocad test: one worker per core
                             "hypothesis==6.170.17",
                             "grimp==3.20",   # tests/docs/test_architecture.py: the import graph
                             "rosbags==0.11.9",   # another tool's bag reader and writer, for the tests
                             "ruff==0.17.5"],   # tests/docs/test_lint.py: ruff.toml's rules
                    "bench": ["py-spy==0.4.3"]},   # scripts/bench_ros_loop.py --profile
    data_files=ament_data_files(),
    cmdclass={"build_py": BuildPyRecordingTheCommit},
    entry_points={
        "console_scripts": [
            "ros2 = trainer.ros2cli:main",
            "protocad-record = trainer.nodes.recorder:main",
            "protocad-train = trainer.learn.train:main",
            "protocad-evaluate = trainer.launch.ros_evaluate:main",
            "protocad-loop = trainer.launch.loop:main",
            "protocad-online = trainer.research.online:main",
            "protocad-visualize = trainer.viz.visualize:main",
            "protocad-compare = trainer.research.compare:main",
            "protocad-probe = trainer.research.probe:main",
            "protocad-study = trainer.study.cli:main",
            "protocad-stack = trainer.launch.stack:main",
            "protocad-checkpoint-publisher = trainer.nodes.checkpoint_publisher:main",
            "protocad-keygen = trainer.launch.run_key:keygen_main",
            "protocad-sign-checkpoint = trainer.launch.run_key:sign_main",
            "protocad-fleet = trainer.launch.fleet:main",
            "protocad-discovery-server = trainer.launch.discovery:main",
        ]
    },
)
