"""Spot models of a profile's knots, built ahead of need (the fast simulator's cache).

A live full-pupil simulation whose sodium profile evolves (measured profiles some seconds
apart, blended in between) or is redrawn every N frames needs a new :class:`SpotModel`
and its render table only when it crosses a knot; building one takes about 0.1 s of CPU
for the full pupil, which is 20-80 frame periods at 200-800 Hz. :class:`KnotModels`
keeps the models of the knots in use and builds the next one in a background thread
while the frames of the current interval render. A build is a pure function of the
knot's density and the shift margin, so the frames are the same whether a model came
from the thread or was built on the spot (and when the thread is late, the frame waits
for it: nothing is approximated).
"""

from __future__ import annotations

from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Hashable


class KnotModels:
    """Models by key, built on demand or ahead of time.

    Args:
        build: ``build(density (K,), margin_px) -> model``, pure (called from a worker
            thread for prefetches).
        keep: models kept (the two knots being blended and the next one).
    """

    def __init__(self, build: Callable, keep: int = 3):
        self._build = build
        self._keep = int(keep)
        self._models: OrderedDict = OrderedDict()
        self._pending: dict[Hashable, Future] = {}
        self._pool: ThreadPoolExecutor | None = None
        self.built_ahead = 0          # models that came from the thread
        self.built_inline = 0         # models built when first needed (a stall)

    def get(self, key: Hashable, density: Callable, margin: float):
        """The model of knot ``key`` at ``margin`` px (``density()`` gives its ``(K,)``
        density if it must be built)."""
        full = (key, float(margin))
        model = self._models.get(full)
        if model is None:
            fut = self._pending.pop(full, None)
            if fut is not None:
                model = fut.result()
                self.built_ahead += 1
            else:
                model = self._build(density(), float(margin))
                self.built_inline += 1
            self._models[full] = model
            while len(self._models) > self._keep:
                self._models.popitem(last=False)
        else:
            self._models.move_to_end(full)
        return model

    def prefetch(self, key: Hashable, density: Callable, margin: float) -> None:
        """Start building knot ``key`` in the background unless it is held or under way."""
        full = (key, float(margin))
        if full in self._models or full in self._pending:
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="knot-models")
        self._pending[full] = self._pool.submit(lambda: self._build(density(), float(margin)))

    def close(self) -> None:
        """Stop the worker (a build under way finishes first)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._pending.clear()


__all__ = ["KnotModels"]
