"""The measured-data format: phantoms with known (d, h, E) and their camera features or frames.

A measured dataset is a folder (or the path of its table) holding

* ``measured.csv`` or ``measured.parquet`` -- one row per phantom inclusion:

  | column | unit | required | meaning |
  |---|---|---|---|
  | ``id`` | | yes | unique name of the inclusion |
  | ``d``, ``h``, ``E`` | mm, mm, kPa | yes | known diameter, centre depth, modulus |
  | ``O1``, ``O2``, ``O3`` | FS, FS mm², mm² | yes, unless ``images``/``background`` | camera features (:mod:`elastimap.camera.features`) |
  | ``O1_se``, ``O2_se``, ``O3_se`` | same | no | standard error of each feature from repeated frames (the noise floor) |
  | ``n_frames`` | | no | frames averaged |
  | ``images``, ``background`` | | no | lesion / background frame files or globs, ``;``-separated, relative to the folder; features, their standard errors, the difference image and its per-pixel standard error are then computed here |
  | ``difference`` | | no | ``.npy`` file: the denoised camera difference image over the footprint window (FS), for the residual map and the radial profile |
  | ``difference_se`` | | no | ``.npy`` file: per-pixel standard error of that image (FS), from the frame scatter (:mod:`elastimap.gap.views`) |
  | ``force``, ``force_se`` | mN | no | measured plate force and its standard error |
  | ``tissue_E`` | kPa | no | background modulus if not the nominal 5 kPa |

* ``measured.json`` (optional sidecar): ``{"kind": "elastimap.gap.measured", "version": 1,
  "synthetic": bool, "sensor": {...SensorModel...}, "feature_settings": {...}, "mesh": "coarse",
  "description": "..."}``.  ``sensor`` and ``feature_settings`` describe the camera model the
  simulations go through (defaults: the nominal synthetic camera and feature settings); ``mesh``
  the forward-model mesh level the comparison uses.  ``sensor_description`` (optional, with
  ``sensor_hash``): the whole sensor the phantoms were pressed with (:mod:`elastimap.sensor`;
  probe, slab, loading, interface, camera), which the simulations then use; ``gap diagnose
  --sensor`` gives it instead.

A SYNTHETIC dataset (``gap synth``) says so in the sidecar (``"synthetic": true``), in its file
names (``synthetic_*.npy``) and in its description; its true effect is kept in a separate sealed
file (``SEALED_truth.json``) that the diagnosis never opens.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from elastimap.camera.features import FeatureSettings
from elastimap.camera.frames import expand, read_stack
from elastimap.camera.optics import SensorModel
from elastimap.dataset.schema import FEATURES
from elastimap.errors import UserError
from elastimap.sensor import Sensor
from elastimap.tables import check_name, read_csv

from .views import from_frames as views_from_frames
from .views import profile_se, radial_profile

KIND = "elastimap.gap.measured"
VERSION = 1
TABLE_NAMES = ("measured.parquet", "measured.csv")
SIDECAR = "measured.json"
SEALED = "SEALED_truth.json"


@dataclass
class Measured:
    ids: list[str]
    dhe: np.ndarray  # (n, 3) d mm, h mm, E kPa
    y: np.ndarray  # (n, 3) camera features
    se: np.ndarray  # (n, 3) standard error (0 where unknown)
    tissue_E: np.ndarray  # (n,) NaN = nominal
    difference: list  # per phantom: 2-D array (FS) or None
    sensor: dict | None = None
    feature_settings: dict = field(default_factory=dict)
    mesh: str = "coarse"
    synthetic: bool = False
    description: str = ""
    source: str = ""
    difference_se: list | None = None  # per phantom: 2-D per-pixel standard error (FS) or None
    force: np.ndarray | None = None  # (n,) measured plate force (mN), NaN = not measured
    force_se: np.ndarray | None = None  # (n,) its standard error (mN)
    #: the sensor the phantoms were pressed with (elastimap.sensor.Sensor; None: the paper's
    #: mechanics with the camera ``sensor``); its camera then replaces ``sensor``
    sensor_description: Sensor | None = None

    def __post_init__(self):
        n = len(self.ids)
        if self.difference_se is None:
            self.difference_se = [None] * n
        if self.force is None:
            self.force = np.full(n, np.nan)
        if self.force_se is None:
            self.force_se = np.zeros(n)

    @property
    def has_force(self) -> bool:
        return bool(np.all(np.isfinite(self.force)))

    @property
    def has_images(self) -> bool:
        return all(d is not None for d in self.difference)

    @property
    def n(self) -> int:
        return len(self.ids)

    def sensor_model(self):
        if self.sensor_description is not None:
            return SensorModel.of(self.sensor_description)
        return SensorModel.from_dict(self.sensor) if self.sensor else SensorModel()

    def settings(self):
        return FeatureSettings.from_dict(self.feature_settings or {})

    def subset(self, idx) -> Measured:
        idx = np.asarray(idx)
        return Measured(
            [self.ids[i] for i in idx],
            self.dhe[idx],
            self.y[idx],
            self.se[idx],
            self.tissue_E[idx],
            [self.difference[i] for i in idx],
            self.sensor,
            self.feature_settings,
            self.mesh,
            self.synthetic,
            self.description,
            self.source,
            [self.difference_se[i] for i in idx],
            self.force[idx],
            self.force_se[idx],
            self.sensor_description,
        )


def _table_path(path: Path) -> Path:
    if path.is_dir():
        for n in TABLE_NAMES:
            if (path / n).exists():
                return path / n
        raise UserError("measured", f"{path}: no {' or '.join(TABLE_NAMES)} in this folder")
    if not path.exists():
        raise UserError("measured", f"{path}: no such file or folder")
    if path.suffix not in (".csv", ".parquet"):
        raise UserError("measured", f"{path}: the table must be .csv or .parquet")
    return path


def load(path: str | os.PathLike, sensor: Sensor | None = None, *, allow_outside: bool = False) -> Measured:
    """Read and validate a measured dataset; every problem is a one-line :class:`UserError`.

    The files the table names (frames, ``.npy`` images) are read only inside the dataset's folder
    -- no absolute paths, ``..`` or links out of it -- unless ``allow_outside``
    (``--allow-outside``); ids must be usable in file names (no ``/``).  ``sensor``: the sensor
    description the phantoms were pressed with (``--sensor``); default the sidecar's
    ``sensor_description``, else the paper's mechanics with the sidecar's camera."""
    tp = _table_path(Path(path))
    base = tp.parent
    df = _read_table(tp)
    sp = base / SIDECAR
    side = _read_sidecar(sp)
    sensor_cam = side.get("sensor")
    settings = side.get("feature_settings", {})
    _check_sidecar(sp, sensor_cam, settings, side)
    if sensor is None and side.get("sensor_description") is not None:
        try:
            sensor = Sensor.from_dict(side["sensor_description"])
        except UserError as exc:
            raise UserError("measured", f"{sp}: sensor_description: {exc.param}: {exc.message}") from None
    if sensor is not None:
        sensor_cam = SensorModel.of(sensor).to_dict()
    y, se, from_frames = _features(df, tp, sensor_cam, settings, allow_outside)
    diffs, dses = _difference_images(df, tp, from_frames, allow_outside)
    force, force_se = _force(df, tp)
    n = len(df)
    tE = (
        pd.to_numeric(df["tissue_E"], errors="coerce").to_numpy(float)
        if "tissue_E" in df.columns
        else np.full(n, np.nan)
    )
    if np.any(np.isinf(tE)) or np.any(tE[np.isfinite(tE)] <= 0):
        raise UserError("measured", f"{tp}: tissue_E must be a positive number of kPa (or empty)")
    mesh = str(side.get("mesh", "coarse"))
    if mesh not in ("tiny", "coarse", "default", "fine"):
        raise UserError("measured", f"{sp}: mesh must be tiny, coarse, default or fine (got {mesh!r})")
    return Measured(
        df["id"].tolist(),
        df[["d", "h", "E"]].to_numpy(float),
        y,
        se,
        tE,
        diffs,
        sensor_cam,
        settings,
        mesh,
        bool(side.get("synthetic", False)),
        str(side.get("description", "")),
        str(tp),
        dses,
        force,
        force_se,
        sensor,
    )


def _read_table(tp: Path) -> pd.DataFrame:
    """The table with its ids checked (file-name safe, unique) and d, h, E positive numbers."""
    if tp.suffix == ".parquet":
        try:
            df = pd.read_parquet(tp)
        except Exception as exc:  # pyarrow raises many types for a damaged file
            raise UserError("measured", f"{tp}: not a readable table ({exc})") from None
    else:
        df = read_csv(tp, "measured")
    if len(df) == 0:
        raise UserError("measured", f"{tp}: no rows")
    if len(df) < 4:
        raise UserError("measured", f"{tp}: need at least 4 phantoms for a cross-validated diagnosis (got {len(df)})")
    missing = [c for c in ("id", "d", "h", "E") if c not in df.columns]
    if missing:
        raise UserError("measured", f"{tp}: missing column(s) {', '.join(missing)} (need id, d, h, E)")
    df["id"] = df["id"].astype(str)
    for id_ in df["id"]:
        check_name(id_, "measured", f"{tp}: id")
    dup = sorted(set(df["id"][df["id"].duplicated()]))
    if dup:
        raise UserError("measured", f"{tp}: duplicate id(s) {dup[:5]}")
    for c in ("d", "h", "E"):
        v = pd.to_numeric(df[c], errors="coerce")
        bad = df["id"][v.isna() | ~(v > 0) | ~np.isfinite(v.astype(float))].tolist()
        if bad:
            raise UserError("measured", f"{tp}: column {c} must be a positive number (rows {bad[:5]})")
        df[c] = v.astype(float)
    return df


def _read_sidecar(sp: Path) -> dict:
    """The sidecar's JSON object ({} without a sidecar), its kind and version checked."""
    if not sp.exists():
        return {}
    try:
        side = json.loads(sp.read_text())
    except json.JSONDecodeError as exc:
        raise UserError("measured", f"{sp}: not valid JSON ({exc})") from None
    if not isinstance(side, dict):
        raise UserError("measured", f"{sp}: must hold a JSON object")
    if side.get("kind") != KIND:
        raise UserError("measured", f"{sp}: not an elastimap gap measured-data sidecar (kind {side.get('kind')!r})")
    if side.get("version", -1) != VERSION:
        raise UserError("measured", f"{sp}: version {side.get('version')!r} not supported (expected {VERSION})")
    return side


