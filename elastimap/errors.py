"""User-facing errors.

A :class:`UserError` is a mistake in what the user asked for (a bad parameter,
an unreadable file).  CLIs print it as one line and exit with code 2, without
a traceback; the Python API raises it like any other ``ValueError``.
"""

from __future__ import annotations


class UserError(ValueError):
    """Bad input from the user: ``param`` names what is wrong, ``message`` what is allowed."""

    def __init__(self, param: str, message: str):
        self.param = param
        self.message = message
        super().__init__(f"{param}: {message}")


def check_range(param: str, value: float, lo: float | None = None, hi: float | None = None,
                *, lo_open: bool = False, hi_open: bool = False, unit: str = "") -> float:
    """Return ``value`` if it lies in the interval, else raise :class:`UserError`.

    ``lo_open``/``hi_open`` make the bound strict.  NaN is always rejected.
    """
    v = float(value)
    u = f" {unit}" if unit else ""
    lo_s = "(" if (lo_open or lo is None) else "["
    hi_s = ")" if (hi_open or hi is None) else "]"
    lo_v = "-inf" if lo is None else f"{lo:g}"
    hi_v = "inf" if hi is None else f"{hi:g}"
    bad = v != v  # NaN
    if lo is not None:
        bad |= v <= lo if lo_open else v < lo
    if hi is not None:
        bad |= v >= hi if hi_open else v > hi
    if bad:
        raise UserError(param, f"must be in {lo_s}{lo_v}, {hi_v}{hi_s}{u} (got {value:g})")
    return v
