"""Typed ROS parameters: one per centroiding option, described, range- and choice-checked,
set through the parameter service as `ros2 param set` does; integers taken for doubles."""

import os
import subprocess
import sys
import time

import pytest

from conftest import set_param, wait_for
from lgs_wfs_ros.centroiding import options

pytestmark = pytest.mark.ros

CENTROIDER = "/wfs/centroider_node"


def describe(ros, node_name, names):
    """Descriptors through the node's describe_parameters service (`ros2 param describe`)."""
    from rclpy.node import Node
    from rclpy.parameter_client import AsyncParameterClient
    client_node = ros.add(Node(f"describe_{time.monotonic_ns()}", context=ros.context))
    client = AsyncParameterClient(client_node, node_name)
    assert client.wait_for_services(timeout_sec=20)
    future = client.describe_parameters(list(names))
    assert wait_for(future.done, timeout=20)
    return dict(zip(names, future.result().descriptors))


@pytest.fixture
def centroider(ros):
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    return ros.add(CentroiderNode(context=ros.context))


def test_every_option_row_is_a_described_typed_parameter(ros, centroider):
    from rcl_interfaces.msg import ParameterType
    rows = [o for rs in options.OPTIONS.values() for o in rs]
    descs = describe(ros, CENTROIDER, [o.parameter for o in rows])
    kinds = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
             float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}
    for o in rows:
        d = descs[o.parameter]
        assert d.type == kinds[o.kind], o.parameter
        assert o.description in d.description and d.read_only == o.read_only
        assert centroider.get_parameter(o.parameter).value == o.default
        for choice in o.choices:
            assert choice in d.additional_constraints and choice in d.description
        if o.kind is int and o.low is not None:
            assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (o.low, o.high)
        if o.kind is float and o.low is not None:
            r = d.floating_point_range[0]
            assert (r.from_value, r.to_value) == (o.low, o.high)
    assert not centroider.has_parameter("options") and not centroider.has_parameter("model")


def test_a_new_row_becomes_a_parameter(ros, monkeypatch):
    from lgs_wfs_ros.ros.centroider_node import CentroiderNode
    row = options.Option("cog", "made_up", 3, "A row added to the table.", low=1, high=5)
    monkeypatch.setitem(options.OPTIONS, "cog", options.OPTIONS["cog"] + (row,))
    node = ros.add(CentroiderNode(context=ros.context, namespace="extra"))
    assert node.get_parameter("cog.made_up").value == 3
    d = node.describe_parameter("cog.made_up")
    assert d.description.startswith("A row added") and d.integer_range[0].to_value == 5


def test_set_option_switch_and_refuse_through_the_service(ros, centroider):
    assert set_param(ros, CENTROIDER, "cmf.reference", "model").successful
    assert set_param(ros, CENTROIDER, "cmf.weighting", "model").successful
    # no response scan: a linearised full-pupil CMF takes seconds to build (tens under load)
    assert set_param(ros, CENTROIDER, "cmf.linearize", False).successful
    assert set_param(ros, CENTROIDER, "algorithm", "cmf").successful
    desc = centroider.centroider.describe()
    assert desc["algorithm"] == "cmf"
    assert centroider.centroider.options["reference"] == "model"
    assert centroider.centroider.options["weighting"] == "model"

    # refused with the reason; the node keeps its value and its centroider
    before = centroider.centroider
    bad = set_param(ros, CENTROIDER, "cmf.reference", "yesterday")
    assert not bad.successful and "history" in bad.reason and "yesterday" in bad.reason
    out = set_param(ros, CENTROIDER, "cmf.update_period", 0)
    assert not out.successful and "update_period" in out.reason
    wrong = set_param(ros, CENTROIDER, "cmf.linearize", "yes")
    assert not wrong.successful
    assert centroider.get_parameter("cmf.reference").value == "model"
    assert centroider.centroider is before
    # an option of the algorithm in use rebuilds it
    assert set_param(ros, CENTROIDER, "cmf.update_period", 7).successful
    assert centroider.centroider is not before
    assert centroider.centroider.options["update_period"] == 7


def test_cmf_defaults_to_the_grid_and_refuses_a_single_filter_option_with_the_reason(
        ros, centroider):
    assert set_param(ros, CENTROIDER, "algorithm", "cmf").successful
    before = centroider.centroider
    assert before.describe()["options"]["filters"] == "grid"
    out = set_param(ros, CENTROIDER, "cmf.linearize", False)
    assert not out.successful and "filters=single" in out.reason
    assert centroider.get_parameter("cmf.linearize").value is True
    assert centroider.centroider is before