def _features(df: pd.DataFrame, tp: Path, sensor_cam, settings, allow_outside: bool):
    """Camera features ``y`` (n, 3) and their standard errors ``se`` from the table, and where the
    table names frames, ``{row: views}`` computed from them (features where the table has none,
    and always the difference image with its per-pixel noise, so the residual map is never lost)."""
    n = len(df)
    has_feat = all(k in df.columns for k in FEATURES)
    has_img = "images" in df.columns and "background" in df.columns
    if not has_feat and not has_img:
        raise UserError("measured", f"{tp}: needs camera features O1,O2,O3 or frame columns images,background")
    y = np.full((n, 3), np.nan)
    se = np.zeros((n, 3))
    if has_feat:
        y = df[list(FEATURES)].apply(pd.to_numeric, errors="coerce").to_numpy(float)
    for j, k in enumerate(FEATURES):
        if f"{k}_se" in df.columns:
            v = pd.to_numeric(df[f"{k}_se"], errors="coerce").to_numpy(float)
            if np.any(v[np.isfinite(v)] < 0):
                raise UserError("measured", f"{tp}: {k}_se must be >= 0")
            se[:, j] = np.where(np.isfinite(v), v, 0.0)
    need = ~np.all(np.isfinite(y), axis=1)
    from_frames: dict[int, dict] = {}
    if need.any() and not has_img:
        raise UserError("measured", f"{tp}: non-numeric features for {df['id'][need].tolist()[:5]}")
    if has_img:
        sm = SensorModel.from_dict(sensor_cam) if sensor_cam else SensorModel()
        fs = FeatureSettings.from_dict(settings or {})
        for i in range(n):
            r = df.iloc[i]
            if not isinstance(r["images"], str) or not r["images"].strip():
                continue
            where = f"{tp}, {r['id']!r}"
            F, fs1 = read_stack(
                _files(r, "images", tp.parent, where, allow_outside), sm.shape, sm.window, "measured", bits=sm.bits
            )
            B, fs2 = read_stack(
                _files(r, "background", tp.parent, where, allow_outside), sm.shape, sm.window, "measured", bits=sm.bits
            )
            if fs1 != fs2:
                raise UserError("measured", f"{where}: the background frames' bit depth differs from the lesion frames")
            v = views_from_frames(F, B, sm, fs, fs1)
            from_frames[i] = v
            if need[i]:
                y[i], se[i] = v["values"], v["se"]
    miss = [df["id"].iloc[i] for i in np.flatnonzero(~np.all(np.isfinite(y), axis=1))]
    if miss:
        raise UserError("measured", f"{tp}: no features and no frames for {miss[:5]}")
    return y, se, from_frames


