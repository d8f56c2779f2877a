"""The calibration-phantom table: the one reader, for the shipped table and for a user's.

A phantom table is a CSV, one row per inclusion; lines starting with ``#`` are comments
(docs/dataset.md, "Calibration phantoms"):

==================  =====  ==============================================================
column              unit   rule
==================  =====  ==============================================================
``name`` (or ``id``)       required, unique, not empty
``d``               mm     required, inclusion diameter, a positive number
``h``               mm     required, depth of the inclusion CENTRE below the surface, > 0
``E``               kPa    required, inclusion Young's modulus, > 0
``phantom``                optional, the phantom the inclusion belongs to (a label)
``tissue_E``        kPa    optional, background modulus, > 0 (absent: the run's own tissue)
``tissue_thickness`` mm    optional, tissue height, > 0 (absent: the run's own tissue)
==================  =====  ==============================================================

:func:`read_phantoms` applies these rules to every table, the shipped one
(:data:`~elastimap.dataset.schema.PHANTOMS_CSV`: the paper's nine inclusions, three phantoms of
three) and a user's, and refuses a bad table with one :class:`~elastimap.errors.UserError` line.  In a sample dataset a
phantom row is tagged ``phantom:<name>`` and has the id ``phantom-<name>`` (:func:`phantom_tag`,
:func:`is_phantom`, :func:`phantom_samples`).  pandas is imported only when a table is read.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from elastimap.errors import UserError
from elastimap.tables import check_name, read_csv

from .schema import PHANTOMS_CSV, TARGETS, UNITS

if TYPE_CHECKING:
    import pandas as pd

#: ``tag`` of a phantom row in a sample dataset is ``TAG_PREFIX + name``; its ``sample_id`` ``ID_PREFIX + name``
TAG_PREFIX = "phantom:"
ID_PREFIX = "phantom-"
#: optional numeric columns (the background the inclusion sits in) and their units
TISSUE = {"tissue_E": "kPa", "tissue_thickness": "mm"}


def read_phantoms(
    path: str | os.PathLike | None = None, *, param: str = "phantoms", min_rows: int = 1, why: str = ""
) -> pd.DataFrame:
    """The phantom table at ``path`` (``None``: the shipped :data:`PHANTOMS_CSV`), checked.

    Returns a DataFrame with a ``name`` column (str; an ``id`` column is read as ``name``), ``d``,
    ``h``, ``E`` and any optional column present (floats), in file order.  Raises
    :class:`UserError` (``param`` names the flag or argument) for a missing or unreadable file, a
    missing column, an empty or repeated name, a value that is not a positive number, or fewer
    than ``min_rows`` rows (``why`` says what the caller needs them for, e.g. "to fit a line").
    """
    import pandas as pd

    p = PHANTOMS_CSV if path is None else Path(path)
    if not p.is_file():
        raise UserError(param, f"{p}: no such file (a CSV with columns name, d, h, E)")
    df = read_csv(p, param)  # unreadable, empty, a column named twice: one line
    if "name" not in df.columns and "id" in df.columns:
        df = df.rename(columns={"id": "name"})
    missing = [c for c in ("name", *TARGETS) if c not in df.columns]
    if missing:
        raise UserError(param, f"{p}: missing column(s) {', '.join(missing)} (need name or id, d, h, E)")
    if len(df) < min_rows:
        need = f" {why}" if why else ""
        raise UserError(param, f"{p}: need at least {min_rows} inclusion(s){need} (got {len(df)})")
    names = df["name"].astype(str).str.strip()
    if df["name"].isna().any() or (names == "").any():
        raise UserError(param, f"{p}: every row needs a name")
    if names.duplicated().any():
        raise UserError(param, f"{p}: duplicate names {sorted(set(names[names.duplicated()]))}")
    for n in names:
        check_name(n, param, f"{p}: phantom name")  # names become file names (frames, sample ids)
    df["name"] = names
    for c in (*TARGETS, *(c for c in TISSUE if c in df.columns)):
        v = pd.to_numeric(df[c], errors="coerce")
        if not (np.isfinite(v).all() and (v > 0).all()):
            raise UserError(param, f"{p}: column {c} must be positive numbers ({UNITS.get(c) or TISSUE[c]})")
        df[c] = v.astype(float)
    if "phantom" in df.columns:
        df["phantom"] = df["phantom"].astype(str)
    return df.reset_index(drop=True)


def phantom_tag(name: str) -> str:
    """The ``tag`` of phantom ``name``'s row in a sample dataset."""
    return TAG_PREFIX + str(name)


def is_phantom(tags) -> np.ndarray:
    """Boolean mask of the phantom rows among ``tags`` (a dataset's ``tag`` column)."""
    return np.char.startswith(np.asarray(tags, dtype=str), TAG_PREFIX)


def phantom_name(tag: str) -> str:
    """The phantom name of a ``phantom:<name>`` tag (:class:`ValueError` for any other tag)."""
    if not str(tag).startswith(TAG_PREFIX):
        raise ValueError(f"not a phantom tag: {tag!r}")
    return str(tag)[len(TAG_PREFIX) :]


def phantom_samples(table: pd.DataFrame | None = None) -> list[dict]:
    """The rows of a phantom table (default: the shipped one) as sweep samples: ``sample_id``,
    ``tag``, ``d``, ``h``, ``E`` and the tissue columns the table gives."""
    table = read_phantoms() if table is None else table
    rows = []
    for r in table.to_dict("records"):
        row = {"sample_id": ID_PREFIX + r["name"], "tag": phantom_tag(r["name"])}
        row.update({c: float(r[c]) for c in (*TARGETS, *TISSUE) if c in r})
        rows.append(row)
    return rows
