"""Adaptive magnitudes: solve the leading candidates again at their fitted magnitude
(docs/gap.md, 'Method').

A mechanics effect starts with its nominal and one sensitivity magnitude
(:func:`~elastimap.gap.candidates.simulate_candidates`); :func:`refine` adds magnitudes near
the fits that could change the verdict, and the emulator's miss at each new point becomes that
candidate's interpolation error.  An effect that costs no solves is rendered at its fit instead.
"""

from __future__ import annotations

import numpy as np

from elastimap.errors import UserError

from .candidates import Candidate, add_points, fit_range, phantom_params
from .measured import Measured
from .model_error import correct, correct_own, render_corrected
from .settings import Settings
from .simulate import Simulator
from .views import sim_views

#: an effect that costs no solves is rendered exactly at a fit farther than this fraction of its range from its points
RENDER_TOL = 1e-3


def extrapolated(row: dict, byname: dict, tol: float) -> bool:
    """Whether a ranking row's fit lies, for any adaptive member, beyond its solved magnitudes
    (outside their hull by more than ``tol`` of the effect's range): there its emulator
    continues the end secant, an unmeasured guess."""
    for name, th in zip(row["members"], row["magnitude"]):
        c = byname.get(name)
        if c is None or not c.adaptive:
            continue
        t = tol * (c.effect.hi - c.effect.lo)
        if th < min(c.grid) - t or th > max(c.grid) + t:
            return True
    return False


def refine(
    meas: Measured,
    C: list[Candidate],
    sim: Simulator,
    sensor,
    settings,
    me: dict,
    st: Settings,
    evaluate_now,
    sim_fine: Simulator | None = None,
):
    """Adaptive magnitudes: while the ranking's leading candidates (the ``refine_top`` best,
    every one within ``refine_margin`` of the best score, and the ``refine_extrapolated`` best of
    those whose fit is :func:`extrapolated`) have a fitted magnitude farther than
    ``refine_tol`` of the range from every solved magnitude, solve them there (every phantom)
    and insert the point (:func:`~elastimap.gap.candidates.add_points`: the emulator's miss there becomes its
    interpolation error).  An effect that costs no solves (``Candidate.render``) is rendered
    at the fit instead, whenever the fit lies farther than ``RENDER_TOL`` of its range from its
    points.  Families refine their members at the family's fit.  Nothing is
    refined when the gap is not significant (the verdict does not depend on the candidates).
    An effect whose discretisation error does not carry over from the baseline
    (``Effect.own_model_error``: it remeshes, or it is the Poisson ratio) is also solved on the
    error mesh ``sim_fine`` at each refined magnitude, and that point is extrapolated with its own two levels
    (:func:`~elastimap.gap.model_error.correct_own`): the baseline's discretisation error does not carry over to another
    mesh (on the coarse mesh it moved by up to 1 % of the profile's peak between slab
    thicknesses of 20 and 23.8 mm).  Those error-mesh solves cost several coarse ones, so they
    are made only for the rows that could be reported this round (:func:`_reportable`: within
    ``ambiguity_margin`` of the best score, or a look-alike of the best); every such row is refined
    however far behind; a candidate refined farther behind keeps the baseline's correction.
    Returns (solves, rounds, error-mesh solve seconds); each candidate adds its solve seconds."""
    byname = {c.effect.name: c for c in C}
    solves = rounds = 0
    fine_seconds = 0.0
    for _ in range(st.refine_rounds):
        ev = evaluate_now()
        if not ev["significant"] or not ev["ranking"]:
            break
        want, rendered, close = _targets(ev["ranking"], byname, st)
        _render_at(rendered, byname, me)
        jobs = _jobs(want, byname, phantom_params(meas, sim.mesh))
        if not jobs:
            if rendered:
                rounds += 1
                continue
            break
        n_solved, sec = _solve_at(jobs, close, byname, meas, sim, sim_fine, sensor, settings, me)
        rounds += 1
        solves += n_solved
        fine_seconds += sec
    return solves, rounds, fine_seconds


def _targets(rows: list[dict], byname: dict, st: Settings):
    """The magnitudes this round adds: ({effect: magnitudes to solve}, {effect: magnitudes to
    render}, the effects of the rows that could be reported), from the ranking (best first)."""
    # pairs of effects (gap/selection.py) are refined only when one leads: the rest of them are the
    # single effects' own rows again (a member near its nominal), which refine those rows' fits
    rows = [r for i, r in enumerate(rows) if not r.get("pair") or i == 0]
    best = rows[0]["score"]
    want: dict[str, list[float]] = {}
    rendered: dict[str, list[float]] = {}  # no-solve effects: rendered exactly at the fit
    close: set[str] = set()  # effects of the rows that could be reported (_reportable)
    # rows whose emulator extrapolates at their fit (beyond every solved magnitude): their
    # score there is not measured, so the best refine_extrapolated of them are refined too
    extrap = [i for i, r in enumerate(rows) if extrapolated(r, byname, st.refine_tol)]
    extra = set(extrap[: st.refine_extrapolated])
    for i, r in enumerate(rows):
        could = _reportable(r, best, st)
        if i >= st.refine_top and r["score"] - best > st.refine_margin and i not in extra and not could:
            continue
        if could:
            close.update(r["members"])
        single = len(r["members"]) == 1
        for name, th in zip(r["members"], r["magnitude"]):
            _target(byname.get(name), name, th, single, want, rendered, st)
    return want, rendered, close