def _npy(df: pd.DataFrame, tp: Path, col: str, i: int, what: str, allow_outside: bool) -> np.ndarray | None:
    """Row ``i``'s ``.npy`` image named in column ``col`` (None where there is none): inside the
    table's folder unless ``allow_outside``, a finite 2-D array."""
    base = tp.parent
    f = df[col].iloc[i] if col in df.columns else None
    if f is None or (isinstance(f, float) and np.isnan(f)) or str(f).strip() == "":
        return None
    fp = base / str(f)
    if not allow_outside and not _inside(fp, base):
        raise UserError(
            "measured",
            f"{tp}: {what} {f} of {df['id'].iloc[i]} lies outside the folder {base} (a table's files are "
            "read only inside its folder; give --allow-outside to allow it)",
        )
    if not fp.is_file():
        raise UserError("measured", f"{tp}: {what} {fp} of {df['id'].iloc[i]} does not exist")
    try:
        a = np.load(fp, allow_pickle=False)
    except Exception as exc:
        raise UserError("measured", f"{fp}: not a .npy array ({exc})") from None
    if a.ndim != 2 or not np.all(np.isfinite(a)):
        raise UserError("measured", f"{fp}: must be a finite 2-D array (got shape {a.shape})")
    return a.astype(float)


def _difference_images(df: pd.DataFrame, tp: Path, from_frames: dict, allow_outside: bool):
    """Each row's difference image and its standard-error image (mm; None where neither the table
    nor the frames give one): the table's ``.npy`` files first, else the frames'."""
    diffs, dses = [], []
    for i in range(len(df)):
        a = _npy(df, tp, "difference", i, "difference image", allow_outside)
        b = _npy(df, tp, "difference_se", i, "difference standard-error image", allow_outside)
        if a is None and i in from_frames:
            a = from_frames[i]["difference"]
        if b is None and i in from_frames:
            b = from_frames[i]["difference_se"]
        if b is not None and a is not None and b.shape != a.shape:
            raise UserError(
                "measured", f"{tp}: difference_se of {df['id'].iloc[i]} has shape {b.shape}, its image {a.shape}"
            )
        if b is not None and np.any(b < 0):
            raise UserError("measured", f"{tp}: difference_se of {df['id'].iloc[i]} must be >= 0")
        diffs.append(a)
        dses.append(b)
    shapes = {a.shape for a in diffs if a is not None}
    if len(shapes) > 1:
        raise UserError("measured", f"{tp}: difference images have different shapes {sorted(shapes)}")
    return diffs, dses


