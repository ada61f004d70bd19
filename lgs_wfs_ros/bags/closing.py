"""The context-manager protocol of the bag readers and writers: ``with X(...) as x:`` closes
``x`` on the way out, exception or not (the exception is never swallowed)."""

from __future__ import annotations


class Closing:
    """Mixin for a class with a ``close()`` method."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False
