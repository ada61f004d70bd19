"""How a node process stops: the linger after a signal and the drain of what was queued."""

import time

import pytest

from lgs_wfs_ros.ros import spinning


class FakeRclpy:
    """``spin_once`` takes one queued message per call (``activity`` counts them)."""

    def __init__(self, queued: int):
        self.queued, self.taken = queued, 0

    def spin_once(self, node, timeout_sec=None):
        time.sleep(0.005)
        if self.queued:
            self.queued -= 1
            self.taken += 1

    def ok(self, context=None):
        return True


@pytest.fixture
def fake(monkeypatch):
    def make(queued):
        f = FakeRclpy(queued)
        monkeypatch.setattr(spinning, "rclpy", f)
        spinning.STOP.set()
        return f
    yield make
    spinning.STOP.clear()


class Node:
    context = None


def test_stop_drains_what_is_queued_before_returning(fake):
    """200 messages queued at the signal (5 ms each to take, ~1 s): a linger of 0.1 s alone
    would leave most of them; with an activity count the spin takes them all."""
    f = fake(200)
    spinning.spin_until(Node(), lambda: False, stop_linger_s=0.1, activity=lambda: f.taken)
    assert f.queued == 0 and f.taken == 200


def test_without_activity_the_linger_alone_decides(fake):
    f = fake(200)
    spinning.spin_until(Node(), lambda: False, stop_linger_s=0.1)
    assert 0 < f.taken < 200


def test_a_stream_that_never_stops_is_cut_after_the_drain_limit(fake, monkeypatch):
    monkeypatch.setattr(spinning, "STOP_DRAIN_MAX_S", 0.3)
    f = fake(10**9)
    t0 = time.monotonic()
    spinning.spin_until(Node(), lambda: False, stop_linger_s=0.1, activity=lambda: f.taken)
    assert time.monotonic() - t0 >= 0.4
    assert f.queued > 0
