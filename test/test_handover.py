"""handover.Handover on stand-in subscriptions: each sequence number handed out once, in order,
the old queue destroyed once the new one delivers (no ROS graph: the order of events is set)."""

import collections
from types import SimpleNamespace

import pytest

pytest.importorskip("rclpy", reason="the handover takes from rclpy subscription handles")
from lgs_wfs_ros.ros.handover import Handover  # noqa: E402


class Sub:
    """A queue with what take_queued uses: ``handle`` (a context manager with
    ``take_message``) and ``qos_profile.depth``; KEEP_LAST: the oldest go when it is full."""

    def __init__(self, depth):
        self.queue = collections.deque(maxlen=depth)
        self.qos_profile = SimpleNamespace(depth=depth)
        self.handle = self
        self.destroyed = False

    def put(self, *seqs):
        for s in seqs:
            self.queue.append((f"m{s}", {"publication_sequence_number": s}))

    def take_message(self, _type, _raw):
        if self.destroyed:
            raise RuntimeError("InvalidHandle")
        return self.queue.popleft() if self.queue else None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


class Node:
    def destroy_subscription(self, sub):
        sub.destroyed = True


def msg(seq):
    return (f"m{seq}", {"publication_sequence_number": seq})


def numbers(taken):
    return [info["publication_sequence_number"] for _, info in taken]


def test_frames_only_the_old_queue_holds_then_both():
    old, new = Sub(100), Sub(700)
    hand = Handover(Node(), old, new, object)
    old.put(2, 3, 4)                          # before the new queue matched
    assert numbers(hand.take(msg(1), from_new=False)) == [1, 2, 3, 4]
    assert not old.destroyed and not hand.over
    old.put(5, 6, 7)
    new.put(6, 7)                             # matched from 5 on
    assert numbers(hand.take(msg(5), from_new=True)) == [5, 6, 7]
    assert old.destroyed and hand.over


def test_a_frame_that_reaches_the_old_queue_first_is_not_repeated():
    old, new = Sub(100), Sub(700)
    hand = Handover(Node(), old, new, object)
    old.put(*range(1, 10))
    new.put(6, 7, 8)                          # 9 is still on its way to the new queue
    assert numbers(hand.take(msg(5), from_new=True)) == list(range(1, 10))
    assert old.destroyed and not hand.over    # 9 may still come through the new queue
    new.put(10)
    assert numbers(hand.take(msg(9), from_new=True)) == [10]
    assert hand.over


def test_an_overflowed_old_queue_loses_nothing_the_new_one_holds():
    """A burst: the old queue (depth 3) kept only its last frames; the new one has all."""
    old, new = Sub(3), Sub(2000)
    hand = Handover(Node(), old, new, object)
    old.put(*range(1, 11))                    # keeps 8, 9, 10
    new.put(*range(2, 11))
    assert numbers(hand.take(msg(1), from_new=True)) == list(range(1, 11))
    assert hand.over


def test_a_second_change_hands_over_what_the_first_old_queue_still_holds():
    a, b, c = Sub(10), Sub(20), Sub(30)
    first = Handover(Node(), a, b, object)
    assert numbers(first.take(msg(1), from_new=False)) == [1]
    a.put(2, 3)
    second = Handover(Node(), b, c, object)
    assert numbers(first.finish_old()) == [2, 3] and a.destroyed
    second.seen |= first.seen
    b.put(1, 2, 3, 4)
    c.put(4)
    assert numbers(second.take(msg(4), from_new=True)) == [4]
    assert b.destroyed
