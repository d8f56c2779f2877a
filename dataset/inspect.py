"""``dataset inspect``: a report on a sample dataset (dict + text)."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import numpy as np

from elastimap.errors import UserError

from . import io
from .schema import FEATURES, TARGETS, THICKNESS, depth_range

EXTRA_FEATURES = ("force", "force_ref")


def _stats(x: np.ndarray) -> dict:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"n": 0}
    return {"n": int(x.size), "min": float(x.min()), "median": float(np.median(x)), "max": float(x.max())}


def _coverage(df) -> dict:
    """How evenly the ok samples fill the parameter box: per-parameter 8-bin counts and the
    fraction of occupied cells of a 4x4x4 grid over (d, h relative to its allowed range, log E)."""
    if len(df) < 2:
        return {}
    d, h, E = (df[c].to_numpy(dtype=float) for c in TARGETS)
    lo, hi = depth_range(d, THICKNESS)
    rel_h = np.clip((h - lo) / np.where(hi > lo, hi - lo, 1.0), 0, 1)
    logE = np.log(E)

    def unit(x):
        span = x.max() - x.min()
        return np.zeros_like(x) if span <= 0 else (x - x.min()) / span

    u = np.stack([unit(d), rel_h, unit(logE)], axis=1)
    hist = {
        name: np.histogram(u[:, i], bins=8, range=(0, 1))[0].tolist()
        for i, name in enumerate(("d", "h (relative to allowed depth)", "log E"))
    }
    cells = np.minimum((u * 4).astype(int), 3)
    occupied = len({tuple(c) for c in cells})
    return {
        "histograms": hist,
        "cells_occupied": occupied,
        "cells": 64,
        "note": "bins over the sampled span; h relative to [1 + d/2, thickness - 2 - d/2]",
    }


def report(path, top: int = 5) -> dict:
    if isinstance(top, bool) or not isinstance(top, int) or top < 0:
        raise UserError("top", f"must be an integer >= 0 (got {top!r})")
    info = io.dataset_info(path)
    df = io.read_table(path)
    man = io.read_manifest(path) if Path(path).is_dir() else None
    rep: dict = {
        "path": str(path),
        "files": info["files"],
        "bytes": info["bytes"],
        "schema_versions": info["versions"],
        "units": info["units"],
        "image_shape": info["image_shape"],
        "pixel_mm": info["pixel"],
        "rows": int(len(df)),
    }
    rep["status"] = dict(Counter(df["status"]))
    rep["tags"] = dict(Counter(t.split(":")[0] for t in df["tag"]))
    if man:
        planned = set(man.get("planned", []))
        disc = man.get("base_params", {}).get("disc", {})
        rep["manifest"] = {
            "mesh": disc.get("mesh"),
            "interface": disc.get("interface"),
            "planned": len(planned),
            "missing": len(planned - set(df["sample_id"])),
            "runs": len(man.get("runs", [])),
            "created": man.get("created"),
        }
    ok = df[df["status"] == "ok"]
    rep["parameters"] = {c: _stats(ok[c]) for c in TARGETS}
    rep["coverage"] = _coverage(ok)
    rep["features"] = {c: _stats(ok[c]) for c in (*FEATURES, *EXTRA_FEATURES)}
    bad = {}
    for c in (*TARGETS, *FEATURES, *EXTRA_FEATURES):
        n = int((~np.isfinite(ok[c].to_numpy(dtype=float))).sum())
        if n:
            bad[c] = n
    shape = info["image_shape"]
    n_img_bad = n_img_missing = 0
    if len(ok):
        want = int(np.prod(shape)) if shape else None
        for v in ok["image"]:
            if v is None:
                n_img_missing += 1
            elif (want is not None and len(v) != want) or not np.all(np.isfinite(v)):
                n_img_bad += 1
    if n_img_missing:
        bad["image (missing)"] = n_img_missing
    if n_img_bad:
        bad["image (wrong size or non-finite)"] = n_img_bad
    rep["non_finite_in_ok_rows"] = bad
    rep["timing"] = {
        "seconds": _stats(ok["seconds"]),
        "ndofs": _stats(ok["ndofs"]),
        "newton_iterations": _stats(ok["newton_iterations"]),
        "peak_memory_mb": _stats(ok["peak_memory_mb"]),
        "total_solve_hours": float(np.nansum(df["seconds"].to_numpy(dtype=float)) / 3600.0),
        "hosts": sorted(set(df["host"])),
        "code_versions": sorted(set(df["code_version"])),
    }
    slow = ok.sort_values("seconds", ascending=False).head(top)
    rep["slowest"] = [
        {"sample_id": r.sample_id, "d": r.d, "h": r.h, "E": r.E, "seconds": r.seconds, "ndofs": r.ndofs}
        for r in slow.itertuples()
    ]
    failed = df[df["status"] != "ok"]
    kinds = Counter(str(e).split(":")[0] for e in failed["error"])
    rep["failures"] = {
        "count": int(len(failed)),
        "by_kind": dict(kinds),
        "examples": [
            {"sample_id": r.sample_id, "d": r.d, "h": r.h, "E": r.E, "error": r.error}
            for r in failed.head(top).itertuples()
        ],
    }
    return rep


def _g(x, nd=4):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.{nd}g}"


def format_report(rep: dict) -> str:
    units = rep["units"]
    L = [
        f"dataset {rep['path']}: {rep['rows']} samples in {rep['files']} file(s), {rep['bytes'] / 1e6:.2f} MB, "
        f"schema version {','.join(map(str, rep['schema_versions']))}"
    ]
    if rep["image_shape"]:
        L.append(f"  images: {rep['image_shape'][0]} x {rep['image_shape'][1]} px, pixel {rep['pixel_mm']:g} mm")
    st = ", ".join(f"{k} {v}" for k, v in sorted(rep["status"].items()))
    tg = ", ".join(f"{k} {v}" for k, v in sorted(rep["tags"].items()))
    L.append(f"  status: {st or 'none'}   tags: {tg or 'none'}")
    m = rep.get("manifest")
    if m:
        L.append(
            f"  sweep: mesh {m['mesh']}, interface {m['interface']}, {m['planned']} planned, "
            f"{m['missing']} missing, {m['runs']} run(s) since {m['created']}"
        )
    L.append("  parameters (ok rows):            min     median        max")
    for c, s in rep["parameters"].items():
        if s.get("n"):
            L.append(
                f"    {c:<4} [{units.get(c, ''):>4}]            {_g(s['min']):>10} {_g(s['median']):>10} {_g(s['max']):>10}"
            )
    cov = rep.get("coverage")
    if cov:
        L.append(
            f"  coverage: {cov['cells_occupied']}/{cov['cells']} cells of a 4x4x4 grid over (d, relative h, log E) occupied"
        )
        for k, h in cov["histograms"].items():
            L.append(f"    {k:<32} 8 bins: {' '.join(f'{x:>3d}' for x in h)}")
    L.append("  features (ok rows):              min     median        max")
    for c, s in rep["features"].items():
        if s.get("n"):
            L.append(
                f"    {c:<9} [{units.get(c, ''):>4}]       {_g(s['min']):>10} {_g(s['median']):>10} {_g(s['max']):>10}"
            )
    bad = rep["non_finite_in_ok_rows"]
    L.append("  NaN/inf in ok rows: " + (", ".join(f"{k} {v}" for k, v in bad.items()) if bad else "none"))
    t = rep["timing"]
    if t["seconds"].get("n"):
        L.append(
            f"  solve time: median {_g(t['seconds']['median'], 3)} s, max {_g(t['seconds']['max'], 3)} s, "
            f"total {t['total_solve_hours']:.3g} h; ndofs {_g(t['ndofs'].get('min'))}-{_g(t['ndofs'].get('max'))}; "
            f"peak memory max {_g(t['peak_memory_mb'].get('max'))} MiB"
        )
    L.append(f"  hosts: {', '.join(t['hosts'])}; code: {', '.join(t['code_versions'])}")
    if rep["slowest"]:
        L.append("  slowest samples:")
        for r in rep["slowest"]:
            L.append(f"    {r['sample_id']}  d={_g(r['d'])} h={_g(r['h'])} E={_g(r['E'])}  {_g(r['seconds'], 3)} s")
    f = rep["failures"]
    if f["count"]:
        L.append(f"  failures: {f['count']} (" + ", ".join(f"{k} {v}" for k, v in f["by_kind"].items()) + ")")
        for r in f["examples"]:
            L.append(f"    {r['sample_id']}  d={_g(r['d'])} h={_g(r['h'])} E={_g(r['E'])}: {str(r['error'])[:160]}")
    else:
        L.append("  failures: none")
    return "\n".join(L)
