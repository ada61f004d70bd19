"""What a node says about itself: conditions logged once then counted, and /diagnostics.

A condition (frames before the sensor description, a simulation behind its rate, a rejected
frame of some kind) is logged the first time it happens, with its cause, and only counted
afterwards; the counts go into the node's periodic INFO line and its diagnostics. Every
node publishes one ``diagnostic_msgs/DiagnosticStatus`` per period on ``/diagnostics``
(the absolute topic rviz, Foxglove and ``ros2 topic echo /diagnostics`` read): level OK /
WARN / ERROR, a one-line state message, and its counters as key/value pairs.
"""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}
DIAGNOSTICS_TOPIC = "/diagnostics"
HARDWARE_ID = "lgs_wfs"


class Health:
    """Once-then-count conditions and the node's state, published on ``/diagnostics``.

    Args:
        node: the rclpy node (its logger, clock and a publisher are used).
        counters: ``counters() -> dict`` of numbers or strings, published as values.
        period_s: seconds between diagnostics messages (0: only on :meth:`publish`).
    """

    def __init__(self, node, counters=dict, period_s: float = 1.0):
        self.node = node
        self.counters = counters
        self.counts: dict[str, int] = {}
        self.level, self.message = OK, "starting"
        self._pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self._timer = node.create_timer(period_s, self.publish) if period_s > 0 else None

    def note(self, condition: str, detail: str = "", level=WARN) -> int:
        """Count ``condition``; log it (with ``detail``) only the first time. Its count."""
        n = self.counts.get(condition, 0) + 1
        self.counts[condition] = n
        if n == 1:
            log = self.node.get_logger()
            text = condition + (f": {detail}" if detail else "") + " (logged once, then counted)"
            {OK: log.info, WARN: log.warning}.get(level, log.error)(text)
        return n

    def set_state(self, level, message: str, log: bool = True) -> None:
        """The node's state: OK, WARN or ERROR with a one-line message (logged on change,
        at its level, unless ``log`` is False: already said by :meth:`note`)."""
        if (level, message) == (self.level, self.message):
            return
        self.level, self.message = level, message
        if not log:
            return
        log = self.node.get_logger()
        {OK: log.info, WARN: log.warning}.get(level, log.error)(message)

    def summary(self) -> str:
        """The conditions counted so far, for a log line ('' when none)."""
        return "; ".join(f"{c}: {n}" for c, n in self.counts.items())

    def status(self) -> DiagnosticStatus:
        values = {**self.counters(), **{f"count: {c}": n for c, n in self.counts.items()}}
        return DiagnosticStatus(
            level=self.level, name=self.node.get_fully_qualified_name(),
            message=self.message, hardware_id=HARDWARE_ID,
            values=[KeyValue(key=str(k), value=str(v)) for k, v in values.items()])

    def publish(self) -> None:
        if not self.node.context.ok():
            return
        msg = DiagnosticArray(status=[self.status()])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        try:
            self._pub.publish(msg)
        except Exception:   # the context went down between the check and the publish
            pass
