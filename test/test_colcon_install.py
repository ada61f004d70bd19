"""colcon-installed works like pip-installed: a `colcon build` into a temporary workspace,
then the installed centroider_node with ``algorithm:=ann`` finds its default model through
the ament index (share/lgs_wfs_ros/models), not the source tree, and stops cleanly."""

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import wait_for

pytestmark = [pytest.mark.ros, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
NODES = ("simulator_node", "centroider_node", "recorder_node", "player_node")


@pytest.fixture(scope="module")
def install(tmp_path_factory):
    colcon = shutil.which("colcon") or str(Path(sys.executable).parent / "colcon")
    if not Path(colcon).exists():
        pytest.skip("colcon is not installed (pip install '.[test]' brings it)")
    ws = tmp_path_factory.mktemp("ws")
    shutil.copytree(ROOT, ws / "src" / "lgs_wfs_ros", ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "install", "log", "*.mcap", "__pycache__", "bags"))
    proc = subprocess.run([colcon, "build", "--packages-select", "lgs_wfs_ros"], cwd=ws,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return ws / "install" / "lgs_wfs_ros"


def test_ros2_run_lists_only_the_nodes(install):
    lib = install / "lib" / "lgs_wfs_ros"
    assert sorted(p.name for p in lib.iterdir()) == sorted(NODES)
    assert (install / "bin" / "lgs-wfs").is_file()     # the CLI: on PATH, not a node
    assert (install / "share" / "lgs_wfs_ros" / "models" / "ann_pupil.onnx").is_file()


def test_installed_centroider_runs_ann_with_the_installed_model(install, ros):
    from rclpy.node import Node
    from std_msgs.msg import String
    from lgs_wfs_ros.ros import qos

    site = next(install.glob("lib/python3*/site-packages"))
    env = dict(os.environ, PYTHONPATH=str(site), AMENT_PREFIX_PATH=str(install),
               PYTHONUNBUFFERED="1", HOME=str(install / "home"))
    env.pop("LGS_WFS_MODELS", None)
    proc = subprocess.Popen([sys.executable, str(install / "lib" / "lgs_wfs_ros" / "centroider_node"),
                             "--ros-args", "-p", "algorithm:=ann"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    got = []
    listener = ros.add(Node("colcon_listener", context=ros.context))
    listener.create_subscription(String, "/wfs/centroider", lambda m: got.append(json.loads(m.data)),
                                 qos.LATCHED)
    try:
        # a fresh install compiles every kernel on the node's first start (no numba cache
        # there yet): the whole test takes ~40 s alone on this 2-core host; in one CI run,
        # beside two other busy test processes, the node took over 60 s to publish
        assert wait_for(lambda: got or proc.poll() is not None, timeout=180)
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    assert got, out
    assert got[-1]["algorithm"] == "ann"
    # the source tree is out of reach of the installed package (its models/ is not beside
    # it, sys.prefix has none): the model can only have come from the install's share
    if "model_path" in got[-1]:
        share = install / "share" / "lgs_wfs_ros" / "models"
        assert Path(got[-1]["model_path"]).parent == share, got[-1]["model_path"]
    assert proc.returncode == 0, out
    for bad in ("Traceback", "Failed to publish log message", "waiting for a sensor"):
        assert bad not in out, out
    assert "final counts" in out
