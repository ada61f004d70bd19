"""Replacing a subscription's queue (another depth) without losing or repeating a message.

A node sizes its frame queue for the sensor it is told about (``qos.frame_qos``), so a sensor
description that arrives after frames started flowing (a slow start, a new sensor) replaces
the subscription. Destroying the old one first drops what it holds and what is published
before the new one matches (the live demo lost 32 of 140 slopes so on a loaded host).

Make before break: the new subscription is created while the old one stays. Until the new
one has delivered, every callback of either takes what both queues hold and hands out each
publication sequence number once, in sequence order; once the new one has delivered, the old
one is destroyed (the publisher sends everything after to the new one). Numbers already
handed out keep being skipped until the new queue has reached the highest of them: a frame
can reach one queue before the other. This holds for one publisher per topic (the contract's
graphs); messages without a sequence number are handed out as they come.
"""

from __future__ import annotations

from .spinning import take_queued


def sequence(info) -> int | None:
    """The publication sequence number in a message info dict (None if the middleware gave
    none)."""
    seq = info.get("publication_sequence_number") if isinstance(info, dict) else None
    return int(seq) if seq else None


class Handover:
    """One queue change of a raw subscription: ``old`` -> ``new`` (both of ``node``)."""

    def __init__(self, node, old, new, msg_type):
        self.node, self.old, self.new, self.msg_type = node, old, new, msg_type
        self.seen: set[int] = set()
        self.old_destroyed = False
        self.over = False            # nothing left to skip: callers forget the handover

    def take(self, message, from_new: bool) -> list:
        """``[(message, info)]`` to handle now, in sequence order: ``message`` (a (message,
        info) pair the executor gave, from ``new`` if ``from_new`` else from ``old``) and all
        that both queues hold, each sequence number once and none handed out before."""
        pairs = [(message, from_new)]
        pairs += [(m, True) for m in take_queued(self.new, self.msg_type,
                                                 self.new.qos_profile.depth)]
        delivered = any(is_new for _, is_new in pairs)
        if not self.old_destroyed:
            pairs += [(m, False) for m in self._take_old()]
            if delivered:            # the publisher sends to the new queue: the old one ends
                self._destroy_old()
        numbered, unnumbered, newest = {}, [], 0      # newest: the new queue's last number
        for (msg, info), is_new in pairs:
            seq = sequence(info)
            if seq is None:
                unnumbered.append((msg, info))
                newest = newest if not is_new else float("inf")
            else:
                newest = max(newest, seq) if is_new else newest
                if seq not in self.seen and seq not in numbered:
                    numbered[seq] = (msg, info)
        self.seen.update(numbered)
        # the new queue is past every number handed out: nothing it brings can repeat one
        self.over = delivered and newest >= max(self.seen, default=0)
        return [numbered[k] for k in sorted(numbered)] + unnumbered

    def finish_old(self) -> list:
        """Destroy ``old`` now (a second change before this one ended); what it still held,
        ``[(message, info)]``, without the sequence numbers handed out before (and counted
        as handed out: the next handover starts from ``seen``)."""
        if self.old_destroyed:
            return []
        rest = [m for m in self._take_old() if sequence(m[1]) not in self.seen]
        self.seen.update(s for s in map(sequence, (info for _, info in rest)) if s is not None)
        self._destroy_old()
        return rest

    def _take_old(self):
        return list(take_queued(self.old, self.msg_type, self.old.qos_profile.depth))

    def _destroy_old(self):
        self.node.destroy_subscription(self.old)
        self.old_destroyed = True
