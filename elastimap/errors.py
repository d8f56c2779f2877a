"""User-facing errors.

A :class:`UserError` is a mistake in what the user asked for (a bad parameter,
an unreadable file).  Libraries name the parameter by its Python name
(``jobs``, ``tissue.E``); CLIs print it as one line naming the flag instead
(``error: --jobs: ...``, :func:`elastimap.cli_util.run`) and exit with code 2,
without a traceback; the Python API raises it like any other ``ValueError``.
"""

from __future__ import annotations


class UserError(ValueError):
    """Bad input from the user: ``param`` names what is wrong, ``message`` what is allowed."""

    def __init__(self, param: str, message: str):
        self.param = param
        self.message = message
        super().__init__(f"{param}: {message}")


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
    that depend on other parameters; fixed rules belong in a declared table
    (:mod:`elastimap.constraints`), which words its messages the same way.
    """
    from .constraints import Interval

    closed = {(False, False): "both", (False, True): "left", (True, False): "right", (True, True): "neither"}
    rule = Interval(float, lo, hi, closed=closed[lo_open, hi_open], unit=unit)
    v = float(value)
    if not rule.is_satisfied_by(v):
        raise UserError(param, f"must be {rule} (got {value:g})")
    return v
