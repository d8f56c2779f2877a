"""Reading and landing sample datasets (a directory of Parquet files).

Layout of a dataset directory (written by ``sweep run``)::

    sweeps/NAME/
        _sweep.json                manifest: solver settings, planned sample ids, run log
        r-<ns>-<rand>.parquet      one row, landed by a worker right after its solve
        b-<ns>-<rand>.parquet      a batch of up to ``BATCH_ROWS`` rows (compaction of r- files)
        .*.tmp                     a file being written (ignored; removed by the next run)

Every row carries its solve key (``key``), so a dataset directory is also a solve store
(:mod:`elastimap.dataset.store`), which lands its own rows the same way.

Every file is written under a temporary name and ``os.replace``d into place, so
a file either exists complete or not at all (kill -9 safe).  A sample id may
appear in several files (a retried failure, a compaction killed before it
removed its inputs): readers keep one row per id, an ``ok`` row before a
``failed`` one, then the newest (``landed_at``).

Public reading API (used by training, camera, gap):

* :func:`read_samples` ``(path, columns=None, status='ok') -> DataFrame``
* :func:`read_image_meta` ``(path) -> ((ny, nx), pixel_mm)``
* :func:`stack_images` ``(df, shape) -> ndarray (n, ny, nx)``

``path`` is a dataset directory or a single Parquet file.
"""

from __future__ import annotations

import json
import os
import time
import uuid
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from elastimap.errors import UserError

from .schema import COLUMNS, IMAGE_KEY, REQUIRED, SCHEMA_KEY, SCHEMA_VERSION, arrow_schema

BATCH_ROWS = 256
LOCK = ".sweep.lock"
MANIFEST = "_sweep.json"  # leading _ : pyarrow.dataset / pandas.read_parquet(dir) skip it
_KEY_COLS = ("sample_id", "status", "landed_at")


# ----------------------------------------------------------------------------- files


class _Vanished(Exception):
    """A file disappeared between listing and reading (a compaction replaced it)."""


