"""Running a node process: spin until done or asked to stop (SIGINT / SIGTERM), shut down in order.

Every node's ``main()`` is :func:`run_node`: configure the environment, ``rclpy.init``, build
the node (a refused start logs the reason and exits 2), spin it on the global executor,
then finish the node, destroy it and ``rclpy.try_shutdown()`` whatever happened.

SIGINT and SIGTERM only set a flag here (rclpy's own handlers are off): with rclpy's, the
context is shut down inside the signal, so the node's last words (final counts, "closed the
bag") and its destruction meet a dead context ("Failed to publish log message to rosout").
The spin notices the flag within ``timeout_sec`` and the shutdown runs in order.
"""

from __future__ import annotations

import signal
import threading
import time

import rclpy
import rclpy.logging
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.signals import SignalHandlerOptions

from . import environment

STOP = threading.Event()     # set by SIGINT / SIGTERM in a node process


def _on_signal(signum, _frame):
    STOP.set()


# after a stop signal and its linger, a node with an activity count spins on until that
# count has not moved for STOP_QUIET_S (its queues drained), STOP_DRAIN_MAX_S at most
STOP_QUIET_S = 0.3
STOP_DRAIN_MAX_S = 3.0


def spin_until(node, done, timeout_sec: float = 0.1, pause_s: float = 0.0,
               stop_linger_s: float = 0.0, activity=None) -> None:
    """Spin ``node`` until ``done()`` is true or the context shuts down.

    rclpy's signal handler shuts the context down on SIGINT and SIGTERM; a spin that was
    waiting then fails with an RCLError about an invalid context, which here just means stop.

    ``pause_s`` > 0 sleeps that long after every executor round, so messages arrive in
    batches that the callbacks drain together (:func:`take_queued`): far less executor
    overhead per message, at the cost of up to ``pause_s`` of latency (for the recorder,
    never for the centroider).

    ``stop_linger_s`` > 0 keeps spinning that long after a stop signal (the recorder: the
    last messages its publishers flush on their own SIGINT still reach the bag).
    ``activity()`` (e.g. messages taken so far), when given, keeps it spinning past the
    linger until the count is quiet for :data:`STOP_QUIET_S`: what the subscribers had
    acknowledged but the node had not taken yet (a loaded machine) is not dropped.
    """
    stop_at = None
    last = None
    while not done():
        if STOP.is_set():
            now = time.monotonic()
            if stop_at is None:
                stop_at = now + stop_linger_s
            if now >= stop_at:
                count = activity() if activity is not None else None
                if count is None or now >= stop_at + STOP_DRAIN_MAX_S:
                    return
                if last is None or count != last[0]:
                    last = (count, now)
                elif now - last[1] >= STOP_QUIET_S:
                    return
        if pause_s > 0:
            time.sleep(pause_s)
        try:
            rclpy.spin_once(node, timeout_sec=timeout_sec)
        except ExternalShutdownException:
            return
        except Exception:
            if not rclpy.ok(context=node.context):
                return
            raise
        if not rclpy.ok(context=node.context):
            return


# at exit, wait this long at most for subscribers to acknowledge what was sent (well inside
# launch's 5 s between SIGINT and SIGTERM)
FLUSH_S = 2.0


def flush(node, timeout_s: float = FLUSH_S) -> bool:
    """Wait until every reliable publisher of ``node`` has its messages acknowledged by its
    subscribers (or ``timeout_s`` passes); True if all were.

    A reliable writer only promises delivery while it exists: destroying the node drops what
    a slow subscriber (the recorder, on a loaded machine) has not acknowledged yet, so the
    last slopes a centroider counted as processed could miss the bag. Called after
    ``finish`` (no more publishing) and before the node is destroyed.
    """
    from rclpy.duration import Duration
    deadline = time.monotonic() + timeout_s
    acked = True
    for pub in list(node.publishers):
        left = deadline - time.monotonic()
        try:
            if not pub.get_subscription_count():
                continue
            acked &= pub.wait_for_all_acked(Duration(nanoseconds=int(max(left, 0.0) * 1e9)))
        except Exception:   # a publisher already gone (InvalidHandle)
            continue
    return acked


DRAIN = 16   # messages taken per executor callback at most (other callbacks wait that long)


def take_queued(sub, msg_type, limit: int, raw: bool = True):
    """Yield up to ``limit`` (message, info) already queued on a subscription (serialized
    bytes when ``raw``, else a ``msg_type`` instance), taken without the executor (rclpy's executor costs ~0.3 ms of Python per message); stops at the
    first empty take or if the subscription is gone.

    ``sub.handle.take_message`` is rclpy's internal handle API: Jazzy's rclpy has no public
    way to take a message outside the executor (``Subscription`` has no ``take``; rclpy's own
    ``wait_for_message`` and executor call the same handle method), and a wait set per
    message (``wait_for_message``) costs what the executor does. Kept for the measured drain
    (docs/transport.md); the node tests drain through it.
    """
    for _ in range(limit):
        try:
            with sub.handle:
                taken = sub.handle.take_message(msg_type, raw)
        except Exception:   # destroyed (InvalidHandle) or the context is shutting down
            return
        if taken is None:
            return
        yield taken


def run_node(name: str, factory, *, done=None, refused=(ValueError,), finish=None,
             args=None, pause_s: float = 0.0, stop_linger_s: float = 0.0,
             activity=None) -> int:
    """Run one node process; the exit code (0, or 2 when the start was refused).

    Args:
        name: the executable's name, for messages.
        factory: builds the node (after ``rclpy.init``); exceptions in ``refused`` mean the
            start was refused with a reason.
        done: ``done(node) -> bool`` ends the spin (default: run until a signal).
        finish: ``finish(node) -> int | None`` runs before the node is destroyed, also after a
            signal; a non-None result becomes the exit code.
        pause_s, stop_linger_s: see :func:`spin_until`.
        activity: ``activity(node) -> int`` that grows with every message taken (see
            :func:`spin_until`).
    """
    environment.configure()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    STOP.clear()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, _on_signal)
    refused = tuple(refused) + (ParameterException,)
    node, code = None, 0
    try:
        node = factory()
        # Added once: rclpy.spin_once would otherwise add and remove the node on every call,
        # which wakes the wait set twice and rebuilds it per message (~0.3 ms per frame).
        rclpy.get_global_executor().add_node(node)
        spin_until(node, (lambda: done(node)) if done else (lambda: False), pause_s=pause_s,
                   stop_linger_s=stop_linger_s,
                   activity=(lambda: activity(node)) if activity else None)
    except refused as exc:
        rclpy.logging.get_logger(name).error(f"cannot start: {exc}")
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            if finish is not None:
                result = finish(node)
                code = code if result is None else result
            if rclpy.ok(context=node.context) and not flush(node):
                node.get_logger().warning(f"some messages were not acknowledged by their "
                                          f"subscribers within {FLUSH_S:g} s of the end")
            node.destroy_node()
        rclpy.try_shutdown()
    return code
