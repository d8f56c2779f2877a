"""Forward solves for the gap work, kept in the solve store, and the camera features they give.

``Simulator(cache_dir, mesh, backend)`` turns a list of :class:`elastimap.solver.params.SolveParams`
into solve records (features, difference image, raw image), solving only what it lacks.  Solves
are kept in a :class:`elastimap.dataset.store.SolveStore` in ``cache_dir`` (keyed by the solve
parameters), so a selftest or a second diagnosis of the same phantoms reuses every earlier solve.
``jobs > 1`` fans the missing FEM solves out to worker processes.

Backends: ``"fem"`` (the DOLFINx forward model, :func:`elastimap.solver.solve`) and ``"toy"`` (the
SYNTHETIC analytic stand-in :data:`elastimap.solver.synthetic.solve`, which reacts to every effect
switch, for fast tests of the gap logic only: it is *not* physics).  Its solves are labelled
``synthetic`` in the store and never answer for the FEM.  ``solver=`` passes another solve
function explicitly.

Camera features of a record (:func:`camera_features_of`) are those of the noise-free,
unquantised frames of the SYNTHETIC camera model: lesion press and background press
(``image_raw - image``), exactly as :mod:`elastimap.camera.features` computes them from real frames.
"""

from __future__ import annotations

import atexit
import dataclasses
import json
import multiprocessing as mp
import os
import time
import warnings
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass

import numpy as np

from elastimap.camera.features import camera_features
from elastimap.camera.optics import background_deflection, render_pair
from elastimap.dataset.store import SolveStore, params_key, solver_label
from elastimap.errors import UserError
from elastimap.sensor import Sensor
from elastimap.solver import synthetic
from elastimap.solver.batch import group_by_geometry, solve_group
from elastimap.solver.params import Discretisation, Inclusion, SolveParams, SolveResult, from_sensor

BACKENDS = ("fem", "toy")
FLUSH_ROWS = 16


@dataclass
class Record:
    key: str
    O1: float
    O2: float
    O3: float
    force: float
    pixel: float
    image: np.ndarray  # difference image (mm)
    image_raw: np.ndarray  # raw probe compression (mm)
    seconds: float

    @property
    def fem(self) -> np.ndarray:
        return np.array([self.O1, self.O2, self.O3])


def base_params(
    mesh: str, d: float, h: float, E: float, tissue_E: float | None = None, sensor: Sensor | None = None
) -> SolveParams:
    """Solve parameters of one phantom (d mm, h mm, E kPa; ``tissue_E`` kPa when not the slab's)
    pressed by ``sensor`` (the sensor description; None: the paper's) on the ``mesh`` level."""
    sensor = sensor or Sensor()
    lesion = Inclusion(d=float(d), h=float(h), E=float(E), nu=sensor.tissue.nu)
    p = from_sensor(sensor, lesion, Discretisation(mesh=mesh))
    if tissue_E is not None and np.isfinite(tissue_E) and tissue_E != p.tissue.E:
        p = p.replace(tissue=dataclasses.replace(p.tissue, E=float(tissue_E)))
    return p


# ------------------------------------------------------------------ backends
def fem_solve(p: SolveParams) -> SolveResult:
    """:func:`elastimap.solver.solve` with its RuntimeWarnings silenced."""
    # DOLFINx and gmsh load only in a process that solves with the FEM backend (seconds)
    from elastimap.solver import solve

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return solve(p)


def _solve_one(args) -> tuple[str, SolveResult | None, str, float]:
    key, pdict, solve = args
    p = SolveParams.from_dict(pdict)
    t0 = time.perf_counter()
    try:
        return key, solve(p), "", time.perf_counter() - t0
    except RuntimeError as exc:  # SolverError / MeshError: a NaN record, not stored
        return key, None, str(exc), time.perf_counter() - t0


