"""Reading the small tables users hand over (phantom specs, feature tables, batch CSVs).

One reader, so that every command refuses the same damage the same way, in one line naming the
parameter and the file: a missing file or a folder, an empty or unparsable file, a header that
names a column twice (pandas would silently read the first and rename the second), and, with
:func:`numbers`, values that are not finite numbers.  Sample datasets (Parquet) have their own
reader, :mod:`elastimap.dataset.io`.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from .errors import UserError

__all__ = ["read_csv", "numbers", "check_name"]


def _header(p: Path) -> list[str]:
    with open(p, newline="", encoding="utf-8", errors="replace") as fh:
        for row in csv.reader(fh, skipinitialspace=True):
            if row and not row[0].lstrip().startswith("#"):
                return [c.strip() for c in row]
    return []


def read_csv(path: str | os.PathLike, param: str, *, required: tuple[str, ...] = ()):
    """A user's CSV (``#`` starts a comment line) as a DataFrame, with ``required`` columns."""
    import pandas as pd

    p = Path(path)
    if not p.exists():
        raise UserError(param, f"{p}: no such file")
    if p.is_dir():
        raise UserError(param, f"{p}: is a folder, not a CSV file")
    try:
        head = _header(p)
        df = pd.read_csv(p, comment="#", skipinitialspace=True)
    except (OSError, UnicodeDecodeError, ValueError, csv.Error) as exc:  # pandas' parser errors are ValueErrors
        raise UserError(param, f"{p}: not a readable CSV table ({type(exc).__name__}: {exc})") from None
    dup = sorted({c for c in head if head.count(c) > 1})
    if dup:
        raise UserError(param, f"{p}: column(s) {', '.join(dup)} appear more than once")
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise UserError(param, f"{p}: missing column(s) {', '.join(missing)} (need {', '.join(required)})")
    return df


def numbers(df, col: str, param: str, where: str, *, positive: bool = False) -> np.ndarray:
    """Column ``col`` as finite floats (``positive``: also > 0); else a :class:`UserError` naming the rows."""
    import pandas as pd

    v = pd.to_numeric(df[col], errors="coerce").to_numpy(float)
    bad = ~np.isfinite(v) | ((v <= 0) if positive else False)
    if bad.any():
        rows = [int(i) + 1 for i in np.flatnonzero(bad)[:5]]
        what = "positive numbers" if positive else "finite numbers"
        raise UserError(param, f"{where}: column {col} must hold {what} (data rows {rows})")
    return v


def check_name(value: str, param: str, what: str = "name") -> str:
    """A name that becomes part of a file name (an id, ``--name``): not empty, no ``/``, ``\\``,
    control characters, and not ``.`` or ``..``; checked before any work."""
    s = str(value)
    if not s.strip() or s in (".", "..") or any(c in s for c in "/\\") or any(ord(c) < 32 for c in s):
        raise UserError(
            param, f"{what} {s!r} cannot be part of a file name (no '/', '\\\\', control characters, '.' or '..')"
        )
    return s
