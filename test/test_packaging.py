"""The package stays a valid ament_python package: package.xml, colcon build, lib/<pkg> executables."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NODES = ("simulator_node", "centroider_node", "recorder_node", "player_node")


def test_package_xml_is_valid_format_3():
    catkin_pkg = pytest.importorskip("catkin_pkg.package", reason="catkin_pkg comes with colcon-ros")
    pkg = catkin_pkg.parse_package(str(ROOT / "package.xml"))
    pkg.validate()
    assert pkg.package_format == 3 and pkg.name == "lgs_wfs_ros"
    assert pkg.get_build_type() == "ament_python"
    assert all("@" in m.email and "." in m.email.split("@")[1] for m in pkg.maintainers)
    deps = {d.name for d in pkg.exec_depends}
    assert {"rclpy", "std_msgs", "sensor_msgs"} <= deps
    assert (ROOT / "resource" / "lgs_wfs_ros").is_file()


@pytest.mark.slow
def test_colcon_build_installs_ros2_run_executables(tmp_path):
    colcon = shutil.which("colcon") or str(Path(sys.executable).parent / "colcon")
    if not Path(colcon).exists():
        pytest.skip("colcon is not installed (pip install '.[test]' brings it)")
    src = tmp_path / "src" / "lgs_wfs_ros"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".git", ".venv", "build", "install",
                                                             "log", "*.mcap", "__pycache__"))
    proc = subprocess.run([colcon, "build", "--packages-select", "lgs_wfs_ros"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    prefix = tmp_path / "install" / "lgs_wfs_ros"
    lib = prefix / "lib" / "lgs_wfs_ros"
    for node in NODES:
        assert (lib / node).is_file(), f"ros2 run would not find {node}"
    share = prefix / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "lgs_wfs_ros").is_file()
    assert (share / "lgs_wfs_ros" / "package.xml").is_file()
    assert (share / "lgs_wfs_ros" / "launch" / "demo.launch.py").is_file()
    # what `ros2 run lgs_wfs_ros centroider_node` executes, with a parameter it must refuse
    site = next(prefix.glob("lib/python3*/site-packages"))
    env = dict(os.environ, PYTHONPATH=str(site))
    run = subprocess.run([sys.executable, str(lib / "centroider_node"), "--ros-args",
                          "-p", "algorithm:=bogus"], capture_output=True, text=True, timeout=60, env=env)
    assert run.returncode != 0
    assert "bogus" in (run.stdout + run.stderr)