def _reportable(row: dict, best: float, st: Settings) -> bool:
    """Whether a ranking row could be reported with the best this round: within the ambiguity margin
    of the best score, or not told apart from the best by the look-alike rule
    (:func:`elastimap.gap.selection.told_apart`, recorded as ``vs_best``)."""
    return row["score"] - best <= st.ambiguity_margin or not row.get("vs_best", {"told_apart": True})["told_apart"]


def _target(c: Candidate | None, name: str, th: float, single: bool, want: dict, rendered: dict, st: Settings):
    """Add the fit ``th`` of one member to ``want`` (solve) or ``rendered`` when no solved or
    rendered magnitude lies near it."""
    # a single effect's fit at the end of its range: the range is extended (one step a
    # round) up to the effect's limits, since a real effect need not stay on the grid.
    # A family's members are not: with several parameters outside their grids a family
    # mimics effects that are not in the library (docs/history/gap.md, 'Blind benchmark, seed 4')
    out = None if c is None or len(c.grid) < 2 or not single else c.effect.beyond(th, *fit_range(c))
    if out is not None:
        # once per effect and magnitude (a family and its member may both ask for it)
        todo = (rendered if c.render is not None else want).setdefault(name, [])
        if all(abs(out - x) > 1e-9 * (c.effect.hi - c.effect.lo) for x in [*c.grid, *c.dropped, *todo]):
            todo.append(float(out))
            c.extended.append(float(out))
        return
    if c is not None and c.render is not None:
        tol = RENDER_TOL * (c.effect.hi - c.effect.lo)
        if min(abs(x - th) for x in list(c.grid) + rendered.get(name, [])) > tol:
            rendered.setdefault(name, []).append(float(th))
        return
    if c is None or not c.adaptive:
        return
    tol = st.refine_tol * (c.effect.hi - c.effect.lo)
    near = list(c.grid) + want.get(name, []) + c.dropped
    if min(abs(x - th) for x in near) <= tol:
        return
    want.setdefault(name, []).append(float(th))


def _render_at(rendered: dict, byname: dict, me: dict) -> None:
    """Render each no-solve effect at its new magnitudes (extrapolated with its own two levels
    when the error mesh's records are at hand) and insert them."""
    for name, ms in rendered.items():
        c = byname[name]
        ok = []
        for m in ms:
            if me.get("_fine_records") is not None and "_factor" in me:
                r = render_corrected(c, m, me)
            else:
                V, D = correct(*c.render(m), me)
                r = (V, D, None) if np.all(np.isfinite(V["features"])) else None
            if r is None:
                c.dropped.append(m)
            else:
                ok.append((m, r[0], r[1]))
        if ok:
            add_points(c, [m for m, _, _ in ok], [V for _, V, _ in ok], [D for _, _, D in ok])


def _jobs(want: dict, byname: dict, p0: list) -> list:
    """[(effect, magnitude, params per phantom)] to solve; an invalid magnitude is dropped."""
    jobs = []
    for name, ms in want.items():
        e = byname[name].effect
        for m in ms:
            try:
                jobs.append((name, m, [e.apply_params(p, m).validate() for p in p0]))
            except UserError:
                byname[name].dropped.append(m)
    return jobs


def _solve_at(jobs, close, byname, meas: Measured, sim, sim_fine, sensor, settings, me: dict):
    """Solve the jobs (and, for an effect with its own model error among ``close``, on the error
    mesh too), correct and insert them.  Returns (solves, error-mesh solve seconds)."""
    recs = sim.run([p for _, _, pl in jobs for p in pl])
    own = [j for j, (name, _, _) in enumerate(jobs) if byname[name].effect.own_model_error and name in close]
    if sim_fine is None or "_factor" not in me:
        own = []
    fine: dict[int, list] = {}
    fine_seconds = 0.0
    if own:
        pf = phantom_params(meas, sim_fine.mesh)
        rf = sim_fine.run([byname[jobs[j][0]].effect.apply_params(p, jobs[j][1]) for j in own for p in pf])
        fine = {j: rf[a * meas.n : (a + 1) * meas.n] for a, j in enumerate(own)}
        fine_seconds = sum(r.seconds for r in rf)
    solves = len(recs) + sum(len(v) for v in fine.values())
    new: dict[str, tuple[list, list, list, list]] = {}
    for j, (name, m, _pl) in enumerate(jobs):
        rj = recs[j * meas.n : (j + 1) * meas.n]
        V, D = sim_views(rj, sensor, settings)
        c = byname[name]
        c.solve_seconds = (c.solve_seconds or 0.0) + sum(r.seconds for r in rj)
        if not np.all(np.isfinite(V["features"])):
            c.dropped.append(m)
            continue
        V1, D1 = sim_views(fine[j], sensor, settings) if j in fine else (None, None)
        extra = None
        if V1 is not None and np.all(np.isfinite(V1["features"])):
            V, D, extra = correct_own(V, D, V1, D1, me)
            c.own_error.append(float(m))
        else:
            V, D = correct(V, D, me)
        a = new.setdefault(name, ([], [], [], []))
        a[0].append(m)
        a[1].append(V)
        a[2].append(D)
        a[3].append(extra)
    for name, (ms, Vs, Ds, extras) in new.items():
        c = byname[name]
        add_points(c, ms, Vs, Ds)
        own_extra = [e for e in extras if e is not None]
        if own_extra:  # its own model error beyond the baseline's, the largest over the new points
            c.interp_error = {
                k: np.hypot(c.interp_error[k], np.max([e[k] for e in own_extra], axis=0)) for k in c.interp_error
            }
    return solves, fine_seconds
