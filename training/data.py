"""Reading the sample table for training, and a SYNTHETIC toy table for tests.

Training only knows the sample-table columns of :mod:`elastimap.dataset.schema`
(features ``O1, O2, O3``, targets ``d, h, E``, ``status``, ``tag``,
``sample_id``); it never looks at how the rows were made.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import pandas as pd

from elastimap.dataset.phantoms import is_phantom, phantom_tag
from elastimap.dataset.schema import FEATURES, TARGETS, UNITS  # noqa: F401  (UNITS: re-exported)
from elastimap.errors import UserError

OPTIONAL = ("sample_id", "tag", "status")


@dataclass
class Samples:
    """The usable (status 'ok') rows, sorted by ``sample_id``, and what was dropped."""

    df: pd.DataFrame  # columns sample_id, tag, O1, O2, O3, d, h, E
    n_total: int  # rows read
    n_failed: int  # rows with status != 'ok' (excluded)
    source: str  # path or '<dataframe>'

    @property
    def n(self) -> int:
        return len(self.df)

    def report(self) -> str:
        s = f"{self.n} usable samples from {self.source}"
        if self.n_failed:
            s += f" ({self.n_failed} failed sample(s) excluded)"
        n_ph = int(is_phantom(self.df["tag"]).sum())
        if n_ph:
            s += f"; {n_ph} calibration-phantom row(s)"
        return s


def load_samples(path: str) -> Samples:
    """Read a sample dataset (a sweep's folder or one of its Parquet files) for training.

    It goes through the one reader of sample datasets, :func:`elastimap.dataset.io.read_samples`
    (the one ``dataset inspect`` uses): every file's schema is checked (a foreign Parquet file is
    refused, naming it), only the folder's own files are read (a sweep in a subfolder is not
    merged), and a sample id is read once (duplicates left by an interrupted compaction or a
    retried failure collapse to one row).  Errors name ``data``.
    """
    from elastimap.dataset.io import read_samples

    cols = [*FEATURES, *TARGETS, *OPTIONAL]
    try:
        df = read_samples(path, columns=cols, status=None)
    except UserError as exc:
        raise UserError("data", exc.message) from None
    return prepare(df, source=str(path))


def prepare(df: pd.DataFrame, source: str = "<dataframe>") -> Samples:
    """Check a sample table and keep its usable rows (also used by the Python API)."""
    missing = [c for c in FEATURES + TARGETS if c not in df.columns]
    if missing:
        raise UserError("data", f"{source} lacks required column(s) {', '.join(missing)}")
    df = df.copy()
    n_total = len(df)
    if "status" in df.columns:
        ok = df["status"].astype(str) == "ok"
    else:
        ok = pd.Series(True, index=df.index)
    n_failed = int((~ok).sum())
    df = df[ok]
    if "tag" not in df.columns:
        df["tag"] = "design"
    df["tag"] = df["tag"].fillna("").astype(str)
    if "sample_id" not in df.columns:
        df["sample_id"] = [f"row{i:06d}" for i in range(len(df))]
    df["sample_id"] = df["sample_id"].astype(str)
    for c in FEATURES + TARGETS:
        try:
            df[c] = pd.to_numeric(df[c], errors="raise").astype(np.float64)
        except (TypeError, ValueError):
            raise UserError("data", f"column {c} of {source} is not numeric") from None
    vals = df[list(FEATURES + TARGETS)].to_numpy()
    bad = ~np.isfinite(vals).all(axis=1)
    if bad.any():
        first = df["sample_id"].to_numpy()[bad][0]
        cols = [c for j, c in enumerate(FEATURES + TARGETS) if (~np.isfinite(vals[bad, j])).any()]
        raise UserError(
            "data",
            f"{int(bad.sum())} 'ok' row(s) of {source} have NaN/inf in {', '.join(cols)} "
            f"(first: sample_id {first}); fix or mark them failed",
        )
    if len(df) == 0:
        raise UserError("data", f"{source} has no usable samples ({n_failed} failed)")
    dup = df["sample_id"].duplicated()
    if dup.any():
        raise UserError("data", f"{source} has duplicate sample_id {df['sample_id'][dup].iloc[0]!r}")
    df = df.sort_values("sample_id", kind="stable").reset_index(drop=True)
    df = df[["sample_id", "tag", *FEATURES, *TARGETS]]
    return Samples(df=df, n_total=n_total, n_failed=n_failed, source=source)


def data_hash(df: pd.DataFrame) -> str:
    """SHA-256 of the sample ids and the feature/target values (row order as given)."""
    h = hashlib.sha256()
    h.update("\n".join(df["sample_id"].astype(str)).encode())
    h.update(np.ascontiguousarray(df[list(FEATURES + TARGETS)].to_numpy(np.float64)).tobytes())
    return h.hexdigest()


# ---------------------------------------------------------------------------
# SYNTHETIC toy table (tests, development, benchmarks) -- not FEM results.

SYNTH_PHANTOMS = {  # name: (d mm, h mm, E kPa) -- invented values for the toy table
    "size-1": (4.0, 8.0, 60.0),
    "size-2": (7.0, 8.0, 60.0),
    "size-3": (10.0, 8.0, 60.0),
    "depth-1": (7.0, 5.0, 60.0),
    "depth-2": (7.0, 9.0, 60.0),
    "depth-3": (7.0, 12.0, 60.0),
    "hardness-1": (7.0, 8.0, 20.0),
    "hardness-2": (7.0, 8.0, 80.0),
    "hardness-3": (7.0, 8.0, 200.0),
}


def synthetic_features(d, h, E):
    """SYNTHETIC smooth analytic stand-in for the FEM forward map (d, h, E) -> (O1, O2, O3).

    Monotone like the paper describes (O1, O3 grow with d and E, all decay with
    depth) and injective on the toy ranges.  Its numbers mean nothing physically.
    """
    d, h, E = (np.asarray(v, dtype=np.float64) for v in (d, h, E))
    O1 = 0.08 * (d / 8) ** 1.2 * (1 - np.exp(-E / 60)) * np.exp(-h / 9)
    O2 = 30.0 * (d / 8) ** 2.2 * (1 - np.exp(-E / 90)) * np.exp(-h / 14)
    O3 = 20.0 * (d / 8) ** 1.8 * (E / 50) ** 0.3 * np.exp(-h / 20)
    return O1, O2, O3


def synthetic_table(n: int = 512, seed: int = 0, phantoms: bool = True, n_failed: int = 0) -> pd.DataFrame:
    """SYNTHETIC toy sample table of ``n`` ok rows (+ ``n_failed`` failed rows).

    ``d ~ U(3, 12) mm``, ``h ~ U(4, 14) mm``, ``E ~ logU(10, 300) kPa``; with
    ``phantoms`` the last 9 of the ``n`` rows are the invented phantom
    inclusions of :data:`SYNTH_PHANTOMS`, tagged ``phantom:<name>``.
    """
    rng = np.random.default_rng(seed)
    n_ph = len(SYNTH_PHANTOMS) if phantoms else 0
    if n < n_ph + 1:
        raise UserError("n", f"need at least {n_ph + 1} samples for the synthetic table")
    m = n - n_ph
    d = rng.uniform(3, 12, m)
    h = rng.uniform(4, 14, m)
    E = np.exp(rng.uniform(np.log(10), np.log(300), m))
    tags = ["design"] * m
    if phantoms:
        ph = np.array(list(SYNTH_PHANTOMS.values()))
        d, h, E = np.r_[d, ph[:, 0]], np.r_[h, ph[:, 1]], np.r_[E, ph[:, 2]]
        tags += [phantom_tag(k) for k in SYNTH_PHANTOMS]
    O1, O2, O3 = synthetic_features(d, h, E)
    df = pd.DataFrame(
        {
            "sample_id": [f"synthetic-{seed}-{i:05d}" for i in range(n)],
            "tag": tags,
            "d": d,
            "h": h,
            "E": E,
            "O1": O1,
            "O2": O2,
            "O3": O3,
            "status": "ok",
        }
    )
    if n_failed:
        bad = pd.DataFrame(
            {
                "sample_id": [f"synthetic-{seed}-failed-{i:03d}" for i in range(n_failed)],
                "tag": "design",
                "d": 5.0,
                "h": 7.0,
                "E": 50.0,
                "O1": np.nan,
                "O2": np.nan,
                "O3": np.nan,
                "status": "failed",
            }
        )
        df = pd.concat([df, bad], ignore_index=True)
    return df