def _solve_group(args) -> list[tuple[str, SolveResult | None, str, float]]:
    """One geometry's samples on one mesh and model (:func:`elastimap.solver.batch.solve_group`)."""
    keys, pdicts = args
    ps = [SolveParams.from_dict(d) for d in pdicts]
    out = []
    t = [time.perf_counter()]

    def land(i, r):
        now = time.perf_counter()
        sec, t[0] = now - t[0], now
        if isinstance(r, Exception):
            out.append((keys[i], None, str(r), sec))
        else:
            out.append((keys[i], r, "", sec))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        solve_group(ps, land, errors="return")
    return out


def _record(key: str, res: SolveResult, seconds: float) -> Record:
    return Record(
        key,
        float(res.O1),
        float(res.O2),
        float(res.O3),
        float(res.force),
        float(res.pixel),
        np.asarray(res.image, np.float32),
        np.asarray(res.image_raw, np.float32),
        float(seconds),
    )


# ------------------------------------------------------------------ the cache
class Simulator:
    """Stored forward solves.  ``stats`` counts solves run and store hits.  ``solver``: a solve
    function ``SolveParams -> SolveResult`` used instead of the backend's."""

    def __init__(
        self,
        cache_dir: str | os.PathLike | None,
        mesh: str = "coarse",
        backend: str = "fem",
        jobs: int = 1,
        progress=None,
        solver: Callable[[SolveParams], SolveResult] | None = None,
    ):
        if backend not in BACKENDS:
            raise UserError("backend", f"must be one of {', '.join(BACKENDS)} (got {backend!r})")
        if mesh not in ("tiny", "coarse", "default", "fine"):
            raise UserError("mesh", f"must be tiny, coarse, default or fine (got {mesh!r})")
        self.mesh, self.backend, self.jobs = mesh, backend, max(1, int(jobs))
        self.solve = solver or (synthetic.solve if backend == "toy" else fem_solve)
        # FEM samples that share a geometry run on one mesh and model (solver.batch)
        self.batched = solver is None and backend == "fem"
        self.label = solver_label(self.solve)
        self.store = SolveStore(cache_dir, solver=self.label) if cache_dir else None
        self.dir = self.store.path if self.store is not None else None
        self.mem: dict[str, Record] = {}
        self.stats = {"solved": 0, "hits": 0, "solve_seconds": 0.0}
        self.progress = progress

    def pool(self):
        """The worker processes (started once, kept for the simulator's life: each start costs
        the imports of DOLFINx in every worker)."""
        if getattr(self, "_pool", None) is None:
            self._pool = ProcessPoolExecutor(self.jobs, mp_context=mp.get_context("spawn"))
            atexit.register(self.close)
        return self._pool

    def close(self) -> None:
        """Stop the worker processes (a later ``run`` starts new ones)."""
        if getattr(self, "_pool", None) is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None

    def run(self, plist: list[SolveParams]) -> list[Record]:
        """Records for every params in ``plist`` (same order), solving the missing ones."""
        keys = [params_key(p) for p in plist]
        todo: dict[str, SolveParams] = {}
        for k, p in zip(keys, plist):
            if k not in self.mem and k not in todo:
                todo[k] = p.validate()
        if todo and self.store is not None:
            for (k, _), res in zip(list(todo.items()), self.store.get_many(todo.values(), need_raw=True)):
                if res is not None:
                    self.mem[k] = _record(f"{self.label}:{k}", res, res.seconds)
                    del todo[k]
        self.stats["hits"] += sum(1 for k in keys if k not in todo)
        if todo:
            args = [(k, p.to_dict(), self.solve) for k, p in todo.items()]
            pending: list[tuple[SolveParams, SolveResult]] = []
            done = [0]

            def flush():
                if self.store is not None and pending:
                    self.store.put_many(pending)
                pending.clear()

            def land(key, res, error, sec):
                if res is None:
                    nan = np.full((2, 2), np.nan, np.float32)
                    rec = Record(
                        f"{self.label}:{key}",
                        np.nan,
                        np.nan,
                        np.nan,
                        np.nan,
                        todo[key].image.pixel,
                        nan,
                        nan,
                        float(sec),
                    )
                    self.stats.setdefault("failed", []).append(error[:200])
                else:
                    rec = _record(f"{self.label}:{key}", res, sec)
                    pending.append((todo[key], res))
                self.mem[key] = rec
                self.stats["solved"] += 1
                self.stats["solve_seconds"] += sec
                done[0] += 1
                if self.progress:
                    self.progress(done[0], len(args))
                if len(pending) >= FLUSH_ROWS:
                    flush()

            try:
                if self.batched:
                    items = list(todo.items())
                    groups = group_by_geometry([p for _, p in items])
                    groups.sort(key=len, reverse=True)  # largest first: better balance over workers
                    gargs = [([items[i][0] for i in g], [items[i][1].to_dict() for i in g]) for g in groups]
                    self.stats["geometries"] = self.stats.get("geometries", 0) + len(groups)
                    if self.jobs > 1 and len(gargs) > 1:
                        futs = [self.pool().submit(_solve_group, a) for a in gargs]
                        for f in as_completed(futs):
                            for r in f.result():
                                land(*r)
                    else:
                        for a in gargs:
                            for r in _solve_group(a):
                                land(*r)
                elif self.jobs > 1 and self.label == "fem" and len(args) > 1:
                    with ProcessPoolExecutor(self.jobs, mp_context=mp.get_context("spawn")) as ex:
                        futs = [ex.submit(_solve_one, a) for a in args]
                        for f in as_completed(futs):
                            land(*f.result())
                else:
                    for a in args:
                        land(*_solve_one(a))
            finally:
                flush()
        return [self.mem[k] for k in keys]


