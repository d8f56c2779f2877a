"""The sample table: one row per forward solve, as landed by the sweep.

Units: lengths mm, moduli kPa, forces mN, time s, memory MiB.  The schema
version and the units are written into every Parquet file's metadata
(key ``elastimap.schema``, a JSON object), together with the elasticity-image
shape and pixel size (key ``elastimap.image``).

This module is the single definition of the columns and of the vocabulary every
room shares; writers (``sweep``) and readers (``training``, ``camera``, ``gap``,
``identify``) import it:

* ``FEATURES`` (O1, O2, O3) and ``TARGETS`` (d, h, E), with their ``UNITS``;
* ``DESIGN_BOX`` (d 2–15 mm, E 10–200 kPa; h spans ``depth_range(d, thickness)``)
  and the default slab ``THICKNESS`` (20 mm).  These two and ``depth_range`` are
  the solver's own defaults, defined in :mod:`elastimap.solver.params` (which
  imports nothing heavy) and re-exported here.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa

from elastimap.solver.params import DESIGN_BOX, THICKNESS, depth_range  # noqa: F401  (vocabulary, re-exported)

#: the shipped calibration-phantom table (installed with the package); read it with
#: :func:`elastimap.dataset.phantoms.read_phantoms`
PHANTOMS_CSV = Path(__file__).resolve().parent / "phantoms.csv"

SCHEMA_VERSION = 1

# name: (arrow type, unit, description)
COLUMNS: dict[str, tuple[pa.DataType, str, str]] = {
    "sample_id": (
        pa.string(),
        "",
        "stable id derived from the design, its seed and the sample index (or a hash of the row)",
    ),
    "tag": (
        pa.string(),
        "",
        "'design' for sampled points, 'phantom:<name>' for calibration-phantom inclusions, 'user' for --samples rows",
    ),
    "d": (pa.float64(), "mm", "inclusion diameter"),
    "h": (pa.float64(), "mm", "depth of the inclusion centre below the tissue surface"),
    "E": (pa.float64(), "kPa", "inclusion Young's modulus"),
    "O1": (pa.float64(), "mm", "maximum of the difference elasticity image"),
    "O2": (pa.float64(), "mm", "sum over pixels of the difference elasticity image"),
    "O3": (pa.float64(), "mm^2", "area where the difference image exceeds the threshold"),
    "force": (pa.float64(), "mN", "plate reaction force with the inclusion (full probe)"),
    "force_ref": (
        pa.float64(),
        "mN",
        "plate reaction force of the reference solve (inclusion modulus = tissue modulus)",
    ),
    "image": (pa.list_(pa.float32()), "mm", "difference elasticity image, row-major, shape in metadata"),
    "params_json": (pa.string(), "", "all solver inputs as JSON (tissue, probe, loading, discretisation, image spec)"),
    "status": (pa.string(), "", "'ok' or 'failed'"),
    "error": (pa.string(), "", "error message of a failed sample ('' when ok)"),
    "ndofs": (pa.int64(), "", "degrees of freedom of one solve"),
    "newton_iterations": (pa.int64(), "", "solver iterations, both solves"),
    "seconds": (pa.float64(), "s", "wall time of the sample (both solves)"),
    "peak_memory_mb": (pa.float64(), "MiB", "peak resident memory of the worker process"),
    "code_version": (pa.string(), "", "elastimap version and git commit"),
    "host": (pa.string(), "", "machine that ran the sample"),
    # added by the sweep (additive; readers that ignore it are unaffected)
    "landed_at": (
        pa.float64(),
        "s",
        "unix time the row was written; the newest row of a sample id wins (an 'ok' row always beats a 'failed' one)",
    ),
    # added by the solve store (additive; see elastimap.dataset.store)
    "key": (
        pa.string(),
        "",
        "solve key: sha256 of the canonical JSON of the solver inputs (elastimap.dataset.store.params_key)",
    ),
    "solver": (
        pa.string(),
        "",
        "what produced the row: 'fem' (the forward model; also when absent) or 'synthetic' (the test stand-in)",
    ),
    "delta": (pa.float64(), "mm", "indentation actually applied"),
    "image_raw": (
        pa.list_(pa.float32()),
        "mm",
        "raw probe compression image (with the inclusion), row-major; solve-store rows only",
    ),
}

# Columns every conforming file must have (the original version-1 set); the later ones are optional
# so that files written before they existed still read.
OPTIONAL = ("landed_at", "key", "solver", "delta", "image_raw")
REQUIRED = tuple(k for k in COLUMNS if k not in OPTIONAL)
SCHEMA_KEY = "elastimap.schema"
IMAGE_KEY = "elastimap.image"

#: the three image features (paper section 3.2) and the three inclusion parameters
FEATURES = ("O1", "O2", "O3")
TARGETS = ("d", "h", "E")
#: unit of each feature and target (mm, mm^2, kPa), read from ``COLUMNS``
UNITS = {name: COLUMNS[name][1] for name in FEATURES + TARGETS}


def arrow_schema(image_shape: tuple[int, int] | None = None, pixel: float | None = None) -> pa.Schema:
    """Arrow schema with the version, units and image geometry in its metadata."""
    import json

    fields = [pa.field(name, typ) for name, (typ, _, _) in COLUMNS.items()]
    meta = {
        "elastimap.schema": json.dumps(
            {
                "version": SCHEMA_VERSION,
                "units": {k: u for k, (_, u, _) in COLUMNS.items() if u},
                "descriptions": {k: d for k, (_, _, d) in COLUMNS.items()},
            }
        ),
    }
    if image_shape is not None:
        meta["elastimap.image"] = json.dumps(
            {"shape": list(image_shape), "pixel_mm": pixel, "order": "row-major, row 0 at y = -size/2"}
        )
    return pa.schema(fields, metadata=meta)