def _force(df: pd.DataFrame, tp: Path) -> tuple[np.ndarray, np.ndarray]:
    """Plate forces (mN; NaN where not measured) and their standard errors (0 where not given)."""
    n = len(df)
    force, force_se = np.full(n, np.nan), np.zeros(n)
    if "force" in df.columns:
        force = pd.to_numeric(df["force"], errors="coerce").to_numpy(float)
        if np.any(force[np.isfinite(force)] <= 0):
            raise UserError("measured", f"{tp}: force must be > 0 mN")
        if "force_se" in df.columns:
            v = pd.to_numeric(df["force_se"], errors="coerce").to_numpy(float)
            if np.any(v[np.isfinite(v)] < 0):
                raise UserError("measured", f"{tp}: force_se must be >= 0")
            force_se = np.where(np.isfinite(v), v, 0.0)
    return force, force_se


def _inside(path: Path, folder: Path) -> bool:
    real, root = os.path.realpath(path), os.path.realpath(folder)
    return real.startswith(root.rstrip(os.sep) + os.sep)


def _files(row, col: str, base: Path, where: str, allow_outside: bool) -> list[str]:
    """The frame files of one row's ``images`` or ``background`` column (inside ``base``)."""
    try:
        return expand(str(row[col]), base, param="measured", allow_outside=allow_outside)
    except UserError as exc:
        raise UserError("measured", f"{where}, column {col}: {exc.message}") from None


