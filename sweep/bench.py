"""``sweep bench``: the same sweep at several worker counts, timed; ``--compare``: the same sweep
by several forward-model paths (:data:`PATHS`), side by side.

Each count runs the identical sample list into a fresh dataset directory, so
every run solves everything (nothing is skipped).  Figures per run:

* wall: the whole command (warm-up, cluster start, fan-out, compaction)
* samples/min: samples / wall
* fan-out samples/min: samples / time from first submit to last result
* driver CPU per sample: CPU seconds of the driver process (which also hosts
  the local dask scheduler) during fan-out, per sample
* driver overhead per sample: wall * jobs / n - mean solve time, i.e. worker
  time per sample not spent solving (start-up, idle, scheduling, landing)

With ``--compare`` (:func:`compare`) each worker count runs the sample list once per path of
``paths`` (default ``separate,shared``), into fresh directories: ``separate`` every press
factorised for itself (:class:`SeparatePresses`, the path before the shared presses),
``shared`` the remeshed forward model as shipped, ``morph`` the morphed, sized-by-d one
(``geometry="morph", sizing="by_d"``, docs/forward-model.md, 'Mesh: sizing and morphing'),
``morph-fixed`` the morphed one with today's sizing.  It
prints each, the ratio of samples/min and of the workers' CPU seconds per sample against the
first path (the latter less sensitive to other load on the machine than wall time), the load
average before each run, the largest peak memory of a sample, and how far each path's features
are from the first path's, sample by sample (largest and mean).
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np

from elastimap.dataset import store
from elastimap.errors import UserError

from .run import SweepConfig, make_plan, run

#: the features and the force :func:`compare` checks between the paths
COMPARED = ("O1", "O2", "O3", "force")

#: the paths ``--compare`` can time: name -> (geometry, sizing, whether each press is factorised
#: for itself)
PATHS = {
    "separate": ("remesh", "fixed", True),
    "shared": ("remesh", "fixed", False),
    "morph": ("morph", "by_d", False),
    "morph-fixed": ("morph", "fixed", False),
}


class SeparatePresses:
    """The forward model with each press assembled, reduced and factorised for itself, the
    inclusion press first (``elastimap.solver.api.solve(presses="separate")``): the baseline of
    :func:`compare`.  A module-level class, so it pickles by module path to the workers."""

    solver_name = store.FEM

    def __call__(self, p):
        from elastimap.solver.api import solve

        return solve(p, presses="separate")

    def warmup(self, p) -> None:
        from elastimap.solver import warmup

        warmup(p)


def bench(counts: list[int], out: str | None = None, **kw) -> dict:
    if not counts:
        raise UserError("counts", "give at least one worker count")
    tmp = None
    if out is None:
        tmp = tempfile.TemporaryDirectory(prefix="sweep-bench-")
        root = Path(tmp.name)
    else:
        root = Path(out)
        if root.exists() and not root.is_dir():
            raise UserError("out", f"{root} is a file, not a folder")
        if root.exists() and any(root.iterdir()):
            raise UserError("out", f"{root} is not empty (the benchmark needs fresh directories)")
    plans = []
    for k in counts:  # check everything before running anything
        cfg = SweepConfig(jobs=k, out=str(root / f"jobs{k}"), progress=False, **kw)
        plans.append((k, cfg, make_plan(cfg)))
    rows = []
    try:
        for k, cfg, plan in plans:
            s = run(cfg, plan)
            if s["interrupted"]:
                raise KeyboardInterrupt
            n = s["done"]
            per = s["wall_s"] * k / n if n else math.nan
            rows.append(
                {
                    "jobs": k,
                    "samples": n,
                    "ok": s["ok"],
                    "failed": s["failed"],
                    "wall_s": s["wall_s"],
                    "samples_per_min": s["samples_per_min"],
                    "fan_out_samples_per_min": 60.0 * n / s["fan_out_s"] if s.get("fan_out_s") else math.nan,
                    "mean_solve_s": s.get("mean_solve_s", math.nan),
                    "driver_cpu_ms_per_sample": s.get("driver_cpu_ms_per_sample", math.nan),
                    "overhead_s_per_sample": per - s.get("mean_solve_s", math.nan),
                    "warmup_s": s.get("warmup_s", math.nan),
                    "cluster_start_s": s.get("cluster_start_s", math.nan),
                }
            )
    finally:
        if tmp is not None:
            tmp.cleanup()
    return {"rows": rows, "mesh": kw.get("mesh"), "out": None if tmp else str(root)}


def format_bench(res: dict) -> str:
    rows = res["rows"]
    head = (
        f"{'jobs':>4} {'samples':>7} {'failed':>6} {'wall s':>8} {'samples/min':>11} {'fan-out/min':>11} "
        f"{'solve s':>8} {'overhead s/sample':>17} {'driver CPU ms/sample':>20}"
    )
    lines = [f"sweep bench (mesh {res['mesh']})", head]
    for r in rows:
        lines.append(
            f"{r['jobs']:>4} {r['samples']:>7} {r['failed']:>6} {r['wall_s']:>8.1f} {r['samples_per_min']:>11.2f} "
            f"{r['fan_out_samples_per_min']:>11.2f} {r['mean_solve_s']:>8.2f} {r['overhead_s_per_sample']:>17.3f} "
            f"{r['driver_cpu_ms_per_sample']:>20.1f}"
        )
    if len(rows) >= 2 and rows[0]["samples_per_min"] > 0:
        r0 = rows[0]
        for r in rows[1:]:
            lines.append(
                f"speed-up jobs {r['jobs']} vs {r0['jobs']}: {r['samples_per_min'] / r0['samples_per_min']:.2f}x "
                f"(fan-out only {r['fan_out_samples_per_min'] / r0['fan_out_samples_per_min']:.2f}x)"
            )
    if res.get("out"):
        lines.append(f"datasets kept under {res['out']}")
    return "\n".join(lines)


def _timed_run(cfg: SweepConfig, plan) -> dict:
    """One sweep run with the load average before it and its workers' CPU seconds (the local
    cluster's worker processes are this process's children, counted once they have exited)."""
    load = os.getloadavg()[0]
    t0 = os.times()
    s = run(cfg, plan)
    t1 = os.times()
    if s["interrupted"]:
        raise KeyboardInterrupt
    s["load_before"] = load
    s["worker_cpu_s"] = (t1.children_user + t1.children_system) - (t0.children_user + t0.children_system)
    return s


def feature_deviation(a, b) -> dict:
    """Largest |b / a − 1| over the samples both datasets hold as ok, per quantity of ``COMPARED``
    (a pair of zeros counts as equal, a zero against a non-zero as 1), its mean under
    ``mean_<quantity>``, and how many were compared."""
    from elastimap.dataset import io

    cols = ["sample_id", "status", *COMPARED]
    ta, tb = (io.read_table(p, cols).set_index("sample_id") for p in (a, b))
    both = ta.index[(ta["status"] == "ok")].intersection(tb.index[tb["status"] == "ok"])
    out = {"samples": int(len(both))}
    for k in COMPARED:
        x, y = ta.loc[both, k].to_numpy(float), tb.loc[both, k].to_numpy(float)
        zero = x == 0
        dev = np.where(zero, (y != 0).astype(float), np.abs(y - x) / np.where(zero, 1.0, np.abs(x)))
        out[k] = float(dev.max()) if dev.size else math.nan
        out[f"mean_{k}"] = float(dev.mean()) if dev.size else math.nan
    return out


def parse_paths(text: str) -> tuple[str, ...]:
    """``separate,morph`` -> ("separate", "morph"): two or more distinct names of :data:`PATHS`."""
    paths = tuple(x.strip() for x in text.split(",") if x.strip())
    if len(paths) < 2 or len(set(paths)) != len(paths) or any(x not in PATHS for x in paths):
        raise UserError("paths", f"give two or more distinct of {', '.join(PATHS)}, comma-separated (got {text!r})")
    return paths


def compare(counts: list[int], out: str | None = None, paths=("separate", "shared"), **kw) -> dict:
    """The same sweep by each path of ``paths`` (names of :data:`PATHS`; the first is the baseline)
    at each worker count in ``counts`` (``kw`` as :class:`~elastimap.sweep.run.SweepConfig`'s,
    without ``solver``, ``geometry`` and ``sizing``, which the paths set)."""
    if not counts:
        raise UserError("counts", "give at least one worker count")
    if kw.get("solver") is not None:
        raise UserError("solver", "--compare times the forward model; leave --solver out")
    kw.pop("solver", None)
    paths = parse_paths(",".join(paths))
    tmp = None
    if out is None:
        tmp = tempfile.TemporaryDirectory(prefix="sweep-compare-")
        root = Path(tmp.name)
    else:
        root = Path(out)
        if root.exists() and any(root.iterdir()):
            raise UserError("out", f"{root} is not empty (the benchmark needs fresh directories)")
    plans = []
    for k in counts:  # check everything before running anything
        for path in paths:
            geometry, sizing, separate = PATHS[path]
            cfg = SweepConfig(
                jobs=k,
                out=str(root / f"{path}-jobs{k}"),
                progress=False,
                solver=SeparatePresses() if separate else None,
                geometry=geometry,
                sizing=sizing,
                **kw,
            )
            plans.append((k, path, cfg, make_plan(cfg)))
    rows = []
    try:
        for k, path, cfg, plan in plans:
            s = _timed_run(cfg, plan)
            rows.append(
                {
                    "jobs": k,
                    "path": path,
                    "samples": s["done"],
                    "failed": s["failed"],
                    "wall_s": s["wall_s"],
                    "samples_per_min": s["samples_per_min"],
                    "mean_solve_s": s.get("mean_solve_s", math.nan),
                    "worker_cpu_s_per_sample": s["worker_cpu_s"] / s["done"] if s["done"] else math.nan,
                    "peak_memory_mb": _peak_memory(cfg.out),
                    "load_before": s["load_before"],
                    "out": cfg.out,
                }
            )
        devs = {
            (k, path): feature_deviation(root / f"{paths[0]}-jobs{k}", root / f"{path}-jobs{k}")
            for k in counts
            for path in paths[1:]
        }
    finally:
        if tmp is not None:
            tmp.cleanup()
    return {"rows": rows, "paths": paths, "deviation": devs, "mesh": kw.get("mesh"), "out": None if tmp else str(root)}


def _peak_memory(path) -> float:
    from elastimap.dataset import io

    mem = io.read_table(path, ["sample_id", "peak_memory_mb"])["peak_memory_mb"].to_numpy(float)
    return float(np.nanmax(mem)) if mem.size else math.nan


def format_compare(res: dict) -> str:
    paths = res["paths"]
    head = (
        f"{'jobs':>4} {'path':>11} {'samples':>7} {'failed':>6} {'wall s':>8} {'samples/min':>11} "
        f"{'worker CPU s/sample':>19} {'solve s':>8} {'peak MiB':>8} {'load before':>11}"
    )
    what = ", ".join(
        f"{p} = {'/'.join(('separate presses' if PATHS[p][2] else 'shared presses', *PATHS[p][:2]))}" for p in paths
    )
    lines = [f"sweep bench --compare (mesh {res['mesh']}): {what}", head]
    for r in res["rows"]:
        lines.append(
            f"{r['jobs']:>4} {r['path']:>11} {r['samples']:>7} {r['failed']:>6} {r['wall_s']:>8.1f} "
            f"{r['samples_per_min']:>11.2f} {r['worker_cpu_s_per_sample']:>19.2f} {r['mean_solve_s']:>8.2f} "
            f"{r['peak_memory_mb']:>8.0f} {r['load_before']:>11.2f}"
        )
    by = {(r["jobs"], r["path"]): r for r in res["rows"]}
    for (k, path), dev in res["deviation"].items():
        a, b = by[(k, paths[0])], by[(k, path)]
        lines.append(
            f"jobs {k}: {path} vs {paths[0]} {b['samples_per_min'] / a['samples_per_min']:.2f}x samples/min, "
            f"{a['worker_cpu_s_per_sample'] / b['worker_cpu_s_per_sample']:.2f}x less worker CPU per sample"
        )
        lines.append(
            f"        features over {dev['samples']} samples, |{path}/{paths[0]} - 1| largest: "
            + ", ".join(f"{q} {dev[q]:.1e}" for q in COMPARED)
            + "; mean: "
            + ", ".join(f"{q} {dev['mean_' + q]:.1e}" for q in COMPARED)
        )
    if res.get("out"):
        lines.append(f"datasets kept under {res['out']}")
    return "\n".join(lines)
