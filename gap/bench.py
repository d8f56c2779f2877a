"""Benchmark of a first diagnosis: solves, seconds and where the time goes (``elastimap gap bench``).

SYNTHETIC measured data for ``n`` phantoms are made first (on ``data_mesh`` with the
``data_interface``, kept in ``data_cache`` so that a rerun does not count them), then one
diagnosis with every default candidate runs **without a solve cache** (every solve it needs is
solved) on ``mesh``, its model error against the next finer level.  Printed: wall seconds, solves
per effect and per stage (baseline, candidates, model-error mesh, refinement, inverse) and
seconds per stage of the diagnosis.
"""

from __future__ import annotations

import os
import platform
import resource
import time

from . import effects as fx
from .diagnose import diagnose
from .settings import FINER, Settings
from .simulate import Simulator
from .synth import phantom_design, synthesize


def run(
    n: int = 12,
    mesh: str = "coarse",
    jobs: int = 2,
    effect: str = "background_E=6.5",
    data_mesh: str = "default",
    data_interface: str = "contact",
    data_cache: str | None = None,
    inverse: bool = False,
    adaptive: bool = True,
    seed: int = 0,
    log=print,
) -> dict:
    dhe = phantom_design(n, seed)
    dc = os.path.join(data_cache, f"fem-{data_mesh}") if data_cache else None
    sim_data = Simulator(dc, data_mesh, "fem", jobs)
    t = time.perf_counter()
    meas, _ = synthesize(
        dhe,
        fx.parse_spec(effect) if effect else [],
        sim_data,
        frames=10,
        seed=seed,
        disc={"interface": data_interface} if data_interface != "tied" else None,
    )
    t_data = time.perf_counter() - t
    sim_data.close()
    log(
        f"data: {n} phantoms, {effect or 'no effect'}, mesh {data_mesh} {data_interface}: "
        f"{sim_data.stats['solved']} solved, {sim_data.stats['hits']} from the data cache, {t_data:.0f} s",
        flush=True,
    )

    def progress(level):
        t_start = time.perf_counter()

        def prog(i, k):
            if log and (i == k or i % 12 == 0):
                log(f"  [{time.perf_counter() - t_start:.0f} s] {level}: solves {i}/{k}", flush=True)

        return prog

    sim = Simulator(None, mesh, "fem", jobs, progress=progress(mesh))
    fine = Simulator(None, FINER[mesh], "fem", jobs, progress=progress(FINER[mesh])) if FINER.get(mesh) else None
    st = Settings(inverse=inverse, adaptive=adaptive, seed=seed)

    def cpu():
        a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime

    c0 = cpu()
    t0 = time.perf_counter()
    res = diagnose(meas, fx.parse_list(None), sim, st, fine)
    wall = time.perf_counter() - t0
    sim.close()
    if fine is not None:
        fine.close()
    cpu_s = cpu() - c0  # the workers' CPU time counts once they have exited (closed above)
    ev = res["evaluation"]
    sbe = res["solves_by_effect"]
    out = {
        "n": n,
        "mesh": mesh,
        "error_mesh": fine.mesh if fine else None,
        "jobs": jobs,
        "adaptive": adaptive,
        "inverse": inverse,
        "effect_in_data": effect,
        "wall_seconds": wall,
        "cpu_seconds": cpu_s,
        "solves_total": sim.stats["solved"] + (fine.stats["solved"] if fine else 0),
        "solves_diagnosis_mesh": sim.stats["solved"],
        "solves_error_mesh": fine.stats["solved"] if fine else 0,
        "solve_seconds_summed": sim.stats["solve_seconds"] + (fine.stats["solve_seconds"] if fine else 0),
        "geometries": sim.stats.get("geometries", 0),
        "solves_by_effect": sbe,
        "solve_seconds_by_effect": res["solve_seconds_by_effect"],
        "refinement": res["refinement"],
        "timing": res["timing"],
        "outcome": ev["outcome"],
        "set": ev["ambiguous_set"],
        "best": ev["best"],
        "machine": f"{platform.node()} {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}",
    }
    L = _lines(out, res, len(res["candidates"]), ev, sbe)
    if log:
        log("\n".join(L))
    out["text"] = "\n".join(L)
    return out


def _lines(out: dict, res: dict, n_cands: int, ev: dict, sbe: dict) -> list[str]:
    """The printed summary of one bench run."""
    n, mesh, jobs, adaptive, inverse = out["n"], out["mesh"], out["jobs"], out["adaptive"], out["inverse"]
    wall, cpu_s = out["wall_seconds"], out["cpu_seconds"]
    L = [
        f"first diagnosis: {n} phantoms, {n_cands} default candidates, mesh {mesh} "
        f"(model error vs {out['error_mesh']}), --jobs {jobs}, no cache, "
        f"{'adaptive magnitudes' if adaptive else 'full grids'}, inverse {'on' if inverse else 'off'}",
        f"  wall {wall:.0f} s, CPU {cpu_s:.0f} s (main process and workers; CPU / {jobs} = the wall time "
        f"{jobs} free cores would need at best: {cpu_s / jobs:.0f} s); {out['solves_total']} solves ({out['solves_diagnosis_mesh']} on {mesh} in "
        f"{out['geometries']} geometries, {out['solves_error_mesh']} on {out['error_mesh']}); "
        f"solve seconds summed over workers {out['solve_seconds_summed']:.0f} s",
        "  seconds by stage: " + ", ".join(f"{k} {v:.0f}" for k, v in res["timing"].items()),
        f"  refinement: {res['refinement']['solves']} solves in {res['refinement']['rounds']} rounds",
        "  solves by effect (sensitivity + refinement, x phantoms): "
        + ", ".join(f"{k} {v}" for k, v in sbe.items() if v),
        "  solve seconds by effect (summed over workers): "
        + ", ".join(f"{k} {v:.0f}" for k, v in sorted(res["solve_seconds_by_effect"].items(), key=lambda kv: -kv[1])),
        f"  verdict: {ev['outcome']} {ev['ambiguous_set'] or ''} (best {ev['best']})",
        f"  machine: {out['machine']}",
    ]
    return L
