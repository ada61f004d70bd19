"""The player's pacing: one clock for the whole run, across the passes of a looped bag."""

import pytest

from lgs_wfs_ros.ros.player_node import PlaySchedule


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_fixed_rate_keeps_its_slots_after_a_late_frame_and_across_passes():
    clock = Clock()
    sch = PlaySchedule(clock)
    period_ns = 10_000_000
    dues = []
    for k in range(8):                     # two passes of a 4-frame bag at 100 Hz
        due = sch.due(100.0, k * period_ns)
        dues.append(due)
        clock.t = max(clock.t, due)
        if k == 2:
            clock.t += 0.025               # the player starved for 2.5 periods
    assert dues == pytest.approx([100.0 + 0.01 * k for k in range(8)])
    assert sch.sent == 8


def test_recorded_timing_follows_the_elapsed_bag_time():
    clock = Clock()
    sch = PlaySchedule(clock)
    elapsed = [0, 5_000_000, 30_000_000, 40_000_000]      # irregular stamps, ns
    dues = [sch.due(None, e) for e in elapsed]
    assert dues == pytest.approx([100.0, 100.005, 100.03, 100.04])


def test_a_rate_change_starts_the_new_pacing_from_now():
    clock = Clock()
    sch = PlaySchedule(clock)
    assert sch.due(100.0, 0) == pytest.approx(100.0)
    assert sch.due(100.0, 0) == pytest.approx(100.01)
    clock.t = 100.5
    assert sch.due(50.0, 0) == pytest.approx(100.5)        # re-anchored at the change
    assert sch.due(50.0, 0) == pytest.approx(100.52)
    assert sch.due(0.0, 0) is None                         # 'max': no pacing
