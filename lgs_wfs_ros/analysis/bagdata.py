"""Former home of :mod:`.bagload` (loading a contract bag) and :mod:`.bagwrite` (writing one),
which did both jobs; it re-exports their names so existing imports keep working. New code
imports from those two modules."""

from .bagload import *  # noqa: F401,F403
from .bagload import __all__ as _load_all
from .bagwrite import *  # noqa: F401,F403
from .bagwrite import __all__ as _write_all

__all__ = sorted(set(_load_all) | set(_write_all))