def _retrying(fn):
    """Re-list and read again when a running sweep's compaction removes a file under our feet.

    Compaction writes the merged file before it removes the inputs, so a fresh listing always
    holds every row (possibly twice, which the id rule resolves)."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args, **kw):
        for attempt in range(10):
            try:
                return fn(*args, **kw)
            except _Vanished as exc:
                last = exc
                time.sleep(0.05 * (attempt + 1))
        raise UserError("path", f"files keep disappearing while reading (last: {last}); is something deleting them?")

    return wrapper


def _first_line(exc: BaseException) -> str:
    """``Type: first line of the message`` (pyarrow's messages run over several lines)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return f"{type(exc).__name__}: {lines[0]}" if lines else type(exc).__name__


def _files(path: str | os.PathLike, *, must_exist: bool = True) -> list[Path]:
    p = Path(path)
    if not p.exists():
        if must_exist:
            raise UserError("path", f"{p} does not exist")
        return []
    if p.is_file():
        if p.suffix != ".parquet":
            raise UserError("path", f"{p} is not a Parquet file (expected a dataset directory or a .parquet file)")
        return [p]
    if not p.is_dir():
        raise UserError("path", f"{p} is neither a directory nor a file")
    files = sorted(f for f in p.glob("*.parquet") if not f.name.startswith("."))
    if not files and must_exist:
        raise UserError("path", f"{p} holds no Parquet files (not a sample dataset, or nothing landed yet)")
    return files


def _meta(f: Path) -> tuple[pa.Schema, dict, dict | None]:
    """Schema, parsed schema metadata and image metadata of one file; UserError if it does not conform."""
    try:
        schema = pq.read_schema(f)
    except FileNotFoundError:
        raise _Vanished(f) from None
    except Exception as exc:  # pyarrow raises several types for corrupt/foreign files
        if not f.exists():
            raise _Vanished(f) from None
        raise UserError("path", f"{f} is not a readable Parquet file ({_first_line(exc)})") from None
    md = schema.metadata or {}
    raw = md.get(SCHEMA_KEY.encode())
    if raw is None:
        raise UserError("path", f"{f} is not an elastimap sample file (no '{SCHEMA_KEY}' metadata)")
    try:
        info = json.loads(raw)
    except ValueError:
        raise UserError("path", f"{f}: the '{SCHEMA_KEY}' metadata is not JSON") from None
    if not isinstance(info, dict):
        raise UserError("path", f"{f}: the '{SCHEMA_KEY}' metadata is not a JSON object")
    version = info.get("version")
    if not isinstance(version, int) or version > SCHEMA_VERSION:
        raise UserError("path", f"{f} has schema version {version!r}; this code reads versions <= {SCHEMA_VERSION}")
    missing = [c for c in REQUIRED if c not in schema.names]
    if missing:
        raise UserError("path", f"{f} lacks column(s) {', '.join(missing)}")
    for c in REQUIRED:
        want = COLUMNS[c][0]
        got = schema.field(c).type
        if not got.equals(want):
            raise UserError("path", f"{f}: column {c} is {got}, expected {want}")
    image = md.get(IMAGE_KEY.encode())
    try:
        img = json.loads(image) if image else None
    except ValueError:
        img = "bad"
    if img is not None and not (isinstance(img, dict) and isinstance(img.get("shape", []), list)):
        raise UserError("path", f"{f}: the '{IMAGE_KEY}' metadata is not a JSON object with a shape")
    return schema, info, img


@_retrying
def dataset_info(path) -> dict:
    """Schema version, units, file count and image geometry of a dataset (checks every file)."""
    files = _files(path)
    infos = [_meta(f) for f in files]
    versions = sorted({i[1]["version"] for i in infos})
    shape, pixel = _image_meta(infos, files)
    units = {}
    for _, info, _ in infos:
        units.update(info.get("units", {}))
    return {
        "files": len(files),
        "versions": versions,
        "units": units,
        "image_shape": shape,
        "pixel": pixel,
        "columns": list(infos[0][0].names),
        "bytes": sum(f.stat().st_size for f in files),
    }


def _image_meta(infos, files) -> tuple[tuple[int, int] | None, float | None]:
    seen = {}
    for (_, _, img), f in zip(infos, files):
        if img and img.get("shape"):
            key = (tuple(int(x) for x in img["shape"]), float(img["pixel_mm"]))
            seen.setdefault(key, f)
    if len(seen) > 1:
        desc = "; ".join(f"{f.name}: shape {k[0]}, pixel {k[1]:g} mm" for k, f in seen.items())
        raise UserError("path", f"files disagree on the elasticity-image geometry ({desc})")
    if not seen:
        return None, None
    ((shape, pixel),) = seen
    return shape, pixel


@_retrying
def read_image_meta(path) -> tuple[tuple[int, int], float]:
    """``((ny, nx), pixel_mm)`` of the elasticity images of a dataset."""
    files = _files(path)
    shape, pixel = _image_meta([_meta(f) for f in files], files)
    if shape is None:
        raise UserError("path", f"{path} has no elasticity-image metadata")
    return shape, pixel


# ----------------------------------------------------------------------------- reading


def _dedupe_index(df: pd.DataFrame) -> np.ndarray:
    """Positions of the rows to keep, one per sample id (ok before failed, then newest), in id order."""
    if df.empty:
        return np.zeros(0, dtype=int)
    ok = (df["status"] == "ok").to_numpy()
    landed = df["landed_at"].to_numpy(dtype=float) if "landed_at" in df else np.zeros(len(df))
    landed = np.nan_to_num(landed, nan=0.0)
    pos = np.arange(len(df))
    order = np.lexsort((-pos, -landed, ~ok))  # the last key is the primary one
    ids = df["sample_id"].to_numpy(dtype=object)[order]
    _, first = np.unique(ids, return_index=True)  # unique() sorts the ids
    return order[first]


def _dedupe(df: pd.DataFrame) -> pd.DataFrame:
    return df.iloc[_dedupe_index(df)].reset_index(drop=True)


@_retrying
def read_table(path, columns: list[str] | None = None) -> pd.DataFrame:
    """All rows of a dataset, one per sample id (any status)."""
    files = _files(path)
    schemas = [_meta(f)[0] for f in files]
    if columns is not None:
        columns = list(dict.fromkeys(columns))
        bad = [c for c in columns if c not in COLUMNS]
        if bad:
            raise UserError("columns", f"unknown column(s) {', '.join(bad)}; known: {', '.join(COLUMNS)}")
    frames = []
    for f, s in zip(files, schemas):
        want = None
        if columns is not None:
            want = [c for c in dict.fromkeys([*_KEY_COLS, *columns]) if c in s.names]
        try:
            t = pq.read_table(f, columns=want)
            t.validate(full=True)  # e.g. invalid UTF-8 in a damaged string column
        except Exception as exc:
            if isinstance(exc, FileNotFoundError) or not f.exists():
                raise _Vanished(f) from None
            raise UserError("path", f"{f} cannot be read ({_first_line(exc)})") from None
        frames.append(t.to_pandas())
    frames = [f for f in frames if len(f)]
    if not frames:
        cols = columns if columns is not None else list(COLUMNS)
        return pd.DataFrame({c: pd.Series(dtype=object) for c in cols})
    df = _dedupe(pd.concat(frames, ignore_index=True))
    if columns is not None:
        for c in columns:
            if c not in df:
                df[c] = np.nan
        df = df[columns]
    return df


def read_samples(path, columns: list[str] | None = None, status: str | None = "ok") -> pd.DataFrame:
    """Rows of a dataset as a DataFrame, one per sample id, sorted by sample id.

    ``status='ok'`` (default) keeps the successful samples, ``'failed'`` the
    failures, ``None`` all.  ``columns`` selects columns (default all);
    ``image`` comes as a column of 1-D float32 arrays (see :func:`stack_images`).
    """
    if status not in ("ok", "failed", None):
        raise UserError("status", f"must be 'ok', 'failed' or None (got {status!r})")
    want = None if columns is None else list(dict.fromkeys([*columns, "status"]))
    df = read_table(path, want)
    if status is not None:
        df = df[df["status"] == status].reset_index(drop=True)
    if columns is not None:
        df = df[list(columns)]
    return df


def stack_images(df: pd.DataFrame, shape: tuple[int, int]) -> np.ndarray:
    """The ``image`` column as a float32 array ``(n, ny, nx)`` (NaN for rows without an image)."""
    ny, nx = shape
    out = np.full((len(df), ny, nx), np.nan, dtype=np.float32)
    for i, v in enumerate(df["image"]):
        if v is not None and len(v) == ny * nx:
            out[i] = np.asarray(v, dtype=np.float32).reshape(ny, nx)
    return out


def landed_status(path) -> dict[str, str]:
    """``{sample_id: status}`` of what a dataset directory holds (empty when nothing landed)."""
    files = _files(path, must_exist=False)
    if not files:
        return {}
    df = read_table(path, list(_KEY_COLS))
    return dict(zip(df["sample_id"], df["status"]))


# ----------------------------------------------------------------------------- writing


def to_table(rows: list[dict], image_shape=None, pixel=None) -> pa.Table:
    schema = arrow_schema(tuple(image_shape) if image_shape is not None else None, pixel)
    cols = {}
    for name in schema.names:
        vals = [r.get(name) for r in rows]
        if name in ("image", "image_raw"):
            vals = [None if v is None else np.asarray(v, dtype=np.float32).ravel() for v in vals]
        cols[name] = pa.array(vals, type=schema.field(name).type)
    return pa.Table.from_pydict(cols, schema=schema)


def write_atomic(table: pa.Table, dest: Path) -> Path:
    """Write ``table`` to ``dest`` via a hidden temporary file and ``os.replace`` (fsynced)."""
    dest = Path(dest)
    tmp = dest.with_name(f".{dest.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        pq.write_table(table, fh, compression="zstd")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, dest)
    return dest


def new_name(prefix: str) -> str:
    return f"{prefix}-{time.time_ns():020d}-{uuid.uuid4().hex[:8]}.parquet"


def land_rows(out_dir, rows: list[dict], image_shape=None, pixel=None, prefix: str = "r") -> Path:
    """Land ``rows`` as one new file in ``out_dir`` (atomically); stamps ``landed_at``."""
    now = time.time()
    for r in rows:
        r.setdefault("landed_at", now)
    return write_atomic(to_table(rows, image_shape, pixel), Path(out_dir) / new_name(prefix))


def remove_stale_tmp(out_dir, older_than: float = 0.0) -> int:
    """Remove temporary files left by killed writers; returns how many."""
    n = 0
    now = time.time()
    for f in Path(out_dir).glob(".*.tmp"):
        try:
            if now - f.stat().st_mtime >= older_than:
                f.unlink()
                n += 1
        except FileNotFoundError:
            pass
    return n


def compact(path, batch_rows: int = BATCH_ROWS, only_rows: bool = False) -> dict:
    """Merge the files of a dataset directory into batch files of at most ``batch_rows`` rows.

    Superseded duplicates are dropped.  New batch files are written (atomically)
    before the old files are removed, so a kill at any point loses nothing (at
    worst it leaves duplicates, which readers drop).  ``only_rows`` merges only
    single-row ``r-`` files (what the sweep does while running).
    Returns ``{"files_before", "files_after", "rows", "dropped"}``.
    """
    p = Path(path)
    if not p.is_dir():
        raise UserError("path", f"{p} is not a dataset directory")
    files = _files(p, must_exist=not only_rows)
    if only_rows:
        files = [f for f in files if f.name.startswith("r-")]
    if batch_rows < 1:
        raise UserError("batch_rows", f"must be >= 1 (got {batch_rows})")
    if not files:
        return {"files_before": 0, "files_after": 0, "rows": 0, "dropped": 0}
    infos = [_meta(f) for f in files]
    shape, pixel = _image_meta(infos, files)
    schema = arrow_schema(shape, pixel)
    tables = []
    for f in files:
        t = pq.read_table(f)
        for name in schema.names:  # optional columns added after the file was written
            if name not in t.column_names:
                t = t.append_column(name, pa.nulls(t.num_rows, schema.field(name).type))
        tables.append(t.select(schema.names).cast(schema))
    table = pa.concat_tables(tables)
    keep = _dedupe_index(table.select(list(_KEY_COLS)).to_pandas())
    table = table.take(pa.array(keep, type=pa.int64()))
    n_written = 0
    for start in range(0, table.num_rows, batch_rows):
        write_atomic(table.slice(start, batch_rows), p / new_name("b"))
        n_written += 1
    for f in files:
        try:
            f.unlink()
        except FileNotFoundError:
            pass
    total = sum(t.num_rows for t in tables)
    return {
        "files_before": len(files),
        "files_after": n_written,
        "rows": table.num_rows,
        "dropped": total - table.num_rows,
    }


def read_manifest(path) -> dict | None:
    f = Path(path) / MANIFEST
    if not f.exists():
        return None
    try:
        return json.loads(f.read_text())
    except ValueError:
        raise UserError("path", f"{f} is not valid JSON") from None


def sensor_record(path) -> dict:
    """``{"sensor": description, "sensor_hash": hash}`` of the sweep folder ``path`` ({} when it is
    not one).  A manifest written before sweeps recorded the sensor is the paper's sensor with the
    folder's solver settings (:func:`elastimap.solver.params.to_sensor` of its base parameters)."""
    from elastimap.sensor import Sensor
    from elastimap.solver.params import SolveParams, to_sensor

    man = read_manifest(path) if Path(path).is_dir() else None
    if man is None:
        return {}
    if man.get("sensor_hash"):
        return {"sensor": man["sensor"], "sensor_hash": man["sensor_hash"]}
    return to_sensor(SolveParams.from_dict(man.get("base_params", {})), Sensor()).record()


def write_manifest(path, manifest: dict) -> None:
    f = Path(path) / MANIFEST
    tmp = f.with_name(f".{f.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(manifest, indent=1, sort_keys=False))
    os.replace(tmp, f)


def acquire_lock(out, param: str = "--out") -> Path:
    """Take ``out/.sweep.lock`` (one writer per dataset directory: a sweep or a compaction).

    A lock left by a dead process on this host (kill -9) is taken over; a live holder, or one on
    another host, raises :class:`UserError`.  The caller removes the file when done.
    """
    import psutil

    from elastimap.provenance import host

    out = Path(out)
    lock = out / LOCK
    me = {"pid": os.getpid(), "host": host(), "created": psutil.Process().create_time()}
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                other = json.loads(lock.read_text() or "{}")
            except (OSError, ValueError):
                other = {}
            alive = False
            if not other:  # being written this instant, or garbage: trust it only while fresh
                try:
                    alive = time.time() - lock.stat().st_mtime < 10
                except FileNotFoundError:
                    continue
            elif other.get("host") == me["host"] and other.get("pid"):
                try:
                    alive = abs(psutil.Process(other["pid"]).create_time() - other.get("created", 0)) < 1.0
                except psutil.Error:
                    alive = False
            elif other.get("host"):
                alive = True  # another machine: cannot check, assume it is running
            if alive:
                raise UserError(
                    param,
                    f"{out} is being written by another sweep or compaction (pid {other.get('pid')} "
                    f"on {other.get('host')}); if that is wrong, remove {lock}",
                ) from None
            try:
                lock.unlink()
            except FileNotFoundError:
                pass
            continue
        try:
            with os.fdopen(fd, "w") as fh:
                json.dump(me, fh)
        except OSError as exc:  # a full disk: an empty lock would refuse the rerun the error asks for
            lock.unlink(missing_ok=True)
            raise UserError(param, f"cannot write the lock {lock}: {exc.strerror or exc}") from None
        return lock
    raise UserError(param, f"cannot take the lock {lock}")
