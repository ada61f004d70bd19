"""Optional dependencies: import one, or say which extra installs it (no traceback).

The package's runtime needs only ``install_requires`` (setup.py); the extras add ROS 2
(``ros``), PyTorch for training (``train``) and the test tools (``test``). A module that
needs an optional dependency calls :func:`require`, which raises :class:`MissingExtra`
with a one-line message naming the extra.
"""

from __future__ import annotations

import importlib


class MissingExtra(ImportError):
    """An optional dependency is not installed; the message names the extra that installs it."""


def require(module: str, extra: str, purpose: str):
    """Import ``module`` or raise :class:`MissingExtra` naming ``extra``.

    Args:
        module: the module to import (e.g. "torch").
        extra: the setup.py extra that installs it (e.g. "train").
        purpose: what needs it, for the message (e.g. "lgs-wfs train").
    Returns: the imported module.
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtra(f"{purpose} needs {module}, which is not installed: install the "
                           f"'{extra}' extra, pip install 'lgs_wfs_ros[{extra}]' "
                           f"(from a checkout: pip install -e '.[{extra}]')") from exc


__all__ = ["MissingExtra", "require"]
