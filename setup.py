"""ament_python package lgs_wfs_ros: installable by colcon on a ROS 2 Jazzy system and by pip in a venv."""

import shutil
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.install_scripts import install_scripts

package_name = "lgs_wfs_ros"

NODES = {
    "simulator_node": "lgs_wfs_ros.ros.simulator_node:main",
    "centroider_node": "lgs_wfs_ros.ros.centroider_node:main",
    "recorder_node": "lgs_wfs_ros.ros.recorder_node:main",
    "player_node": "lgs_wfs_ros.ros.player_node:main",
}

CLI = "lgs-wfs"


class InstallScripts(install_scripts):
    """colcon installs the scripts into lib/lgs_wfs_ros (setup.cfg), where `ros2 run` lists
    every file as an executable of the package; the lgs-wfs CLI is no node, so under colcon
    it moves to <prefix>/bin (on PATH once the workspace is sourced). pip is unaffected."""

    def run(self):
        super().run()
        target = Path(self.install_dir)
        cli = target / CLI
        if target.name != package_name or not cli.exists():
            return
        bindir = target.parent.parent / "bin"
        bindir.mkdir(parents=True, exist_ok=True)
        shutil.move(str(cli), str(bindir / CLI))
        self.outfiles = [str(bindir / CLI) if Path(f) == cli else f for f in self.outfiles]


setup(
    name=package_name,
    cmdclass={"install_scripts": InstallScripts},
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={package_name: ["data/*.npz", "data/*.json", "config/*.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.py")),
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.xml")
         + glob("config/*.json")),
        ("share/" + package_name + "/models", glob("models/*.onnx") + glob("models/*.json")),
        ("share/" + package_name + "/models/paper_prior", glob("models/paper_prior/*.onnx")
         + glob("models/paper_prior/*.md")),
    ],
    python_requires=">=3.10",
    # Ranges here; the exact versions CI tests with are pinned in constraints.txt.
    # Runtime: exactly what the modules outside ros/ import (test_packaging checks it).
    install_requires=[
        "numpy>=1.26,<3",
        "scipy>=1.11,<2",
        "onnxruntime>=1.17,<2",
        "onnx>=1.15,<2",
        "matplotlib>=3.7,<4",
        "tqdm>=4.60,<5",
        "PyYAML>=6,<7",
        "mcap>=1.1,<2",              # the MCAP container (bags/reader.py)
        "zstandard>=0.22,<1",        # MCAP chunk compression (bags/reader.py, writer.py)
        "lz4>=4,<5",
    ],
    extras_require={
        # ROS 2 Jazzy from PyPI wheels, for a plain venv; leave it out on a system ROS install.
        "ros": ["ros-jazzy-rclpy[fastrtps]==7.1.6", "ros-jazzy-common-interfaces==5.3.6"],
        "train": ["torch==2.13.0"],
        # zero-copy frames between the nodes of one host (frame_transport: shm)
        "shm": ["iceoryx2>=0.10,<0.11"],
        # compiled single-pass centroid kernels and the fast simulator (numpy fallback without);
        # llvmlite, numba's code generator, for the prefetch hint (kernels/_jit.py)
        "fast": ["numba>=0.68,<0.69", "llvmlite>=0.50,<0.51"],
        # Test-only tools: aotools and the mcap reference readers check our own code;
        # colcon builds the package in a test, as a ROS install would.
        "test": ["pytest>=8,<10", "pytest-xdist>=3.8,<4", "aotools>=1.0.7,<2", "mcap-ros2-support>=0.5,<1",
                 "import-linter>=2.16,<3",
                 "colcon-core>=0.15", "colcon-ros>=0.4", "colcon-python-setup-py>=0.2.8",
                 "colcon-package-selection>=0.2",
                 # bags written by another rosbag2 writer (test/test_bags_interop.py)
                 "rosbags>=0.10,<0.12"],
    },
    zip_safe=True,
    maintainer="lgs_wfs_ros developers",
    maintainer_email="lgs-wfs-ros@example.org",
    description="Centroiding elongated sodium laser-guide-star spots on Shack-Hartmann "
                "wavefront sensors: simulator, CoG/CMF/ANN centroiders, ROS 2 nodes, MCAP bags.",
    license="BSD-3-Clause",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [f"{name} = {target}" for name, target in NODES.items()]
        + [f"{CLI} = lgs_wfs_ros.cli:main"],
    },
)