def test_an_integer_is_taken_for_a_double(ros, centroider):
    res = set_param(ros, CENTROIDER, "cmf.sodium_fwhm_m", 12000)
    assert res.successful, res.reason
    value = centroider.get_parameter("cmf.sodium_fwhm_m").value
    assert value == 12000.0 and isinstance(value, float)
    # but a string for a double is not, and the range still holds for a converted integer
    assert not set_param(ros, CENTROIDER, "cmf.sodium_fwhm_m", "far").successful
    assert not set_param(ros, CENTROIDER, "cmf.sodium_fwhm_m", 10**7).successful
    assert centroider.get_parameter("cmf.sodium_fwhm_m").value == 12000.0


def test_simulator_takes_an_integer_photons_at_start_and_at_run_time(ros):
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.ros.simulator_node import SimulatorNode
    sim = ros.add(SimulatorNode(context=ros.context, parameter_overrides=[
        Parameter("photons", value=1000), Parameter("n_subaps", value=8),
        Parameter("diameter_m", value=4), Parameter("obstruction_m", value=0.5),
        Parameter("frames", value=1), Parameter("wait_for_subscribers", value=1)]))
    assert sim.get_parameter("photons").value == 1000.0
    assert sim.sim.sensor.photons == 1000.0 and sim.sim.sensor.diameter_m == 4.0
    res = set_param(ros, "/wfs/simulator_node", "photons", 250)
    assert res.successful, res.reason
    assert sim.sim.sensor.photons == 250.0
    assert sim.sim.threads == 2                     # render_threads' default
    assert not set_param(ros, "/wfs/simulator_node", "render_threads", 0).successful
    res = set_param(ros, "/wfs/simulator_node", "render_threads", 1)
    assert res.successful, res.reason
    assert sim.sim.threads == 1 and sim.sim.sensor.photons == 250.0
    sim.stop()


def test_a_number_is_taken_for_a_string_as_its_text(ros, tmp_path):
    """The player's rate is 'recorded', 'max' or a number: `-p rate:=800` and `ros2 param set
    ... rate 400` arrive as numbers, which rclpy refused for a string parameter."""
    from rclpy.parameter import Parameter
    from lgs_wfs_ros.analysis.bagdata import ContractBagWriter
    from lgs_wfs_ros.ros.player_node import PlayerNode
    from lgs_wfs_ros.sensor import Sensor
    import numpy as np
    sensor = Sensor.paper_single("polar")
    path = tmp_path / "one.mcap"
    with ContractBagWriter(path, sensor) as bag:
        bag.frame(1000, np.zeros(sensor.frame_shape, np.uint16))
    player = ros.add(PlayerNode(context=ros.context, parameter_overrides=[
        Parameter("bag", value=str(path)), Parameter("rate", value=800),
        Parameter("start_delay_s", value=30.0)]))
    assert player.get_parameter("rate").value == "800"
    res = set_param(ros, "/wfs/player_node", "rate", 400.5)
    assert res.successful, res.reason
    assert player.get_parameter("rate").value == "400.5"
    res = set_param(ros, "/wfs/player_node", "rate", -3)       # still validated
    assert not res.successful and player.get_parameter("rate").value == "400.5"
    assert not set_param(ros, "/wfs/player_node", "loop", 1).successful   # bool stays bool
    player.stop()


def run_node(module, *ros_args, timeout=60):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run([sys.executable, "-m", f"lgs_wfs_ros.ros.{module}", "--ros-args",
                           *ros_args], capture_output=True, text=True, timeout=timeout, env=env)


def test_command_line_integer_for_double_and_a_refused_start():
    ok = run_node("simulator_node", "-p", "photons:=1000", "-p", "frames:=1",
                  "-p", "n_subaps:=8", "-p", "diameter_m:=4", "-p", "obstruction_m:=0.5")
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert "1000 photons" in ok.stderr
    rate = run_node("player_node", "-p", "bag:=/nonexistent.mcap", "-p", "rate:=800")
    assert rate.returncode == 2 and "no such file" in rate.stderr, rate.stderr  # the bag,
    assert "expecting type" not in rate.stderr                                 # not the rate
    bad = run_node("simulator_node", "-p", "photons:=-5.0", "-p", "frames:=1")
    assert bad.returncode == 2
    assert "photons" in bad.stderr and "Traceback" not in bad.stdout + bad.stderr
