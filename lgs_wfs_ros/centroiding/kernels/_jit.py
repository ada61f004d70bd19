"""numba, when the ``fast`` extra is installed: :data:`AVAILABLE` says whether the compiled
passes run (each module's wrappers read it at call time and keep a numpy path for when it
is False)."""

try:                                     # optional: the 'fast' extra
    import numba
    AVAILABLE = True
except ImportError:                      # pragma: no cover - exercised where it is absent
    numba = None
    AVAILABLE = False
