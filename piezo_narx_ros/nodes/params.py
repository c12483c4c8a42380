"""
Node parameters: one ParamSpec per parameter (default, description, limits).

`declare_parameters` declares them with descriptors and validates them at start-up and on every
later change.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter

from piezo_narx_ros.errors import ConfigError


@dataclass(frozen=True)
class ParamSpec:
    """
    One node parameter: default (its type fixes the parameter type), description and limits.

    `low`/`high` are inclusive bounds for numbers (published in the descriptor so that tools show
    them), `choices` a closed set for strings, `check` an extra predicate with its reason, e.g.
    `(lambda v: v > 0, 'must be > 0')`.
    """

    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple | None = None
    read_only: bool = False
    check: tuple[Callable[[Any], bool], str] | None = None

    @property
    def is_float(self) -> bool:
        return isinstance(self.default, float)

    def descriptor(self, final: bool = True) -> ParameterDescriptor:
        """
        Return the ParameterDescriptor carrying the description, the range and the read-only flag.

        `final=False` is the descriptor used to declare the parameter: writable, no range, and
        dynamically typed for floats, so that `-p fs:=500` (an integer) reaches our own check and
        its one-line message. `declare_parameters` then applies the final descriptor, which fixes
        the type (a float parameter holds 500.0), the range and the read-only flag.
        """
        d = ParameterDescriptor(name=self.name, description=self.description,
                                read_only=self.read_only and final,
                                dynamic_typing=self.is_float and not final)
        if self.is_float and final:
            d.type = ParameterType.PARAMETER_DOUBLE
        notes = []
        if self.choices is not None:
            notes.append('one of: ' + ', '.join(map(str, self.choices)))
        numeric = isinstance(self.default, (int, float)) and not isinstance(self.default, bool)
        if numeric and self.low is not None and self.high is not None and final:
            if self.is_float:
                d.floating_point_range = [FloatingPointRange(
                    from_value=float(self.low), to_value=float(self.high), step=0.0)]
            else:
                d.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high),
                                                step=0)]
        if self.low is not None:
            notes.append(f'>= {self.low}')
        if self.high is not None:
            notes.append(f'<= {self.high}')
        if self.check is not None:
            notes.append(self.check[1])
        d.additional_constraints = '; '.join(notes)
        return d

    def validate(self, value: Any) -> str | None:
        """Reason why `value` is refused, or None when it is acceptable."""
        if value is None:
            return (f'{self.name} has no value (`[]` has no type in ROS 2; give at least one '
                    f'element, default {self.default!r})')
        if self.is_float and (isinstance(value, bool) or not isinstance(value, (int, float))):
            return f'{self.name} must be a number, got {value!r}'
        if isinstance(value, float) and not math.isfinite(value):
            return f'{self.name} must be finite, got {value}'
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if self.low is not None and value < self.low:
                return f'{self.name} must be >= {self.low}, got {value}'
            if self.high is not None and value > self.high:
                return f'{self.name} must be <= {self.high}, got {value}'
        if self.choices is not None and value not in self.choices:
            return f'{self.name} must be one of {list(self.choices)}, got {value!r}'
        if self.check is not None:
            try:
                ok = self.check[0](value)
            except (TypeError, ValueError, AttributeError):   # e.g. len() of a number
                ok = False
            if not ok:
                return f'{self.name} {self.check[1]}, got {value!r}'
        return None


def declare_parameters(node: Node, specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """
    Declare every spec on `node` and validate the start-up values and later changes.

    Later `set_parameters` calls are validated too. Returns {name: value}. Raises ConfigError (one
    line) on a bad value.
    """
    specs = list(specs)
    by_name = {s.name: s for s in specs}
    values: dict[str, Any] = {}
    for spec in specs:
        try:
            # Declared loosely first (see ParamSpec.descriptor), so a bad value gets our message.
            param = node.declare_parameter(spec.name, spec.default, spec.descriptor(final=False))
        except ParameterException as exc:  # wrong type
            raise ConfigError(f'parameter {spec.name}: {one_line(exc)}') from None
        value = param.value
        reason = spec.validate(value)
        if reason:
            raise ConfigError(f'parameter {reason}')
        if spec.is_float:
            value = float(value)
        final = spec.descriptor(final=True)
        if not spec.is_float:
            final.type = node.describe_parameter(spec.name).type  # set_descriptor insists on it
        # The stored value becomes the checked one (500 -> 500.0 for a float), then the range and
        # read-only flag apply: `ros2 param describe` shows the bounds of read-only ones too.
        node.set_descriptor(spec.name, final,
                            Parameter(spec.name, value=value).get_parameter_value())
        values[spec.name] = value

    def on_set(params) -> SetParametersResult:
        for p in params:
            spec = by_name.get(p.name)
            if spec is None:
                continue
            reason = spec.validate(p.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)
    return values


def one_line(exc: BaseException) -> str:
    """Return the message of `exc` on one line (whitespace runs collapsed)."""
    return ' '.join(str(exc).split())
