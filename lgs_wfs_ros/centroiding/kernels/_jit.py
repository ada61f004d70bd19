"""numba, when the ``fast`` extra is installed.

:data:`COMPILED` says whether numba is there (the modules compile their passes at import);
:func:`enabled` whether the compiled passes run now: the package's ``AVAILABLE``, read at
each call, so that turning it off (a test comparing the numpy paths) takes every wrapper
and every caller to numpy together.
"""

import sys

try:                                     # optional: the 'fast' extra
    import numba
    COMPILED = True
except ImportError:                      # pragma: no cover - exercised where it is absent
    numba = None
    COMPILED = False


def enabled() -> bool:
    """True when the compiled passes are to be used (``kernels.AVAILABLE``)."""
    return bool(sys.modules[__package__].AVAILABLE)
