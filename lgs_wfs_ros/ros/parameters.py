"""Declaring node parameters with descriptors, and refusing changes with a reason.

The demo_nodes_py pattern: validate in an on-set callback (which may refuse with a reason and
leaves every parameter as it was), apply in a post-set callback.
"""

from __future__ import annotations

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)


def declare(node, name: str, default, description: str, *, low=None, high=None,
            choices=None, read_only: bool = False):
    """Declare one parameter with a descriptor (description, range, allowed values)."""
    extra = ""
    if choices:
        extra = " One of: " + ", ".join(map(str, choices)) + "."
    desc = ParameterDescriptor(description=description + extra, read_only=read_only)
    if low is not None or high is not None:
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=0)]
        elif isinstance(default, float):
            desc.floating_point_range = [FloatingPointRange(from_value=float(low),
                                                            to_value=float(high), step=0.0)]
    return node.declare_parameter(name, default, desc)


def refuse(reason: str) -> SetParametersResult:
    return SetParametersResult(successful=False, reason=reason)


def accept() -> SetParametersResult:
    return SetParametersResult(successful=True)


def values(node, names) -> dict:
    """Current values of the named parameters."""
    return {n: node.get_parameter(n).value for n in names}
