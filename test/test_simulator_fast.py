"""The simulator's fast path (compiled Poisson noise, frames written into a given buffer) is
statistically today's; profiles are a function of the frame index alone."""

import numpy as np
import pytest

from lgs_wfs_ros.optics import detector
from lgs_wfs_ros.optics.simulator import SimulationConfig, Simulator
from lgs_wfs_ros.sensor import Sensor


def test_profile_at_is_a_function_of_the_index():
    sim = Simulator(Sensor.paper_single("polar"), SimulationConfig(profile="random",
                                                                     random_every=3, seed=2))
    first = [sim.profile_at(i)[0].copy() for i in (0, 4, 7)]
    again = [sim.profile_at(i)[0].copy() for i in (7, 0, 4)]      # another order
    for a, b in zip(first, [again[1], again[2], again[0]]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(sim.profile_at(1)[0], first[0])   # same epoch
    assert not np.array_equal(first[0], first[1])
    other = Simulator(sim.sensor, sim.config.replace(seed=3))
    assert not np.array_equal(other.profile_at(0)[0], first[0])
