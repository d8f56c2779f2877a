"""The solve store: each forward solve kept once, found again by its inputs.

::

    store = SolveStore("data/solves")
    res = store.get(params)                  # SolveResult, or None when never solved
    store.put(params, res)
    res = store.solve(params, solve)         # get, or solve + put

**Key.** :func:`params_key` is the SHA-256 (hex) of :func:`canonical_json` of
``SolveParams.to_dict()``: keys sorted, no spaces, every number written as a float (so
``d=8`` and ``d=8.0`` are one key, and ``-0.0`` is ``0.0``).  ``to_dict`` leaves out effect
switches at their defaults, so the keys of existing solves stay the same when a switch is added.
The key depends on nothing but the solve inputs: it is the same in every process and on every
machine.

**Format.** A store is a folder of Parquet files in the sample-table format
(:mod:`elastimap.dataset.schema`), landed by :func:`elastimap.dataset.io.land_rows`: written under
a temporary name and ``os.replace``\\ d, so a file exists complete or not at all and a kill -9
loses at most the solve being written.  Several processes may put into one store at once.  A
sweep folder is a store too: its rows carry the key (rows of sweeps from before the key was
stored get it computed from ``params_json``).  Rows put here have ``sample_id = key``, tag
``solve``, and also the raw image (``image_raw``), which the sweep's rows leave out.  Images are
float32, as everywhere in the sample table.

**Lookup.** Only ``ok`` rows of the store's solver answer (column ``solver``; ``fem`` when
absent), so rows of the SYNTHETIC test stand-in never answer for the forward model.  Among
several rows of one key the newest wins; with ``need_raw=True`` only rows with ``image_raw``
count.  A reader looks at the folder again when a key is missing, so it sees other processes'
new solves (and its own puts at once).  Part files of the gap cache from before the store (``solves-*.parquet``) are not read.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from elastimap.errors import UserError
from elastimap.provenance import code_version, host
from elastimap.solver.params import SolveParams, SolveResult

from . import io

#: the ``solver`` label of the forward model's rows (also what a missing label means)
FEM = "fem"
#: the ``tag`` of rows put into a store (sweep rows keep their sample tags)
TAG = "solve"
_LEGACY = "solves-"  # the gap cache's part files before the store; not read
_RESULT_COLS = (
    "O1",
    "O2",
    "O3",
    "force",
    "force_ref",
    "delta",
    "image",
    "image_raw",
    "ndofs",
    "newton_iterations",
    "seconds",
    "peak_memory_mb",
)
_VANISH_RETRIES = 10


# ----------------------------------------------------------------------------- key


def _canon(v):
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, (int, float, np.integer, np.floating)):
        return float(v) + 0.0  # + 0.0 turns -0.0 into 0.0
    if isinstance(v, dict):
        return {str(k): _canon(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_canon(x) for x in v]
    raise TypeError(f"cannot key a solve parameter of type {type(v).__name__}: {v!r}")


def canonical_json(params: SolveParams) -> str:
    """``params.to_dict()`` as canonical JSON (sorted keys, no spaces, numbers as floats)."""
    return json.dumps(_canon(params.to_dict()), sort_keys=True, separators=(",", ":"), allow_nan=False)


def params_key(params: SolveParams) -> str:
    """The solve key: SHA-256 (64 hex digits) of :func:`canonical_json`."""
    return hashlib.sha256(canonical_json(params).encode()).hexdigest()


def solver_label(solve: Callable | None) -> str:
    """The ``solver`` label of what ``solve`` produces: its ``solver_name`` attribute (the test
    stand-in has ``'synthetic'``), else ``'fem'``; ``None`` means the forward model."""
    return FEM if solve is None else str(getattr(solve, "solver_name", FEM))


# ----------------------------------------------------------------------------- rows


def result_row(params: SolveParams, res: SolveResult, *, solver: str = FEM, raw: bool = True) -> dict:
    """The sample-table row of one solve (``sample_id = key``, tag ``solve``); status ``failed``
    when a feature, a force or the image is not finite.  ``raw``: keep ``image_raw`` too."""
    key = params_key(params)
    inc = params.inclusion
    img = np.asarray(res.image, dtype=np.float32)
    img_raw = None
    if raw and getattr(res, "image_raw", None) is not None:
        img_raw = np.asarray(res.image_raw, dtype=np.float32).ravel()
    peak = getattr(res, "peak_memory_mb", None)
    row = {
        "sample_id": key,
        "tag": TAG,
        "d": float(inc.d),
        "h": float(inc.h),
        "E": float(inc.E),
        "O1": float(res.O1),
        "O2": float(res.O2),
        "O3": float(res.O3),
        "force": float(res.force),
        "force_ref": float(res.force_ref),
        "delta": float(res.delta),
        "image": img.ravel(),
        "image_raw": img_raw,
        "params_json": json.dumps(params.to_dict(), sort_keys=True),
        "key": key,
        "solver": solver,
        "status": "ok",
        "error": "",
        "ndofs": int(res.ndofs),
        "newton_iterations": int(res.newton_iterations),
        "seconds": float(res.seconds),
        "peak_memory_mb": float(peak) if peak is not None else None,
        "code_version": code_version(),
        "host": host(),
    }
    bad = [k for k in ("O1", "O2", "O3", "force", "force_ref") if not math.isfinite(row[k])]
    if bad or not np.all(np.isfinite(img)):
        row.update(status="failed", error=f"non-finite result ({', '.join(bad) or 'image'})")
    return row


def image_shape(params: SolveParams) -> tuple[int, int]:
    """Shape ``(ny, nx)`` of the elasticity image of a solve (the full probe footprint)."""
    n = int(round(params.probe.size / params.image.pixel))
    return (n, n)


def _num(v, default=math.nan) -> float:
    return default if v is None else float(v)


def result_from_row(params: SolveParams, row: dict, shape=None, pixel=None) -> SolveResult:
    """A :class:`SolveResult` from a stored row (``ncells``, ``timings`` and the interface
    diagnostics are not stored: 0 and empty; ``image_raw`` is None when the row has none)."""
    shape = tuple(shape) if shape else image_shape(params)
    img = np.asarray(row["image"], dtype=np.float32).reshape(shape)
    raw = row.get("image_raw")
    raw = None if raw is None else np.asarray(raw, dtype=np.float32).reshape(shape)
    delta = _num(row.get("delta"))
    if not math.isfinite(delta):
        delta = params.loading.delta
    return SolveResult(
        params=params,
        O1=_num(row["O1"]),
        O2=_num(row["O2"]),
        O3=_num(row["O3"]),
        force=_num(row["force"]),
        force_ref=_num(row["force_ref"]),
        delta=delta,
        image=img,
        image_raw=raw,
        pixel=float(pixel) if pixel else params.image.pixel,
        ndofs=int(_num(row.get("ndofs"), 0)),
        ncells=0,
        newton_iterations=int(_num(row.get("newton_iterations"), 0)),
        seconds=_num(row.get("seconds")),
        timings={},
        peak_memory_mb=_num(row.get("peak_memory_mb")),
    )


# ----------------------------------------------------------------------------- the store


class SolveStore:
    """Forward solves in a folder, keyed by :func:`params_key` (see the module docstring).

    ``solver`` is the label of the rows this store serves and writes (``'fem'`` or the
    stand-in's ``'synthetic'``).  The folder is created by the first :meth:`put`.
    """

    def __init__(self, path: str | Path, solver: str = FEM):
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise UserError("path", f"{self.path} is not a folder (a solve store is a folder of Parquet files)")
        self.solver = solver
        self._geometry: dict[str, tuple] = {}  # file name -> (shape, pixel)
        self._index: dict[str, list[tuple[float, bool, str, int]]] = {}  # key -> [(landed_at, has_raw, file, row)]
        self._tmp_cleaned = False

    # -- index
    def _files(self) -> list[Path]:
        if not self.path.is_dir():
            return []
        return sorted(f for f in self.path.glob("*.parquet") if not f.name.startswith((".", _LEGACY)))

    def refresh(self) -> None:
        """Pick up files landed (or compacted away) since the last look."""
        for _ in range(_VANISH_RETRIES):
            files = self._files()
            names = {f.name for f in files}
            gone = [n for n in self._geometry if n not in names]
            if gone:
                for n in gone:
                    del self._geometry[n]
                gone_set = set(gone)
                self._index = {
                    k: kept for k, v in self._index.items() if (kept := [e for e in v if e[2] not in gone_set])
                }
            try:
                for f in files:
                    if f.name not in self._geometry:
                        self._scan(f)
                return
            except (FileNotFoundError, io._Vanished):
                continue  # a compaction replaced it: its rows are in a newer file, list again
        raise UserError("path", f"files in {self.path} keep disappearing while reading; is something deleting them?")

    def _scan(self, f: Path) -> None:
        schema, _, img = io._meta(f)
        names = schema.names
        cols = [c for c in ("key", "solver", "status", "landed_at") if c in names]
        t = pq.read_table(f, columns=cols)
        n = t.num_rows
        keys = t.column("key").to_pylist() if "key" in names else [None] * n
        if any(k is None for k in keys):  # rows landed before the key was stored
            pj = pq.read_table(f, columns=["params_json"]).column(0).to_pylist()
            keys = [k if k is not None else params_key(SolveParams.from_dict(json.loads(j))) for k, j in zip(keys, pj)]
        solver = t.column("solver").to_pylist() if "solver" in names else [None] * n
        status = t.column("status").to_pylist()
        landed = t.column("landed_at").to_pylist() if "landed_at" in names else [None] * n
        if "image_raw" in names:
            has_raw = [not x for x in pq.read_table(f, columns=["image_raw"]).column(0).is_null().to_pylist()]
        else:
            has_raw = [False] * n
        for i in range(n):
            if status[i] == "ok" and (solver[i] or FEM) == self.solver:
                self._index.setdefault(keys[i], []).append((landed[i] or 0.0, bool(has_raw[i]), f.name, i))
        shape = tuple(int(x) for x in img["shape"]) if img and img.get("shape") else None
        self._geometry[f.name] = (shape, img.get("pixel_mm") if img else None)

    def _pick(self, key: str, need_raw: bool):
        cands = [e for e in self._index.get(key, ()) if e[1] or not need_raw]
        return max(cands) if cands else None

    # -- reading
    def get(self, params: SolveParams, *, need_raw: bool = False) -> SolveResult | None:
        """The stored result of ``params``, or None (``need_raw``: only a row with ``image_raw``)."""
        return self.get_many([params], need_raw=need_raw)[0]

    def get_many(self, plist: Iterable[SolveParams], *, need_raw: bool = False) -> list[SolveResult | None]:
        """:meth:`get` for many params at once (each file read once)."""
        plist = list(plist)
        keys = [params_key(p) for p in plist]
        if any(self._pick(k, need_raw) is None for k in keys):
            self.refresh()
        for _ in range(_VANISH_RETRIES):
            out: list[SolveResult | None] = [None] * len(plist)
            by_file: dict[str, list[tuple[int, int]]] = {}
            for i, k in enumerate(keys):
                e = self._pick(k, need_raw)
                if e is not None:
                    by_file.setdefault(e[2], []).append((i, e[3]))
            try:
                for name, wanted in by_file.items():
                    f = self.path / name
                    cols = [c for c in _RESULT_COLS if c in pq.read_schema(f).names]
                    rows = pq.read_table(f, columns=cols).take([r for _, r in wanted]).to_pylist()
                    shape, pixel = self._geometry[name]
                    for (i, _), row in zip(wanted, rows):
                        out[i] = result_from_row(plist[i], row, shape, pixel)
                return out
            except (FileNotFoundError, OSError):
                if all((self.path / n).exists() for n in by_file):
                    raise
                self.refresh()  # compacted away meanwhile: look again
        raise UserError("path", f"files in {self.path} keep disappearing while reading; is something deleting them?")

    def __contains__(self, params: SolveParams) -> bool:
        key = params_key(params)
        if self._pick(key, False) is None:
            self.refresh()
        return self._pick(key, False) is not None

    def keys(self) -> set[str]:
        """The keys of every result this store serves."""
        self.refresh()
        return set(self._index)

    def __len__(self) -> int:
        return len(self.keys())

    # -- writing
    def put(self, params: SolveParams, result: SolveResult) -> str:
        """Land one result (atomically); returns its key."""
        return self.put_many([(params, result)])[0]

    def put_many(self, pairs: Iterable[tuple[SolveParams, SolveResult]]) -> list[str]:
        """Land several results, one file per image geometry; returns their keys."""
        groups: dict[tuple, list[dict]] = {}
        keys = []
        for p, res in pairs:
            row = result_row(p, res, solver=self.solver)
            keys.append(row["key"])
            groups.setdefault((tuple(np.shape(res.image)), float(res.pixel)), []).append(row)
        if not groups:
            return keys
        self.path.mkdir(parents=True, exist_ok=True)
        if not self._tmp_cleaned:  # temporary files of writers killed long ago
            io.remove_stale_tmp(self.path, older_than=3600.0)
            self._tmp_cleaned = True
        for (shape, pixel), rows in groups.items():
            f = io.land_rows(self.path, rows, shape, pixel)
            try:
                if f.name not in self._geometry:
                    self._scan(f)  # this reader sees its own puts at once
            except (FileNotFoundError, io._Vanished):
                pass  # already compacted away: the next refresh finds its rows
        return keys

    def solve(
        self, params: SolveParams, solve: Callable[[SolveParams], SolveResult] | None = None, *, need_raw: bool = True
    ) -> SolveResult:
        """The stored result of ``params``, or ``solve(params)`` (the forward model when None) put
        into the store first and returned as stored (images float32)."""
        hit = self.get(params, need_raw=need_raw)
        if hit is not None:
            return hit
        if solve is None:
            from elastimap.solver import solve
        res = solve(params)
        self.put(params, res)
        return self.get(params, need_raw=need_raw) or res
