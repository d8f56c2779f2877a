"""``sweep bench``: the same sweep at several worker counts, timed.

Each count runs the identical sample list into a fresh dataset directory, so
every run solves everything (nothing is skipped).  Figures per run:

* wall: the whole command (warm-up, cluster start, fan-out, compaction)
* samples/min: samples / wall
* fan-out samples/min: samples / time from first submit to last result
* driver CPU per sample: CPU seconds of the driver process (which also hosts
  the local dask scheduler) during fan-out, per sample
* driver overhead per sample: wall * jobs / n - mean solve time, i.e. worker
  time per sample not spent solving (start-up, idle, scheduling, landing)
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

from elastimap.errors import UserError

from .run import SweepConfig, make_plan, run


def bench(counts: list[int], out: str | None = None, **kw) -> dict:
    if not counts:
        raise UserError("counts", "give at least one worker count")
    tmp = None
    if out is None:
        tmp = tempfile.TemporaryDirectory(prefix="sweep-bench-")
        root = Path(tmp.name)
    else:
        root = Path(out)
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