# ------------------------------------------------------------------ camera side
_CAM_MEMO: dict = {}
_CAM_MEMO_MAX = 20000


def camera_features_of(rec: Record, sensor, settings=None) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free SYNTHETIC camera features (O1 FS, O2 FS mm², O3 mm²) and the denoised
    difference image (FS, footprint window) of one solve record (memoised per record and
    camera model: a selftest reuses the same sweep records in every trial)."""
    if not np.isfinite(rec.O1):
        return np.full(3, np.nan), np.full((sensor.window[2],) * 2, np.nan)
    key = (
        rec.key,
        json.dumps(sensor.to_dict(), sort_keys=True),
        json.dumps(settings.to_dict() if settings is not None else None, sort_keys=True),
    )
    hit = _CAM_MEMO.get(key)
    if hit is None:
        hit = _camera_features(rec, sensor, settings)
        if len(_CAM_MEMO) >= _CAM_MEMO_MAX:
            _CAM_MEMO.clear()
        _CAM_MEMO[key] = hit
    return hit[0].copy(), hit[1]


def _camera_features(rec: Record, sensor, settings=None) -> tuple[np.ndarray, np.ndarray]:
    F = sensor.expected(rec.image_raw, rec.pixel)
    B = sensor.expected(background_deflection(rec.image_raw, rec.image), rec.pixel)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cf = camera_features(F[None], B[None], sensor.full_scale, sensor.window, sensor.pixel_mm, settings)
    return cf.values, cf.difference


def measure(rec: Record, sensor, settings, frames: int, rng: np.random.Generator):
    """Noisy SYNTHETIC measurement: ``frames`` lesion and background frames through the camera
    model; returns (features (3,), standard error (3,), difference image)."""
    L, B = render_pair(sensor, rec.image_raw, rec.image, rec.pixel, frames, rng)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cf = camera_features(L, B, sensor.full_scale, sensor.window, sensor.pixel_mm, settings)
    se = np.asarray(cf.frame_sd) / np.sqrt(max(frames, 1))
    return cf.values, se, cf.difference