def _check_sidecar(sp: Path, sensor, settings, side: dict) -> None:
    """The sidecar's camera model and feature settings are usable (else a one-line refusal naming it)."""
    if not isinstance(settings, dict):
        raise UserError("measured", f"{sp}: feature_settings must be a JSON object (got {type(settings).__name__})")
    if sensor is not None and not isinstance(sensor, dict):
        raise UserError("measured", f"{sp}: sensor must be a JSON object (got {type(sensor).__name__})")
    if not isinstance(side.get("synthetic", False), bool):
        raise UserError("measured", f"{sp}: synthetic must be true or false")
    for what, make, value in (
        ("sensor", SensorModel.from_dict, sensor),
        ("feature_settings", FeatureSettings.from_dict, settings),
    ):
        if value is None:
            continue
        try:
            make(value)
        except UserError as exc:
            raise UserError("measured", f"{sp}: {what}: {exc.message}") from None
        except (TypeError, ValueError, KeyError, AttributeError) as exc:
            raise UserError("measured", f"{sp}: {what} is not valid ({type(exc).__name__}: {exc})") from None


def write(m: Measured, folder: str | os.PathLike, fmt: str = "csv") -> Path:
    """Write a dataset in the format above (difference images as ``.npy`` next to the table)."""
    for id_ in m.ids:
        check_name(id_, "ids", "id")
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    prefix = "synthetic_" if m.synthetic else ""
    rows = []
    for i, id_ in enumerate(m.ids):
        r = {"id": id_, "d": m.dhe[i, 0], "h": m.dhe[i, 1], "E": m.dhe[i, 2]}
        for j, k in enumerate(FEATURES):
            r[k] = m.y[i, j]
        for j, k in enumerate(FEATURES):
            r[f"{k}_se"] = m.se[i, j]
        if np.isfinite(m.tissue_E[i]):
            r["tissue_E"] = m.tissue_E[i]
        if np.isfinite(m.force[i]):
            r["force"], r["force_se"] = m.force[i], m.force_se[i]
        if m.difference[i] is not None:
            fn = f"{prefix}difference_{id_}.npy"
            np.save(out / fn, np.asarray(m.difference[i], np.float32))
            r["difference"] = fn
        if m.difference_se[i] is not None:
            fn = f"{prefix}difference_se_{id_}.npy"
            np.save(out / fn, np.asarray(m.difference_se[i], np.float32))
            r["difference_se"] = fn
        rows.append(r)
    df = pd.DataFrame(rows)
    tp = out / ("measured.parquet" if fmt == "parquet" else "measured.csv")
    if fmt == "parquet":
        df.to_parquet(tp, index=False)
    else:
        df.to_csv(tp, index=False, float_format="%.10g")
    side = {
        "kind": KIND,
        "version": VERSION,
        "synthetic": m.synthetic,
        "description": m.description,
        "sensor": m.sensor,
        "feature_settings": m.feature_settings,
        "mesh": m.mesh,
    }
    if m.sensor_description is not None:
        side.update(sensor_description=m.sensor_description.to_dict(), sensor_hash=m.sensor_description.hash())
    (out / SIDECAR).write_text(json.dumps(side, indent=2) + "\n")
    return tp


def measured_views(meas: Measured, sensor, settings) -> dict:
    """{view: (values (n,q), standard errors (n,q))} of the measured data."""
    out = {"features": (meas.y, meas.se)}
    if meas.has_images:
        P, Pse = [], []
        for D, Dse in zip(meas.difference, meas.difference_se):
            P.append(radial_profile(D, sensor.pixel_mm))
            if Dse is None:  # no per-pixel noise given: the window's outer ring's scatter, uniform
                ring = np.zeros(D.shape, bool)
                w = max(2, D.shape[0] // 10)
                ring[:w, :] = ring[-w:, :] = ring[:, :w] = ring[:, -w:] = True
                Dse = np.full(D.shape, float(np.std(D[ring])))
            Pse.append(profile_se(Dse, sensor.pixel_mm, settings.smooth_px))
        out["profile"] = (np.asarray(P), np.asarray(Pse))
    if meas.has_force:
        out["force"] = (meas.force[:, None], meas.force_se[:, None])
    return out
