"""Declaring node parameters with descriptors, and refusing changes with a reason.

The demo_nodes_py pattern: validate in an on-set callback (which may refuse with a reason and
leaves every parameter as it was), apply in a post-set callback. On top of rclpy, every node
that declares through :func:`declare` gets, once:

- an integer taken where a double is due, both at start-up (``-p photons:=1000``, which
  rclpy refuses with an exception) and at run time (``ros2 param set ... photons 1000``,
  which rclpy refuses as "Wrong parameter type"): a pre-set callback converts it;
- likewise a number where a string is due, as its text (the player's ``rate`` is
  ``recorded``, ``max`` or a number: ``-p rate:=800`` arrives as an integer);
- the allowed choices of a string parameter checked (a descriptor cannot hold them: they are
  in its description and ``additional_constraints``, so ``ros2 param describe`` shows them).

Ranges go into the descriptor's ``integer_range`` / ``floating_point_range``, which rclpy
enforces with its own reason ("out of range").
"""

from __future__ import annotations

import math

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.parameter import Parameter

INT64 = 2**63 - 1
_WIDENED = {ParameterType.PARAMETER_DOUBLE: (Parameter.Type.INTEGER, float),
            ParameterType.PARAMETER_DOUBLE_ARRAY: (Parameter.Type.INTEGER_ARRAY,
                                                   lambda v: [float(x) for x in v])}


class _Checks:
    """Per-node state: the allowed choices of each string parameter."""

    def __init__(self, node):
        self.node = node
        self.choices: dict[str, tuple] = {}
        node.add_pre_set_parameters_callback(self.widen)
        node.add_on_set_parameters_callback(self.check_choices)

    def widen(self, params):
        """An integer (array) for a double (array) parameter, as a double (array)."""
        out = []
        for p in params:
            if self.node.has_parameter(p.name):
                desc = self.node.describe_parameter(p.name)
                widen = _WIDENED.get(desc.type)
                if not desc.dynamic_typing and widen and p.type_ == widen[0]:
                    p = Parameter(p.name, value=widen[1](p.value))
                elif (not desc.dynamic_typing and desc.type == ParameterType.PARAMETER_STRING
                      and p.type_ in (Parameter.Type.INTEGER, Parameter.Type.DOUBLE)):
                    p = Parameter(p.name, value=str(p.value))
            out.append(p)
        return out

    def check_choices(self, params):
        for p in params:
            allowed = self.choices.get(p.name)
            if allowed and p.value not in allowed:
                return refuse(f"{p.name} must be one of {', '.join(map(str, allowed))}, "
                              f"got {p.value!r}")
        return accept()


def _checks(node) -> _Checks:
    checks = getattr(node, "_lgs_parameter_checks", None)
    if checks is None:
        checks = node._lgs_parameter_checks = _Checks(node)
    return checks


def descriptor(default, description: str, *, low=None, high=None, choices=None,
               read_only: bool = False) -> ParameterDescriptor:
    """The descriptor: description (choices appended), range for numbers, read-only flag."""
    desc = ParameterDescriptor(description=description, read_only=read_only)
    if choices:
        desc.additional_constraints = "One of: " + ", ".join(map(str, choices)) + "."
        desc.description += " " + desc.additional_constraints
    if (low is not None or high is not None) and not isinstance(default, bool):
        if isinstance(default, int):
            desc.integer_range = [IntegerRange(
                from_value=-INT64 if low is None else int(low),
                to_value=INT64 if high is None else int(high), step=0)]
        elif isinstance(default, float):
            desc.floating_point_range = [FloatingPointRange(
                from_value=-math.inf if low is None else float(low),
                to_value=math.inf if high is None else float(high), step=0.0)]
    return desc


def declare(node, name: str, default, description: str, *, low=None, high=None,
            choices=None, read_only: bool = False):
    """Declare one parameter with a descriptor (description, range, allowed values).

    A start-up override of the wrong type is refused by rclpy with an exception; for an
    integer where a double is due it is taken as that double instead, and a number where a
    string is due as its text.
    """
    checks = _checks(node)
    if choices:
        checks.choices[name] = tuple(choices)
    desc = descriptor(default, description, low=low, high=high, choices=choices,
                      read_only=read_only)
    try:
        return node.declare_parameter(name, default, desc)
    except InvalidParameterTypeException:
        if not isinstance(default, (float, str)):
            raise
    # The override is of another type: read it through a dynamically typed declaration
    # (public API only), then declare the double (the string) with its value (its text).
    given = node.declare_parameter(name, default, ParameterDescriptor(dynamic_typing=True))
    value = given.value
    node.undeclare_parameter(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        kind = "a string" if isinstance(default, str) else "a number"
        raise ValueError(f"parameter {name} must be {kind}, got {value!r}")
    value = str(value) if isinstance(default, str) else float(value)
    # declared with the given value as its default: ranges and callbacks apply as usual
    return node.declare_parameter(name, value, desc, ignore_override=True)


def declare_option(node, opt):
    """Declare a :class:`~lgs_wfs_ros.centroiding.options.Option` as ``<algorithm>.<option>``
    with its description, range, choices and read-only flag."""
    return declare(node, opt.parameter, opt.default, opt.description, low=opt.low,
                   high=opt.high, choices=opt.choices or None, read_only=opt.read_only)


def refuse(reason: str) -> SetParametersResult:
    return SetParametersResult(successful=False, reason=reason)


def accept() -> SetParametersResult:
    return SetParametersResult(successful=True)


def values(node, names) -> dict:
    """Current values of the named parameters."""
    return {n: node.get_parameter(n).value for n in names}
