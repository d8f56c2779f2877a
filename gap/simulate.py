"""Forward solves for the gap work, cached on disk, and the camera features they give.

``Simulator(cache_dir, mesh, backend)`` turns a list of :class:`elastimap.solver.params.SolveParams`
into solve records (features, difference image, raw image), solving only what the cache lacks.
The cache is a folder of Parquet part files (one row per solve, keyed by the SHA-1 of the
solve parameters and the backend), so a selftest or a second diagnosis of the same phantoms
reuses every earlier solve.  ``jobs > 1`` fans the missing solves out to worker processes.

Backends: ``"fem"`` (the DOLFINx forward model, :func:`solver.solve`) and ``"toy"`` (an
analytic TOY stand-in that reacts to every effect switch, for fast tests of the gap logic only:
it is *not* physics).

Camera features of a record (:func:`camera_features_of`) are those of the noise-free,
unquantised frames of the SYNTHETIC camera model: lesion press and background press
(``image_raw - image``), exactly as :mod:`elastimap.camera.features` computes them from real frames.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from elastimap.errors import UserError
from elastimap.solver.image import features as image_features
from elastimap.solver.image import pixel_centres
from elastimap.solver.params import Discretisation, SolveParams

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
    image: np.ndarray       # difference image (mm)
    image_raw: np.ndarray   # raw probe compression (mm)
    seconds: float

    @property
    def fem(self) -> np.ndarray:
        return np.array([self.O1, self.O2, self.O3])


def params_key(p: SolveParams, backend: str) -> str:
    blob = json.dumps({"backend": backend, "params": p.to_dict()}, sort_keys=True, default=float)
    return hashlib.sha1(blob.encode()).hexdigest()


def base_params(mesh: str, d: float, h: float, E: float, tissue_E: float | None = None) -> SolveParams:
    p = SolveParams(disc=Discretisation(mesh=mesh)).with_inclusion(d=float(d), h=float(h), E=float(E))
    if tissue_E is not None and np.isfinite(tissue_E) and tissue_E != p.tissue.E:
        p = p.replace(tissue=__import__("dataclasses").replace(p.tissue, E=float(tissue_E)))
    return p


# ------------------------------------------------------------------ backends
def toy_solve(p: SolveParams) -> dict:
    """TOY analytic forward model reacting to the effect switches (tests only, not physics)."""
    inc, t, probe = p.inclusion, p.tissue, p.probe
    pixel, size = p.image.pixel, probe.size
    x = pixel_centres(size, pixel)
    X, Y = np.meshgrid(x, x)
    a = size / 2
    kprobe = probe.layers[0][1] / 300.0
    edge = np.exp(-(a - np.abs(X))) + np.exp(-(a - np.abs(Y)))
    base = 0.08 * (p.loading.delta / 3.0) * (1.0 + 0.8 * edge) * (1 - 0.2 * (X ** 2 + Y ** 2) / (2 * a * a)) / kprobe ** 0.5
    beta, kt = t.nonlinearity, p.disc.friction_kt
    fk = kt / (kt + 0.3)
    skin = np.log(t.skin_E / t.E) if t.skin_thickness > 0 else 0.0
    amp = (0.03 * (p.loading.delta / 3.0) * (inc.d / 8.0) ** 2.2 * (8.0 / inc.h) ** 1.6
           * (max(inc.E - t.E, 0.0) / 45.0) ** 0.6)
    amp *= (1 + 0.5 * beta * inc.d / 8.0) * (1 + 0.06 * fk) * np.exp(-0.12 * skin * 8.0 / inc.h)
    amp *= inc.aspect ** 0.9 * kprobe ** -0.35
    width = 0.35 * inc.d * (1.0 - 0.2 * np.log(inc.E / 50.0)) + 0.25 * inc.h
    width *= (1 - 0.04 * beta) * (1 + 0.2 * fk) * (1 + 0.1 * skin) * inc.aspect ** 0.25 * kprobe ** 0.3
    prof = (1.0 + 0.12 * inc.h) * (1 + 0.1 * fk)
    R = np.sqrt((X - inc.offset_x) ** 2 + (Y - inc.offset_y) ** 2)
    diff = amp * np.exp(-(R / width) ** prof)
    o1, o2, o3 = image_features(diff, pixel, p.image.threshold, p.image.supersample)
    force = 1400.0 * (t.E / 5.0) ** 0.5 * (1 + 0.2 * beta) * (1 + 0.1 * fk)
    return dict(O1=o1, O2=o2, O3=o3, force=force, pixel=pixel, image=diff.astype(np.float32),
                image_raw=(base + diff).astype(np.float32))


def fem_solve(p: SolveParams) -> dict:
    from elastimap.solver import solve

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        r = solve(p)
    return dict(O1=r.O1, O2=r.O2, O3=r.O3, force=r.force, pixel=r.pixel, image=r.image, image_raw=r.image_raw)


def _solve_one(args) -> tuple[str, dict, float]:
    key, pdict, backend = args
    p = SolveParams.from_dict(pdict)
    t0 = time.perf_counter()
    try:
        out = toy_solve(p) if backend == "toy" else fem_solve(p)
    except RuntimeError as exc:  # SolverError / MeshError: a NaN record, not cached
        nan = np.full((2, 2), np.nan, np.float32)
        out = dict(O1=np.nan, O2=np.nan, O3=np.nan, force=np.nan, pixel=p.image.pixel, image=nan, image_raw=nan,
                   error=str(exc))
    return key, out, time.perf_counter() - t0


# ------------------------------------------------------------------ the cache
class Simulator:
    """Cached forward solves.  ``stats`` counts solves run and cache hits."""

    def __init__(self, cache_dir: str | os.PathLike | None, mesh: str = "coarse", backend: str = "fem",
                 jobs: int = 1, progress=None):
        if backend not in BACKENDS:
            raise UserError("backend", f"must be one of {', '.join(BACKENDS)} (got {backend!r})")
        if mesh not in ("tiny", "coarse", "default", "fine"):
            raise UserError("mesh", f"must be tiny, coarse, default or fine (got {mesh!r})")
        self.mesh, self.backend, self.jobs = mesh, backend, max(1, int(jobs))
        self.dir = Path(cache_dir) if cache_dir else None
        self.mem: dict[str, Record] = {}
        self.stats = {"solved": 0, "hits": 0, "solve_seconds": 0.0}
        self.progress = progress
        if self.dir is not None:
            self.dir.mkdir(parents=True, exist_ok=True)
            self._load()

    def _load(self) -> None:
        import pyarrow.parquet as pq

        for f in sorted(self.dir.glob("solves-*.parquet")):
            try:
                t = pq.read_table(f).to_pylist()
            except Exception:  # a half-written part from a killed run: ignore it
                continue
            for r in t:
                shape = tuple(r["shape"])
                self.mem[r["key"]] = Record(
                    r["key"], r["O1"], r["O2"], r["O3"], r["force"], r["pixel"],
                    np.frombuffer(r["image"], np.float32).reshape(shape),
                    np.frombuffer(r["image_raw"], np.float32).reshape(shape), r["seconds"])

    def _flush(self, recs: list[tuple[Record, str]]) -> None:
        if self.dir is None or not recs:
            return
        import pyarrow as pa
        import pyarrow.parquet as pq

        rows = [{"key": r.key, "params_json": pj, "backend": self.backend, "O1": r.O1, "O2": r.O2, "O3": r.O3,
                 "force": r.force, "pixel": r.pixel, "shape": list(r.image.shape),
                 "image": np.asarray(r.image, np.float32).tobytes(),
                 "image_raw": np.asarray(r.image_raw, np.float32).tobytes(), "seconds": r.seconds}
                for r, pj in recs]
        tmp = self.dir / f".tmp-{uuid.uuid4().hex}.parquet"
        pq.write_table(pa.Table.from_pylist(rows), tmp)
        os.replace(tmp, self.dir / f"solves-{time.time_ns()}-{uuid.uuid4().hex[:8]}.parquet")

    def run(self, plist: list[SolveParams]) -> list[Record]:
        """Records for every params in ``plist`` (same order), solving the missing ones."""
        keys = [params_key(p, self.backend) for p in plist]
        todo: dict[str, SolveParams] = {}
        for k, p in zip(keys, plist):
            if k in self.mem:
                self.stats["hits"] += 1
            elif k not in todo:
                todo[k] = p.validate()
        if todo:
            args = [(k, p.to_dict(), self.backend) for k, p in todo.items()]
            pending: list[tuple[Record, str]] = []
            done = [0]

            def land(key, out, sec):
                rec = Record(key, float(out["O1"]), float(out["O2"]), float(out["O3"]), float(out["force"]),
                             float(out["pixel"]), np.asarray(out["image"], np.float32),
                             np.asarray(out["image_raw"], np.float32), float(sec))
                self.mem[key] = rec
                if "error" in out:
                    self.stats.setdefault("failed", []).append(out["error"][:200])
                else:
                    pending.append((rec, json.dumps(todo[key].to_dict(), sort_keys=True)))
                self.stats["solved"] += 1
                self.stats["solve_seconds"] += sec
                done[0] += 1
                if self.progress:
                    self.progress(done[0], len(args))
                if len(pending) >= FLUSH_ROWS:
                    self._flush(pending)
                    pending.clear()

            try:
                if self.jobs > 1 and self.backend == "fem" and len(args) > 1:
                    import multiprocessing as mp
                    from concurrent.futures import ProcessPoolExecutor, as_completed

                    with ProcessPoolExecutor(self.jobs, mp_context=mp.get_context("spawn")) as ex:
                        futs = [ex.submit(_solve_one, a) for a in args]
                        for f in as_completed(futs):
                            land(*f.result())
                else:
                    for a in args:
                        land(*_solve_one(a))
            finally:
                self._flush(pending)
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
    key = (rec.key, json.dumps(sensor.to_dict(), sort_keys=True),
           json.dumps(settings.to_dict() if settings is not None else None, sort_keys=True))
    hit = _CAM_MEMO.get(key)
    if hit is None:
        hit = _camera_features(rec, sensor, settings)
        if len(_CAM_MEMO) >= _CAM_MEMO_MAX:
            _CAM_MEMO.clear()
        _CAM_MEMO[key] = hit
    return hit[0].copy(), hit[1]


def _camera_features(rec: Record, sensor, settings=None) -> tuple[np.ndarray, np.ndarray]:
    from elastimap.camera.features import camera_features
    from elastimap.camera.optics import background_deflection

    F = sensor.expected(rec.image_raw, rec.pixel)
    B = sensor.expected(background_deflection(rec.image_raw, rec.image), rec.pixel)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cf = camera_features(F[None], B[None], sensor.full_scale, sensor.window, sensor.pixel_mm, settings)
    return cf.values, cf.difference


def measure(rec: Record, sensor, settings, frames: int, rng: np.random.Generator):
    """Noisy SYNTHETIC measurement: ``frames`` lesion and background frames through the camera
    model; returns (features (3,), standard error (3,), difference image)."""
    from elastimap.camera.features import camera_features
    from elastimap.camera.optics import render_pair

    L, B = render_pair(sensor, rec.image_raw, rec.image, rec.pixel, frames, rng)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cf = camera_features(L, B, sensor.full_scale, sensor.window, sensor.pixel_mm, settings)
    se = np.asarray(cf.frame_sd) / np.sqrt(max(frames, 1))
    return cf.values, se, cf.difference
