"""Candidates: the sweep of each effect over the measured phantoms (docs/gap.md, 'Method').

A :class:`Candidate` holds one effect's predicted views (K magnitudes, n phantoms, q quantities)
and difference images.  A mechanics effect costs forward solves; an optics effect is the baseline
solve through another camera, and a plate-travel offset of a linear model is the baseline scaled,
so those two are *rendered* (``Candidate.render``) at any magnitude without solving.
:func:`simulate_candidates` solves the baseline and every candidate's plan through the cache;
:func:`add_points` inserts magnitudes solved later (adaptive refinement) and measures the
emulator's miss there; :class:`Interp` is that emulator.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import PchipInterpolator

from elastimap.errors import UserError

from . import effects as fx
from .measured import Measured
from .simulate import Record, Simulator, base_params
from .views import sim_views


@dataclass
class Candidate:
    """The sweep of one effect over the phantoms: views (K, n, q) and images (K, n, ny, nx)."""

    effect: fx.Effect
    grid: np.ndarray
    V: dict
    D: np.ndarray | None
    dropped: list = field(default_factory=list)
    interp_error: dict | None = None  # adaptive: measured interpolation error per view (n, q)
    adaptive: bool = False  # solved at a few magnitudes (sensitivity + refinement), not the grid
    refinements: list = field(default_factory=list)  # magnitudes solved near the fit
    own_error: list = field(default_factory=list)  # magnitudes with their own model error (Effect.own_model_error)
    #: an effect that costs no solves (optics, a linear model's plate travel): (magnitude, records
    #: of the baseline phantoms; default: this mesh's) -> (views, images)
    render: object = None
    #: its own level difference Δ = this mesh − error mesh at magnitudes [(m, {view: (n, q)})]
    own_delta: list = field(default_factory=list)
    extended: list = field(default_factory=list)  # magnitudes added beyond the grid (a fit at its end)
    #: solve seconds of its magnitudes (summed over workers, store hits count their stored time); None: nothing solved
    solve_seconds: float | None = None


def phantom_params(meas: Measured, mesh: str):
    return [
        base_params(mesh, *meas.dhe[i], tissue_E=meas.tissue_E[i], sensor=meas.sensor_description)
        for i in range(meas.n)
    ]


def _scaled(rec: Record, s: float) -> Record:
    """The record of the same linear problem at s times the plate travel (exact for linear models)."""
    return Record(
        f"{rec.key}*{s:.12g}",
        rec.O1 * s,
        rec.O2 * s,
        rec.O3,
        rec.force * s,
        rec.pixel,
        rec.image * s,
        rec.image_raw * s,
        0.0,
    )


def needs_solves(e: fx.Effect, linear: bool) -> bool:
    """Whether a magnitude of ``e`` other than the nominal costs forward solves: optics effects
    are camera-only (the baseline solve through another camera), and a plate-travel offset of a
    linear model is the baseline scaled."""
    return e.stage == "mechanics" and not (e.scales_with_delta and linear)


def solve_plan(meas: Measured, cands: list[fx.Effect], mesh: str, adaptive: bool):
    """[(effect, magnitude, params per phantom or None, how)]: "solve", "reuse" (no solve) or
    "invalid".  Adaptive: one sensitivity magnitude per solved effect (``Effect.sensitivity``),
    else every grid magnitude."""
    p0 = phantom_params(meas, mesh)
    linear = not any(p.nonlinear for p in p0)
    plan = []
    for e in cands:
        solved = needs_solves(e, linear)
        ms = [e.nominal, e.sensitivity] if (adaptive and solved) else list(e.grid)
        for m in ms:
            if not solved or e.is_nominal(m):
                plan.append((e, m, None, "reuse"))
                continue
            try:
                pl = [e.apply_params(p, m).validate() for p in p0]
            except UserError:
                plan.append((e, m, None, "invalid"))
                continue
            plan.append((e, m, pl, "solve"))
    return p0, linear, plan


def simulate_candidates(meas: Measured, cands: list[fx.Effect], sim: Simulator, sensor, settings, adaptive=False):
    """Baseline views and images and every candidate's sweep (solves through the cache).
    ``adaptive``: solved effects get their nominal and one sensitivity magnitude only
    (:func:`elastimap.gap.adaptive.refine` adds magnitudes near the fit).  Returns
    (V0, D0, candidates, baseline solve seconds); each candidate carries its own solve seconds."""
    p0, linear, plan = solve_plan(meas, cands, sim.mesh, adaptive)
    flat = list(p0) + [p for _, _, pl, _ in plan if pl is not None for p in pl]
    recs = sim.run(flat)
    base = recs[: meas.n]
    V0, D0 = sim_views(base, sensor, settings)
    base_seconds = sum(r.seconds for r in base)
    if not np.all(np.isfinite(V0["features"])):
        bad = np.flatnonzero(~np.all(np.isfinite(V0["features"]), axis=1))
        raise UserError("measured", f"the baseline solve failed for phantom(s) {[meas.ids[i] for i in bad]}")
    solved = iter(recs[meas.n :])
    out = []
    for e in cands:
        steps = [(m, how) for e2, m, _pl, how in plan if e2 is e]
        c = _sweep(e, steps, solved, meas.n, base, p0, V0, D0, sensor, settings)
        c.adaptive = adaptive and needs_solves(e, linear)
        c.interp_error = {k: np.zeros_like(v) for k, v in V0.items()} if c.adaptive else None
        c.render = None if needs_solves(e, linear) else _renderer(e, base, p0, sensor, settings)
        out.append(c)
    return V0, D0, out, base_seconds


def _sweep(e: fx.Effect, steps, solved, n: int, base, p0, V0: dict, D0, sensor, settings) -> Candidate:
    """One effect's candidate from its plan steps [(magnitude, how)]; ``solved`` yields the
    records of the solved steps in plan order (n per step)."""
    ms, Vs, Ds, dropped = [], [], [], []
    seconds = None
    for m, how in steps:
        if how == "invalid":
            dropped.append(float(m))
            continue
        if how == "solve":
            recs = [next(solved) for _ in range(n)]
            V, D = sim_views(recs, sensor, settings)
            seconds = (seconds or 0.0) + sum(r.seconds for r in recs)
        elif e.is_nominal(m):
            V, D = V0, D0
        elif e.stage == "optics":
            V, D = sim_views(base, e.apply_sensor(sensor, m), settings)
        else:  # plate travel of a linear model: scale the baseline solve
            s = (p0[0].loading.delta + float(m)) / p0[0].loading.delta
            V, D = sim_views([_scaled(r, s) for r in base], sensor, settings)
        if not np.all(np.isfinite(V["features"])):
            dropped.append(float(m))
            continue
        ms.append(float(m))
        Vs.append(V)
        Ds.append(D)
    order = np.argsort(ms)
    return Candidate(
        e,
        np.asarray(ms)[order],
        {k: np.asarray([Vs[i][k] for i in order]) for k in V0},
        np.asarray(Ds)[order] if Ds else None,
        dropped,
        solve_seconds=seconds,
    )


def _renderer(e: fx.Effect, base, p0, sensor, settings):
    """(magnitude, records of the baseline phantoms; default: this mesh's) -> (views, images) of
    an effect that costs no solves: the records through the effect's camera, or scaled."""

    def render(m, recs=None):
        recs = base if recs is None else recs
        if e.stage == "optics":
            return sim_views(recs, e.apply_sensor(sensor, m), settings)
        s = (p0[0].loading.delta + float(m)) / p0[0].loading.delta
        return sim_views([_scaled(r, s) for r in recs], sensor, settings)

    return render


def add_points(c: Candidate, ms: list[float], V: list[dict], D: list) -> None:
    """Insert solved magnitudes into an adaptive candidate.  Its interpolation error becomes the
    miss of the emulator *before* the insertion at the new magnitudes (per view, phantom and
    quantity; the largest over the new points): measured, not assumed."""
    em = {k: Interp(c.grid, c.V[k]) for k in c.V}
    miss = {k: np.zeros_like(c.V[k][0]) for k in c.V}
    for m, v in zip(ms, V):
        for k in c.V:
            miss[k] = np.maximum(miss[k], np.abs(v[k] - em[k](m)))
    g = np.r_[c.grid, ms]
    order = np.argsort(g)
    c.grid = g[order]
    c.V = {k: np.concatenate([c.V[k], np.asarray([v[k] for v in V])])[order] for k in c.V}
    if c.D is not None:
        c.D = np.concatenate([c.D, np.asarray(D)])[order]
    c.interp_error = miss
    c.refinements += [float(m) for m in ms]


def fit_range(c: Candidate) -> tuple[float, float]:
    """The magnitudes a candidate is fitted over: adaptive, the effect's grid range or beyond it
    where points were solved; a full sweep (or a rendered effect), its valid points."""
    if c.adaptive:
        return float(min(c.effect.lo, c.grid.min())), float(max(c.effect.hi, c.grid.max()))
    return float(c.grid.min()), float(c.grid.max())


class Interp:
    """Shape-preserving (PCHIP) interpolation of Y (K, ...) over the solved magnitudes g (K,),
    continued linearly (the end secant) beyond them; K = 1: constant."""

    def __init__(self, g: np.ndarray, Y: np.ndarray):
        self.g, self.Y = np.asarray(g, float), np.asarray(Y, float)
        self._p = PchipInterpolator(self.g, self.Y, axis=0) if len(self.g) > 1 else None

    def __call__(self, m):
        m = np.asarray(m, float)
        if self._p is None:
            return np.broadcast_to(self.Y[0], m.shape + self.Y.shape[1:]).copy()
        g, Y = self.g, self.Y
        out = self._p(np.clip(m, g[0], g[-1]))
        lo, hi = m < g[0], m > g[-1]
        if np.any(lo) or np.any(hi):
            s0 = (Y[1] - Y[0]) / (g[1] - g[0])
            s1 = (Y[-1] - Y[-2]) / (g[-1] - g[-2])
            ext = lambda mm, a, gg, sl: a + np.multiply.outer(mm - gg, sl)  # noqa: E731
            if m.ndim == 0:
                return ext(m, Y[0], g[0], s0) if lo else (ext(m, Y[-1], g[-1], s1) if hi else out)
            out[lo] = ext(m[lo], Y[0], g[0], s0)
            out[hi] = ext(m[hi], Y[-1], g[-1], s1)
        return out
