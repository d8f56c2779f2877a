"""Declared parameter rules and the one function that checks them.

A library states what each of its parameters may be as a table, next to the
parameters themselves::

    _parameter_constraints = {
        "jobs": [Interval(int, 1, 256)],
        "timeout": [None, Interval(float, 0, None, unit="s")],
        "design": [Options(("lhs", "sobol"))],
    }

and calls :func:`validate_params` on the values.  A parameter passes when it
satisfies ANY rule of its list (``None`` in the list allows ``None``).  The first
parameter that fails raises :class:`elastimap.errors.UserError` with the
*Python* parameter name and a sentence saying what is allowed, e.g.
``jobs: must be an integer in [1, 256] (got 0)``.  Command lines translate the
name into their flag (``--jobs``) in one place, :func:`elastimap.cli_util.run`.

Rules that tie two parameters together (a depth range that depends on the
diameter) stay as code after the table: the table holds what one value alone
must satisfy.

This module imports nothing heavy; a rule is a small object with
``is_satisfied_by(value)`` and a description.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from .errors import UserError

__all__ = ["Interval", "Options", "InstanceOf", "Predicate", "validate_params", "describe", "check_range"]


class Constraint:
    """One rule a value may satisfy; ``str(rule)`` completes "must be ..."."""

    def is_satisfied_by(self, value: Any) -> bool:  # pragma: no cover - interface
        raise NotImplementedError

    def __str__(self) -> str:  # pragma: no cover - interface
        raise NotImplementedError


class Interval(Constraint):
    """A number in ``[lo, hi]``; ``closed`` is ``"both"``, ``"left"``, ``"right"`` or ``"neither"``.

    ``kind`` is ``int`` (integers only, ``bool`` excluded) or ``float`` (any real, NaN
    rejected).  ``None`` for a bound means unbounded on that side; ``unit`` is printed
    after the bounds.
    """

    def __init__(self, kind: type, lo: float | None, hi: float | None, *, closed: str = "both", unit: str = ""):
        if kind not in (int, float):
            raise TypeError("Interval kind must be int or float")
        if closed not in ("both", "left", "right", "neither"):
            raise ValueError(f"closed must be both, left, right or neither (got {closed!r})")
        self.kind, self.lo, self.hi, self.closed, self.unit = kind, lo, hi, closed, unit

    def is_satisfied_by(self, value: Any) -> bool:
        if isinstance(value, bool):
            return False
        if self.kind is int:
            if not isinstance(value, numbers.Integral):
                return False
        elif not isinstance(value, numbers.Real) or not math.isfinite(value):
            return False  # NaN and ±inf: no parameter of the project is infinite
        lo_closed = self.closed in ("both", "left")
        hi_closed = self.closed in ("both", "right")
        if self.lo is not None and (value < self.lo if lo_closed else value <= self.lo):
            return False
        if self.hi is not None and (value > self.hi if hi_closed else value >= self.hi):
            return False
        return True

    def __str__(self) -> str:
        lo_closed = self.closed in ("both", "left")
        hi_closed = self.closed in ("both", "right")
        u = f" {self.unit}" if self.unit else ""
        lo, hi = _num(self.lo), _num(self.hi)
        if self.lo is not None and self.hi is not None:
            rng = f"in {'[' if lo_closed else '('}{lo}, {hi}{']' if hi_closed else ')'}{u}"
        elif self.lo is not None:
            rng = f"{'>=' if lo_closed else '>'} {lo}{u}"
        elif self.hi is not None:
            rng = f"{'<=' if hi_closed else '<'} {hi}{u}"
        else:
            rng = ""
        if self.kind is int:
            return f"an integer {rng}".rstrip()
        return rng or "a number"


def _num(x: float | None) -> str:
    if x is None:
        return ""
    if float(x).is_integer() and abs(x) < 1e15:
        return str(int(x))
    return f"{x:g}"


class Options(Constraint):
    """One of a fixed set of values (compared with ``==``)."""

    def __init__(self, values: Iterable[Any]):
        self.values = tuple(values)

    def is_satisfied_by(self, value: Any) -> bool:
        try:
            return value in self.values
        except TypeError:
            return False

    def __str__(self) -> str:
        return "one of " + ", ".join(str(v) for v in self.values)


class InstanceOf(Constraint):
    """An instance of ``types``; ``what`` names it in the message (default: the type names)."""

    def __init__(self, types: type | tuple[type, ...], what: str | None = None):
        self.types = types if isinstance(types, tuple) else (types,)
        self.what = what or " or ".join(f"a {t.__name__}" for t in self.types)

    def is_satisfied_by(self, value: Any) -> bool:
        return isinstance(value, self.types)

    def __str__(self) -> str:
        return self.what


class Predicate(Constraint):
    """Any test that does not fit the others: ``test(value) -> bool`` and what it means."""

    def __init__(self, test: Callable[[Any], bool], what: str):
        self.test, self.what = test, what

    def is_satisfied_by(self, value: Any) -> bool:
        try:
            return bool(self.test(value))
        except Exception:  # a value the test cannot even look at (a list where a str is due) fails it
            return False

    def __str__(self) -> str:
        return self.what


def describe(rules: list) -> str:
    """The "must be ..." sentence of one parameter's rule list (``None``, "not given", is left out)."""
    parts = [str(r) for r in rules if r is not None] or ["None"]
    return parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " or " + parts[-1]


def _show(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    return repr(value)


def validate_params(values: Mapping[str, Any], constraints: Mapping[str, list], *, prefix: str = "") -> None:
    """Check ``values[name]`` against ``constraints[name]`` for every name of the table, in table order.

    Raises :class:`UserError` (``param`` = ``prefix + name``) at the first value that satisfies
    none of its rules.  Names missing from ``values`` are skipped; names without rules are not
    checked.
    """
    for name, rules in constraints.items():
        if name not in values:
            continue
        v = values[name]
        if v is None and None in rules:
            continue
        if any(r is not None and r.is_satisfied_by(v) for r in rules):
            continue
        raise UserError(prefix + name, f"must be {describe(rules)} (got {_show(v)})")


def check_range(
    param: str,
    value: float,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    unit: str = "",
) -> float:
    """Return ``value`` as a float if it lies in the interval, else raise :class:`UserError`.

    ``lo_open``/``hi_open`` make the bound strict.  NaN and ±inf are always rejected.  Meant for bounds
    that depend on other parameters; fixed rules belong in a declared table (:func:`validate_params`),
    whose messages are worded the same way.
    """
    closed = {(False, False): "both", (False, True): "left", (True, False): "right", (True, True): "neither"}
    rule = Interval(float, lo, hi, closed=closed[lo_open, hi_open], unit=unit)
    v = float(value)
    if not rule.is_satisfied_by(v):
        raise UserError(param, f"must be {rule} (got {value:g})")
    return v
