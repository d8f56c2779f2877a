"""The diagnosis: is there a gap beyond the model's own tolerance, which effect(s) explain it,
where it lies, how far it shrinks, and which measurement would tell look-alikes apart.

Notation: phantom i = 1..n with known (d, h, E)_i; for each phantom a vector of measured
quantities y_iq from one or more *views* (:mod:`elastimap.gap.views`: the three camera
features, the radial profile of the camera difference image, the plate force when measured)
with standard errors se_iq from the frame scatter; the baseline model's prediction y0_iq and
candidate c's prediction f_c(θ)_iq (θ its magnitude(s)).

* **Model error, measured.**  Every phantom's baseline is also solved on the next finer mesh
  level (``error_mesh``).  With Δ_iq = y0_iq(h) − y0_iq(h/r) and the refinement ratio r of the
  mesh sizes, the Richardson estimate of the discretisation error of the diagnosis mesh is
  σ_disc,iq = κ · max(|Δ_iq|, median_i(|Δ_iq| / |y0_iq|) · |y0_iq|), κ = 1 / (1 − r^(−p)),
  with the convergence order p per view (``order_image`` for features and profile,
  ``order_force`` for the force; measured on three levels, see docs/gap.md).  The median floor
  keeps a quantity whose two-level difference happens to cross zero from getting no error.
  Without a second level the error is the assumed floor ρ |y0| (``model_floor``; the report
  says "assumed").  Each candidate adds its magnitude-interpolation error σ_int,c (adaptive
  mechanics effects: the emulator's measured miss at its last refinement solve; full grids: the
  leave-one-magnitude-out PCHIP miss of the sweep / 4).  Total, per phantom and quantity:
  S_iq² = se_iq² + σ_disc,iq² + σ_int,c,iq²  (diagonal covariance).
* **Adaptive magnitudes** (:func:`refine`).  A mechanics effect is solved at its nominal and one
  sensitivity magnitude; while the gap is significant, the leading candidates are solved again at
  their fitted magnitude (every phantom) and the emulator's miss there is their interpolation error.
  An effect that costs no solves (optics: the camera alone; a linear model's plate travel: the
  baseline scaled) is rendered exactly at its fit the same way, so no candidate's fit rests on
  interpolation where it matters.
* **Calibrated tests.**  χ²_c = Σ_iq ((y − f_c)/S)² over N = n · Q terms.  The gap is
  **significant** when the baseline's χ²_0 > χ²_N(1 − α) (α = ``alpha``, 1 %), i.e. beyond
  the noise *and* the model's own tolerance.  A candidate **passes** when its held-out
  (leave-one-phantom-out, or 10-fold for n > 15) χ² ≤ χ²_N(1 − α).  α is fixed before any
  data are seen; nothing is tuned on the data scored.
* **Fit and intervals.**  Single effects: θ̂ minimises χ² over a dense PCHIP interpolation of
  the sweep; 95 % interval {θ : χ²(θ) − χ²_min ≤ 3.84 · c}, c = max(1, χ²_min / (N − 1)).
  Families (k parameters, composed f = y0 + Σ_l (f_l(θ_l) − y0)): coordinate descent on the
  members' dense grids; interval ±1.96 · sqrt(c · [2 H⁻¹]_ll) from the numerical Hessian H.
* **Selection and ambiguity.**  score_c = held-out χ²_c + k_c ln N.  If the best candidate
  passes, every candidate within ``ambiguity_margin`` (Δscore ≤ 2 ln 10 = 4.6, a likelihood
  ratio below 10) of it is reported with it: one → **explained**, several → **ambiguous**
  ("cannot be told apart with these phantoms").  Nothing passes → **unexplained**.  A family
  in the set whose fit moves one member only is reported as that member, one that moves all
  members by one factor as its nested common-factor effect (:func:`reported_set`).
* **What resolves an ambiguity** (:func:`propose`): the predicted separation in noise units
  sqrt(Σ ((f_a − f_b) / S)²) of every pair of the set for (i) the plate force at the same
  phantoms (force gauge error ``force_noise`` relative, plus the force model error), (ii) a
  second indentation depth (solved) and (iii) new phantoms in the design box, predicted by a
  linear emulator of z_c = (f_c − y0)/S in (ln d, h, ln E) over the measured phantoms and
  checked with solves at the best proposal.
* **Where**: by view and feature (relative gap, bootstrap CI), by region of (d, h, E), by
  stage (affine-recalibration share), by image region (mean residual map and annuli with the
  noise band sqrt(Σ_i se_i²)/n plus the per-pixel model error).
* **Shrink**: on withheld phantoms (every third) before/after, and (d, h, E) after retraining the
  inverse (``elastimap.training.api.fit_ensemble``) for a single-effect winner.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import stats
from scipy.interpolate import PchipInterpolator
from scipy.optimize import brentq, minimize_scalar

from elastimap.errors import UserError

from . import effects as fx
from . import views as vw
from .measured import FEATURES, Measured
from .simulate import Record, Simulator, base_params, camera_features_of

NDENSE = 401
#: an effect that costs no solves is rendered exactly at a fit farther than this fraction of its range from its points
RENDER_TOL = 1e-3
#: solve seconds (summed over workers, store hits count their stored time) by effect, this process
SOLVE_SECONDS: dict[str, float] = {}
FINER = {"tiny": "coarse", "coarse": "default", "default": "fine", "fine": None}


@dataclass
class Settings:
    alpha: float = 0.01  # level of the calibrated χ² tests
    ambiguity_margin: float = 4.6  # Δscore below which candidates cannot be told apart (2 ln 10)
    model_floor: float = 0.005  # relative model error, used only without a second mesh level
    order_image: float = 3.0  # convergence order p of features and profile (measured)
    order_force: float = 1.0  # convergence order p of the plate force (measured)
    richardson: bool = True  # correct the model by its Richardson estimate; σ = its spread over the orders below
    order_range_image: tuple = (2.0, 4.0)  # orders p bracketing the measured image order (3.4-3.8)
    order_range_force: tuple = (0.75, 1.5)  # orders p bracketing the measured force order (about 1)
    force_noise: float = 0.01  # relative standard error assumed for a plate-force gauge (proposals)
    second_delta: float = 4.5  # mm, the second indentation depth a proposal considers
    propose_phantoms: int = 4  # phantoms solved at the second depth
    propose_solves: bool = True  # run the solves that check a proposal
    families: tuple = fx.DEFAULT_FAMILIES
    bootstrap: int = 200
    seed: int = 0
    adaptive: bool = True  # mechanics magnitudes: sensitivity solve + refinement near the fit (else the grid)
    refine_rounds: int = 3  # at most this many refinement rounds
    refine_top: int = 2  # refine the best this many candidates ...
    refine_margin: float = 9.2  # ... and every one within this Δscore of the best (2 x ambiguity_margin)
    refine_extrapolated: int = 2  # ... and the best this many whose fit is extrapolated (beyond the solved magnitudes)
    refine_tol: float = 0.03  # a fit within this fraction of the effect's range of a solved magnitude is not re-solved
    inverse: bool = True
    n_train: int = 40
    train_repeats: int = 4
    train_epochs: int = 300


# ------------------------------------------------------------------ simulated views
def sim_views(recs, sensor, settings) -> tuple[dict, np.ndarray]:
    """Views {"features" (n,3), "profile" (n,K), "force" (n,1)} and difference images of records."""
    F, P, D, Fo = [], [], [], []
    for r in recs:
        v, d = camera_features_of(r, sensor, settings)
        F.append(v)
        D.append(d)
        P.append(
            vw.radial_profile(d, sensor.pixel_mm) if np.all(np.isfinite(d)) else np.full(len(vw.EDGES) - 1, np.nan)
        )
        Fo.append([r.force])
    return {"features": np.asarray(F), "profile": np.asarray(P), "force": np.asarray(Fo, float)}, np.asarray(D)


def measured_views(meas: Measured, sensor, settings) -> dict:
    """{view: (values (n,q), standard errors (n,q))} of the measured data."""
    out = {"features": (meas.y, meas.se)}
    if meas.has_images:
        P, Pse = [], []
        for D, Dse in zip(meas.difference, meas.difference_se):
            P.append(vw.radial_profile(D, sensor.pixel_mm))
            if Dse is None:  # no per-pixel noise given: the window's outer ring's scatter, uniform
                ring = np.zeros(D.shape, bool)
                w = max(2, D.shape[0] // 10)
                ring[:w, :] = ring[-w:, :] = ring[:, :w] = ring[:, -w:] = True
                Dse = np.full(D.shape, float(np.std(D[ring])))
            Pse.append(vw.profile_se(Dse, sensor.pixel_mm, settings.smooth_px))
        out["profile"] = (np.asarray(P), np.asarray(Pse))
    if meas.has_force:
        out["force"] = (meas.force[:, None], meas.force_se[:, None])
    return out


def decision_views(mv: dict) -> list[str]:
    """The views the verdict uses: the image profile when every phantom has an image, else the
    features; plus the force when measured (the features are always reported as a view)."""
    names = ["profile"] if "profile" in mv else ["features"]
    if "force" in mv:
        names.append("force")
    return names


def cat(d: dict, names) -> np.ndarray:
    return np.concatenate([d[k] for k in names], axis=-1)


# ------------------------------------------------------------------ candidates
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


def phantom_params(meas: Measured, mesh: str):
    return [base_params(mesh, *meas.dhe[i], tissue_E=meas.tissue_E[i]) for i in range(meas.n)]


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
    (:func:`refine` adds magnitudes near the fit)."""
    p0, linear, plan = solve_plan(meas, cands, sim.mesh, adaptive)
    flat = list(p0) + [p for _, _, pl, _ in plan if pl is not None for p in pl]
    recs = sim.run(flat)
    base = recs[: meas.n]
    V0, D0 = sim_views(base, sensor, settings)
    SOLVE_SECONDS["baseline"] = SOLVE_SECONDS.get("baseline", 0.0) + sum(r.seconds for r in base)
    if not np.all(np.isfinite(V0["features"])):
        bad = np.flatnonzero(~np.all(np.isfinite(V0["features"]), axis=1))
        raise UserError("measured", f"the baseline solve failed for phantom(s) {[meas.ids[i] for i in bad]}")
    pos = meas.n
    out = []
    for e in cands:
        ms, Vs, Ds, dropped = [], [], [], []
        for e2, m, _pl, how in plan:
            if e2 is not e:
                continue
            if how == "invalid":
                dropped.append(float(m))
                continue
            if how == "solve":
                V, D = sim_views(recs[pos : pos + meas.n], sensor, settings)
                SOLVE_SECONDS[e.name] = SOLVE_SECONDS.get(e.name, 0.0) + sum(
                    r.seconds for r in recs[pos : pos + meas.n]
                )
                pos += meas.n
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
        ad = adaptive and needs_solves(e, linear)

        def render(m, recs=None, e=e):
            recs = base if recs is None else recs
            if e.stage == "optics":
                return sim_views(recs, e.apply_sensor(sensor, m), settings)
            s = (p0[0].loading.delta + float(m)) / p0[0].loading.delta
            return sim_views([_scaled(r, s) for r in recs], sensor, settings)

        out.append(
            Candidate(
                e,
                np.asarray(ms)[order],
                {k: np.asarray([Vs[i][k] for i in order]) for k in V0},
                np.asarray(Ds)[order] if Ds else None,
                dropped,
                interp_error={k: np.zeros_like(v) for k, v in V0.items()} if ad else None,
                adaptive=ad,
                render=None if needs_solves(e, linear) else render,
            )
        )
    return V0, D0, out


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


# ------------------------------------------------------------------ model error
def model_error(
    meas: Measured, sim: Simulator, sim_fine: Simulator | None, sensor, settings, V0: dict, D0, st: Settings
) -> dict:
    """Per-phantom, per-quantity model error of the baseline (module docstring)."""
    if sim_fine is None or sim_fine.mesh == sim.mesh:
        sig = {k: st.model_floor * np.abs(v) for k, v in V0.items()}
        return {
            "kind": "assumed",
            "sigma": sig,
            "image_sigma": st.model_floor * np.abs(D0),
            "note": f"assumed floor {100 * st.model_floor:g} % of each quantity (no second mesh level)",
        }
    from elastimap.solver.geometry import LEVELS

    recs1 = sim_fine.run(phantom_params(meas, sim_fine.mesh))
    SOLVE_SECONDS["error_mesh"] = SOLVE_SECONDS.get("error_mesh", 0.0) + sum(r.seconds for r in recs1)
    V1, D1 = sim_views(recs1, sensor, settings)
    r = LEVELS[sim.mesh][0] / LEVELS[sim_fine.mesh][0]
    sig, rel, delta = {}, {}, {}
    for k, v in V0.items():
        p = st.order_force if k == "force" else st.order_image
        kappa = 1.0 / (1.0 - r ** (-p))
        d = v - V1[k]
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(np.abs(v) > 0, np.abs(d) / np.abs(v), 0.0)
        floor = np.nanmedian(frac, axis=0)
        sig[k] = kappa * np.maximum(np.abs(d), floor * np.abs(v))
        rel[k] = (np.median(sig[k] / np.maximum(np.abs(v), 1e-300), axis=0)).tolist()
        delta[k] = d
    kap_img = 1.0 / (1.0 - r ** (-st.order_image))
    kap = {k: 1.0 / (1.0 - r ** (-(st.order_force if k == "force" else st.order_image))) for k in V0}
    return {
        "kind": "measured",
        "sigma": sig,
        "image_sigma": kap_img * np.abs(D0 - D1),
        "delta": delta,
        "kappa": kap,
        "image_delta": D0 - D1,
        "kappa_image": kap_img,
        "fine_mesh": sim_fine.mesh,
        "ratio": r,
        "relative_median": rel,
        "fine_views": V1,
        "_fine_records": recs1,
        "note": f"Richardson estimate from meshes {sim.mesh} and {sim_fine.mesh} (h ratio {r:.3g}; "
        f"order {st.order_image:g} for image quantities, {st.order_force:g} for the force)",
    }


def profile_scale(v: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """s_i = <v_i, y0_i> / <y0_i, y0_i>: the size of a prediction's radial profile relative to the
    baseline's, per phantom (last axis: the annuli).  Exactly the factor of an effect that scales
    the image uniformly; dominated by the large inner annuli, so it stays well defined where one
    annulus of the baseline crosses zero."""
    return np.sum(v * y0, axis=-1) / np.maximum(np.sum(y0 * y0, axis=-1), 1e-300)


def richardson_correct(V0: dict, D0, C: list[Candidate], me: dict, st: Settings) -> tuple[dict, np.ndarray]:
    """Extrapolate every prediction to the converged mesh with the measured error.  The baseline:
    y0 − κ Δ, D0 − κ (D0 − D1).  A candidate's features and force are multiplied by the baseline's
    relative correction (1 − κ_q Δ_iq / y0_iq) (clipped to [0.5, 1.5]); its radial profile and
    images get the baseline's correction scaled by its profile's size, f − s_i κ Δ_i with
    s_i = :func:`profile_scale` (a per-annulus ratio would blow up where an annulus of the baseline
    crosses zero).  Returns the corrected baseline; candidates are corrected in place.  The model
    error σ (in ``me``, replaced) becomes the uncertainty of this extrapolation: the spread
    |κ(p_lo) − κ(p_hi)| · max(|Δ|, median floor) over the bracketing orders.  An effect that
    remeshes (or otherwise changes the discretisation error, ``Effect.own_model_error``) gets
    its own correction at its refined magnitudes (:func:`refine`)."""
    r = me["ratio"]

    def kap(p):
        return 1.0 / (1.0 - r ** (-p))

    fac, spread = {}, {}
    for k, v in V0.items():
        with np.errstate(divide="ignore", invalid="ignore"):
            f = 1.0 - me["kappa"][k] * me["delta"][k] / v
        fac[k] = np.clip(np.where(np.isfinite(f), f, 1.0), 0.5, 1.5)
        lo, hi = st.order_range_force if k == "force" else st.order_range_image
        spread[k] = abs(kap(lo) - kap(hi))
        me["sigma"][k] = me["sigma"][k] / me["kappa"][k] * spread[k]
        me["relative_median"][k] = np.median(me["sigma"][k] / np.maximum(np.abs(v), 1e-300), axis=0).tolist()
    me["_spread"] = spread
    lo, hi = st.order_range_image
    me["image_sigma"] = me["image_sigma"] / me["kappa_image"] * abs(kap(lo) - kap(hi))
    me["_factor"], me["_dD"] = fac, me["kappa_image"] * me["image_delta"]
    me["_dprofile"] = me["kappa"]["profile"] * me["delta"]["profile"] if "profile" in V0 else None
    me["_profile0"] = V0["profile"] if "profile" in V0 else None
    for c in C:
        if c.render is not None and me.get("_fine_records") is not None:
            own_correct_rendered(c, me)
        else:
            c.V, c.D = correct(c.V, c.D, me)
    return correct(V0, D0, me)


def render_corrected(c: Candidate, m: float, me: dict):
    """A no-solve effect at magnitude m, extrapolated with its own two levels: the camera (or the
    plate-travel scaling) applied to the baseline records of both meshes, then :func:`correct_own`.
    The camera is nonlinear (saturation, gamma), so the baseline's correction, made through the
    nominal camera, is not the correction through another one.  Returns (views, images, σ beyond
    the baseline's) or None when the views are not finite; records its own Δ (``own_delta``).
    That σ is not used: σ enters the χ² score, and a σ of the candidate's own (here largest at
    the strongest magnitudes) would favour the candidate with the larger σ; the candidate keeps
    the baseline's σ like every effect on the baseline's mesh, and its own order uncertainty
    enters its interval as its own signed mode (:meth:`Single.own_delta`)."""
    V, D = c.render(m)
    V1, D1 = c.render(m, me["_fine_records"])
    if not (np.all(np.isfinite(V["features"])) and np.all(np.isfinite(V1["features"]))):
        return None
    c.own_delta.append((float(m), {k: V[k] - V1[k] for k in V}))
    return correct_own(V, D, V1, D1, me)


def own_correct_rendered(c: Candidate, me: dict) -> None:
    """Replace a no-solve candidate's sweep by :func:`render_corrected` at every magnitude."""
    keep, Vs, Ds = [], [], []
    for m in c.grid:
        r = render_corrected(c, float(m), me)
        if r is None:
            c.dropped.append(float(m))
            continue
        keep.append(float(m))
        Vs.append(r[0])
        Ds.append(r[1])
    c.grid = np.asarray(keep)
    c.V = {k: np.asarray([v[k] for v in Vs]) for k in c.V}
    c.D = np.asarray(Ds) if c.D is not None else None


def correct(V: dict, D, me: dict):
    """The Richardson extrapolation of :func:`richardson_correct` applied to one prediction (views
    (..., n, q), images (..., n, ny, nx)); unchanged when the model error is not extrapolated."""
    if "_factor" not in me:
        return V, D
    out = {k: v * me["_factor"][k] for k, v in V.items() if k != "profile"}
    s = None
    if "profile" in V:
        s = profile_scale(V["profile"], me["_profile0"])
        out["profile"] = V["profile"] - s[..., None] * me["_dprofile"]
    if D is not None:
        D = D - (s[..., None, None] if s is not None else 1.0) * me["_dD"]
    return out, D


def correct_own(V: dict, D, V1: dict, D1, me: dict):
    """Richardson extrapolation of a prediction with its own second mesh level (V1, D1 on the
    error mesh at the same magnitude): y − κ_q (y − y1), D − κ (D − D1).  Also returns the part of
    its own model error σ_own = spread_q · |y − y1| (as in :func:`richardson_correct`) beyond the
    baseline's σ, sqrt(max(σ_own² − σ_0², 0)) per phantom and quantity."""
    out = {k: v - me["kappa"][k] * (v - V1[k]) for k, v in V.items()}
    extra = {
        k: np.sqrt(np.maximum((me["_spread"][k] * np.abs(v - V1[k])) ** 2 - me["sigma"][k] ** 2, 0.0))
        for k, v in V.items()
    }
    return out, (None if D is None else D - me["kappa_image"] * (D - D1)), extra


def fit_range(c: Candidate) -> tuple[float, float]:
    """The magnitudes a candidate is fitted over: adaptive, the effect's grid range or beyond it
    where points were solved; a full sweep (or a rendered effect), its valid points."""
    if c.adaptive:
        return float(min(c.effect.lo, c.grid.min())), float(max(c.effect.hi, c.grid.max()))
    return float(c.grid.min()), float(c.grid.max())


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
    and insert the point (:func:`add_points`: the emulator's miss there becomes its
    interpolation error).  An effect that costs no solves (``Candidate.render``) is rendered
    at the fit instead, whenever the fit lies farther than ``RENDER_TOL`` of its range from its
    points.  Families refine their members at the family's fit.  Nothing is
    refined when the gap is not significant (the verdict does not depend on the candidates).
    An effect whose discretisation error does not carry over from the baseline
    (``Effect.own_model_error``: it remeshes, or it is the Poisson ratio) is also solved on the
    error mesh ``sim_fine`` at each refined magnitude, and that point is extrapolated with its own two levels
    (:func:`correct_own`): the baseline's discretisation error does not carry over to another
    mesh (on the coarse mesh it moved by up to 1 % of the profile's peak between slab
    thicknesses of 20 and 23.8 mm).  Those error-mesh solves cost several coarse ones, so they
    are made only for the rows that could be reported this round (within ``ambiguity_margin``
    of the best score); a candidate refined farther behind keeps the baseline's correction.
    Returns (solves, rounds)."""
    byname = {c.effect.name: c for c in C}
    p0 = phantom_params(meas, sim.mesh)
    solves = rounds = 0
    for _ in range(st.refine_rounds):
        ev = evaluate_now()
        if not ev["significant"] or not ev["ranking"]:
            break
        rows = ev["ranking"]
        best = rows[0]["score"]
        want: dict[str, list[float]] = {}
        rendered: dict[str, list[float]] = {}  # no-solve effects: rendered exactly at the fit
        close: set[str] = set()  # effects of the rows that could be reported (within the ambiguity margin)
        # rows whose emulator extrapolates at their fit (beyond every solved magnitude): their
        # score there is not measured, so the best refine_extrapolated of them are refined too
        extrap = [i for i, r in enumerate(rows) if extrapolated(r, byname, st.refine_tol)]
        extra = set(extrap[: st.refine_extrapolated])
        for i, r in enumerate(rows):
            if i >= st.refine_top and r["score"] - best > st.refine_margin and i not in extra:
                continue
            if r["score"] - best <= st.ambiguity_margin:
                close.update(r["members"])
            single = len(r["members"]) == 1
            for name, th in zip(r["members"], r["magnitude"]):
                c = byname.get(name)
                # a single effect's fit at the end of its range: the range is extended (one step a
                # round) up to the effect's limits, since a real effect need not stay on the grid.
                # A family's members are not: with several parameters outside their grids a family
                # mimics effects that are not in the library (seed-4 blind run, aspect ratio)
                out = None if c is None or len(c.grid) < 2 or not single else c.effect.beyond(th, *fit_range(c))
                if out is not None:
                    # once per effect and magnitude (a family and its member may both ask for it)
                    todo = (rendered if c.render is not None else want).setdefault(name, [])
                    if all(abs(out - x) > 1e-9 * (c.effect.hi - c.effect.lo) for x in [*c.grid, *c.dropped, *todo]):
                        todo.append(float(out))
                        c.extended.append(float(out))
                    continue
                if c is not None and c.render is not None:
                    tol = RENDER_TOL * (c.effect.hi - c.effect.lo)
                    if min(abs(x - th) for x in list(c.grid) + rendered.get(name, [])) > tol:
                        rendered.setdefault(name, []).append(float(th))
                    continue
                if c is None or not c.adaptive:
                    continue
                tol = st.refine_tol * (c.effect.hi - c.effect.lo)
                near = list(c.grid) + want.get(name, []) + c.dropped
                if min(abs(x - th) for x in near) <= tol:
                    continue
                want.setdefault(name, []).append(float(th))
        jobs = []
        for name, ms in want.items():
            e = byname[name].effect
            for m in ms:
                try:
                    jobs.append((name, m, [e.apply_params(p, m).validate() for p in p0]))
                except UserError:
                    byname[name].dropped.append(m)
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
        if not jobs:
            if rendered:
                rounds += 1
                continue
            break
        recs = sim.run([p for _, _, pl in jobs for p in pl])
        own = [j for j, (name, _, _) in enumerate(jobs) if byname[name].effect.own_model_error and name in close]
        if sim_fine is None or "_factor" not in me:
            own = []
        fine: dict[int, list] = {}
        if own:
            pf = phantom_params(meas, sim_fine.mesh)
            rf = sim_fine.run([byname[jobs[j][0]].effect.apply_params(p, jobs[j][1]) for j in own for p in pf])
            fine = {j: rf[a * meas.n : (a + 1) * meas.n] for a, j in enumerate(own)}
            SOLVE_SECONDS["error_mesh"] = SOLVE_SECONDS.get("error_mesh", 0.0) + sum(r.seconds for r in rf)
        rounds += 1
        solves += len(recs) + sum(len(v) for v in fine.values())
        new: dict[str, tuple[list, list, list]] = {}
        for j, (name, m, _pl) in enumerate(jobs):
            V, D = sim_views(recs[j * meas.n : (j + 1) * meas.n], sensor, settings)
            sec = sum(r.seconds for r in recs[j * meas.n : (j + 1) * meas.n])
            SOLVE_SECONDS[name] = SOLVE_SECONDS.get(name, 0.0) + sec
            if not np.all(np.isfinite(V["features"])):
                byname[name].dropped.append(m)
                continue
            V1, D1 = sim_views(fine[j], sensor, settings) if j in fine else (None, None)
            extra = None
            if V1 is not None and np.all(np.isfinite(V1["features"])):
                V, D, extra = correct_own(V, D, V1, D1, me)
                byname[name].own_error.append(float(m))
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
    return solves, rounds


# ------------------------------------------------------------------ models (fit, predict, interval)
def _interp_error(g: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Leave-one-magnitude-out PCHIP miss over the interior grid points, / 4 (halved spacing)."""
    if len(g) < 3:
        return np.zeros(Y.shape[1:])
    err = np.zeros(Y.shape[1:])
    for k in range(1, len(g) - 1):
        keep = np.r_[0:k, k + 1 : len(g)]
        err = np.maximum(err, np.abs(Y[k] - PchipInterpolator(g[keep], Y[keep], axis=0)(g[k])))
    return 0.25 * err


def chi2(y, f, S) -> np.ndarray:
    return np.sum(((y - f) / S) ** 2, axis=-1)


def with_systematic(mdl, y, S, th, stat: list, sys) -> list[tuple[float, float]]:
    """Widen statistical intervals by the shift a coherent model error causes: refit with the
    data moved by +e and by −e in every quantity at once, for each coherent error mode e, and add
    the largest shift on each side in quadrature.  ``sys``: one mode (an array like ``y``) or a
    list of modes.  The diagnosis passes two (:func:`systematic_modes`): σ_sys in every quantity
    (the mesh error is one-signed across phantoms) and the signed shift of the Richardson
    extrapolation when the convergence order is off."""
    modes = [m for m in (sys if isinstance(sys, (list, tuple)) else [sys]) if m is not None and np.any(m != 0)]
    if not modes:
        return stat
    idx = np.arange(y.shape[0])
    fits = [mdl.fit(y + sgn * e, S, idx) for e in modes for sgn in (1.0, -1.0)]
    out = []
    for l, (lo, hi) in enumerate(stat):
        t = float(th[l])
        dlo = max(0.0, t - min(f[l] for f in fits))
        dhi = max(0.0, max(f[l] for f in fits) - t)
        g = mdl.grid_of(l)
        out.append((float(max(g.min(), t - math.hypot(t - lo, dlo))), float(min(g.max(), t + math.hypot(hi - t, dhi)))))
    return out


def systematic_modes(me: dict, names) -> tuple[list[np.ndarray], np.ndarray | None]:
    """The coherent model-error modes the intervals are widened by (:func:`with_systematic`):
    σ_sys itself (one sign in every quantity), and, when the predictions were extrapolated
    (:func:`richardson_correct`), the signed error of that extrapolation if the order p is off
    by the bracketing range: spread_q · Δ_iq (Δ = coarse − error mesh, per phantom and quantity),
    the direction every prediction moves when p does.  Also returns spread_q per term, with
    which a candidate that has its own Δ (:meth:`Single.own_delta`) gets its own signed mode."""
    modes = [cat(me["sigma"], names)]
    spread = None
    if "_spread" in me and "delta" in me:
        modes.append(cat({k: me["_spread"][k] * me["delta"][k] for k in names}, names))
        spread = cat({k: np.full_like(me["delta"][k], me["_spread"][k]) for k in names}, names)
    return modes, spread


def jackknife_interval(mdl, th, th_folds: np.ndarray) -> list[tuple[float, float]] | None:
    r"""The fit's 95 % interval from its spread over the held-out folds (grouped jackknife):
    with θ̂_(k) fitted without fold k (g folds),

    $$ \widehat{\rm var}(\hat\theta) = \frac{g-1}{g} \sum_k (\hat\theta_{(k)} - \bar\theta)^2,
       \qquad \hat\theta \pm t_{0.975,\,g-1} \sqrt{\widehat{\rm var}} $$

    (Efron & Tibshirani 1993, ch. 11).  It measures how much the estimate depends on which
    phantoms it sees, whatever the cause: noise, and a model-form error that differs from
    phantom to phantom, which the likelihood interval (its error model: noise + the measured
    discretisation error) does not hold.  None with fewer than 3 folds."""
    g = len(th_folds)
    if g < 3:
        return None
    th_folds = np.atleast_2d(np.asarray(th_folds, float).reshape(g, -1))
    var = (g - 1) / g * np.sum((th_folds - th_folds.mean(axis=0)) ** 2, axis=0)
    hw = float(stats.t.ppf(0.975, g - 1)) * np.sqrt(var)
    out = []
    for l, (t, w) in enumerate(zip(np.atleast_1d(th), hw)):
        span = mdl.grid_of(l)
        out.append((float(max(span.min(), t - w)), float(min(span.max(), t + w))))
    return out


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


class Single:
    """One effect, one magnitude, over the effect's whole range [lo, hi]: interpolated between
    the solved magnitudes (the full grid, or the adaptive points), extrapolated linearly beyond."""

    def __init__(self, c: Candidate, names):
        self.c, self.name, self.k, self.names = c, c.effect.name, 1, list(names)
        self.effect, self.stage, self.unit = c.effect, c.effect.stage, c.effect.unit
        self.grid = c.grid
        self.lo, self.hi = fit_range(c)
        self.Y = cat(c.V, self.names)  # (K, n, Q)
        self._pchip = Interp(self.grid, self.Y)
        if self.hi > self.lo and len(self.grid) > 1:
            self.dense = np.linspace(self.lo, self.hi, NDENSE)
            self.dense_Y = self._pchip(self.dense)
        else:
            self.dense, self.dense_Y = self.grid.copy(), self.Y.copy()
        self.interp = (
            cat(c.interp_error, self.names) if c.interp_error is not None else _interp_error(self.grid, self.Y)
        )

    def span(self):
        return np.array([self.lo, self.hi]) if len(self.grid) > 1 else np.array([self.grid[0], self.grid[0]])

    @property
    def labels(self):
        return [self.name]

    def grid_of(self, l):
        return self.span()

    def predict(self, th, names=None) -> np.ndarray:
        m = float(np.clip(float(np.atleast_1d(th)[0]), *self.span()))
        if names is None or list(names) == self.names:
            return self._pchip(m)
        return Interp(self.grid, cat(self.c.V, names))(m)

    def image(self, th):
        D, g = self.c.D, self.grid
        if D is None:
            return None
        m = float(np.atleast_1d(th)[0])
        k = int(np.clip(np.searchsorted(g, m), 1, len(g) - 1)) if len(g) > 1 else 0
        if len(g) == 1:
            return D[0]
        t = float(np.clip((m - g[k - 1]) / (g[k] - g[k - 1]), 0, 1))
        return (1 - t) * D[k - 1] + t * D[k]

    def own_delta(self, th) -> np.ndarray | None:
        """Its own level difference Δ at magnitude th (linear between the magnitudes it was
        measured at), or None (the baseline's Δ stands for it)."""
        pts = sorted(self.c.own_delta, key=lambda x: x[0])
        if not pts:
            return None
        ms = np.array([m for m, _ in pts])
        D = np.array([cat(d, self.names) for _, d in pts])
        m = float(np.clip(float(np.atleast_1d(th)[0]), ms[0], ms[-1]))
        k = int(np.clip(np.searchsorted(ms, m), 1, len(ms) - 1)) if len(ms) > 1 else 0
        if len(ms) == 1:
            return D[0]
        t = (m - ms[k - 1]) / max(ms[k] - ms[k - 1], 1e-300)
        return (1 - t) * D[k - 1] + t * D[k]

    def tie(self) -> np.ndarray:
        """A negligible preference for the nominal magnitude, so that a flat χ² (an effect these
        phantoms do not see) fits the nominal, not a grid end."""
        span = max(float(self.hi - self.lo), 1e-300)
        return 1e-9 * ((self.dense - self.effect.nominal) / span) ** 2

    def _chi(self, m, y, S, idx) -> float:
        return float(chi2(y[idx], self.predict(m)[idx], S[idx]).sum())

    def fit(self, y, S, idx) -> np.ndarray:
        """Dense-grid argmin, then refined between the neighbouring dense points (bounded Brent):
        with precise data the dense spacing alone is coarser than the fit's resolution."""
        tot = chi2(y[idx], self.dense_Y[:, idx], S[idx]).sum(axis=1)
        k = int(np.argmin(tot + self.tie() * (1 + tot.min())))
        if len(self.dense) < 3:
            return np.array([self.dense[k]])
        lo, hi = self.dense[max(k - 1, 0)], self.dense[min(k + 1, len(self.dense) - 1)]
        r = minimize_scalar(
            lambda m: self._chi(m, y, S, idx),
            bounds=(lo, hi),
            method="bounded",
            options={"xatol": 1e-7 * (self.hi - self.lo)},
        )
        m = float(r.x) if r.fun < tot[k] else float(self.dense[k])
        return np.array([m])

    def interval(self, y, S, th) -> list[tuple[float, float]]:
        """{m : χ²(m) − χ²(m̂) ≤ 3.84 c}: the crossings located on the dense grid, then refined (Brent)."""
        m0 = float(th[0])
        idx = np.arange(y.shape[0])
        f0 = self._chi(m0, y, S, idx)
        N = y.size
        c = max(1.0, f0 / max(N - 1, 1))
        thr = 3.84 * c
        tot = chi2(y, self.dense_Y, S).sum(axis=1) - f0 - thr
        g = lambda m: self._chi(m, y, S, idx) - f0 - thr  # noqa: E731
        out = []
        left = np.flatnonzero((self.dense < m0) & (tot > 0))
        if len(left):
            a = self.dense[left[-1]]
            out.append(float(brentq(g, a, m0)) if g(a) > 0 > g(m0) else float(a))
        else:
            out.append(float(self.span()[0]))
        right = np.flatnonzero((self.dense > m0) & (tot > 0))
        if len(right):
            b = self.dense[right[0]]
            out.append(float(brentq(g, m0, b)) if g(b) > 0 > g(m0) else float(b))
        else:
            out.append(float(self.span()[1]))
        return [(out[0], out[1])]

    def at_edge(self, th) -> bool:
        m = float(th[0])
        return bool(len(self.grid) > 1 and (abs(m - self.lo) < 1e-9 or abs(m - self.hi) < 1e-9))

    def params_at(self, p, th):
        return self.effect.apply_params(p, float(th[0]))

    def sensor_at(self, s, th):
        return self.effect.apply_sensor(s, float(th[0]))

    def nominal(self):
        return [self.effect.nominal]

    def units(self):
        return [self.unit]


class Composed:
    """A family: f(θ) = y0 + Σ_l (f_l(θ_l) − y0), fitted by coordinate descent."""

    def __init__(self, fam: fx.Family, members: list[Single], y0: np.ndarray, V0: dict):
        self.fam, self.name, self.members, self.k = fam, fam.name, members, len(members)
        self.names, self.stage, self.y0, self.V0 = members[0].names, fam.stage, y0, V0
        self.unit = "/".join(m.unit for m in members)
        self.interp = np.sqrt(sum(m.interp**2 for m in members))
        self.grid = members[0].grid
        self.effect = None
        #: each member is held inside its effect's grid range (an extension of a member's own
        #: range, made for its single fit, is not the family's)
        self.bounds = [(max(m.lo, m.effect.lo), min(m.hi, m.effect.hi)) for m in members]

    @property
    def labels(self):
        return [m.name for m in self.members]

    def grid_of(self, l):
        return np.array(self.bounds[l]) if len(self.members[l].grid) > 1 else self.members[l].span()

    def predict(self, th, names=None) -> np.ndarray:
        base = self.y0 if names is None or list(names) == self.names else cat(self.V0, names)
        return base + sum(m.predict(t, names) - base for m, t in zip(self.members, th))

    def image(self, th):
        Ds = [m.image(t) for m, t in zip(self.members, th)]
        if any(D is None for D in Ds):
            return None
        D0 = self.members[0].c.D[np.argmin(np.abs(self.members[0].grid - self.members[0].effect.nominal))]
        return D0 + sum(D - D0 for D in Ds)

    def fit(self, y, S, idx) -> np.ndarray:
        th = np.array([m.effect.nominal for m in self.members], float)
        parts = [m.predict(t) - self.y0 for m, t in zip(self.members, th)]
        for _ in range(4):
            for l, m in enumerate(self.members):
                rest = self.y0 + sum(p for j, p in enumerate(parts) if j != l)
                a, b = self.bounds[l]
                ok = (m.dense >= a - 1e-12) & (m.dense <= b + 1e-12)
                f = rest[None] + (m.dense_Y[ok] - self.y0[None])
                tot = chi2(y[idx], f[:, idx], S[idx]).sum(axis=1)
                th[l] = m.dense[ok][int(np.argmin(tot + m.tie()[ok] * (1 + tot.min())))]
                parts[l] = m.predict(th[l]) - self.y0
        for _ in range(2):  # refine each parameter between its neighbouring dense points
            for l, m in enumerate(self.members):
                step = (m.hi - m.lo) / (NDENSE - 1)
                if step <= 0:
                    continue
                rest = self.y0 + sum(p for j, p in enumerate(parts) if j != l)
                fun = lambda t, rest=rest, m=m: float(chi2(y[idx], (rest + m.predict(t) - self.y0)[idx], S[idx]).sum())
                lo, hi = max(self.bounds[l][0], th[l] - step), min(self.bounds[l][1], th[l] + step)
                r = minimize_scalar(fun, bounds=(lo, hi), method="bounded", options={"xatol": 1e-7 * step * NDENSE})
                if r.fun < fun(th[l]):
                    th[l] = float(r.x)
                    parts[l] = m.predict(th[l]) - self.y0
        return th

    def interval(self, y, S, th) -> list[tuple[float, float]]:
        th = np.asarray(th, float)
        spans = np.array([m.hi - m.lo for m in self.members])
        h = 0.01 * spans

        def F(t):
            return float(chi2(y, self.predict(t), S).sum())

        k = self.k
        H = np.zeros((k, k))
        f0 = F(th)
        for a in range(k):
            for b in range(a, k):
                ea, eb = np.eye(k)[a] * h[a], np.eye(k)[b] * h[b]
                H[a, b] = H[b, a] = (F(th + ea + eb) - F(th + ea - eb) - F(th - ea + eb) + F(th - ea - eb)) / (
                    4 * h[a] * h[b]
                )
        c = max(1.0, f0 / max(y.size - k, 1))
        try:
            cov = 2.0 * np.linalg.inv(H) * c
            sd = np.sqrt(np.clip(np.diag(cov), 0, None))
            if not np.all(np.isfinite(sd)) or np.any(np.diag(cov) <= 0):
                raise np.linalg.LinAlgError
        except np.linalg.LinAlgError:
            sd = spans  # not identifiable from these phantoms: the whole grid
        return [(float(max(a, t - 1.96 * s)), float(min(b, t + 1.96 * s))) for (a, b), t, s in zip(self.bounds, th, sd)]

    def at_edge(self, th) -> bool:
        return any(
            len(m.grid) > 1 and (abs(t - a) < 1e-9 or abs(t - b) < 1e-9)
            for m, (a, b), t in zip(self.members, self.bounds, th)
        )

    def params_at(self, p, th):
        for m, t in zip(self.members, th):
            p = m.params_at(p, [t])
        return p

    def sensor_at(self, s, th):
        for m, t in zip(self.members, th):
            s = m.sensor_at(s, [t])
        return s

    def nominal(self):
        return [m.effect.nominal for m in self.members]

    def units(self):
        return [m.unit for m in self.members]


def build_models(C: list[Candidate], names, V0: dict, st: Settings) -> list:
    singles = [Single(c, names) for c in C]
    byname = {m.name: m for m in singles}
    y0 = cat(V0, names)
    fams = [
        Composed(f, [byname[n] for n in f.members], y0, V0) for f in fx.families_for([c.effect for c in C], st.families)
    ]
    return singles + fams


# ------------------------------------------------------------------ statistics
def folds(n: int, seed: int) -> list[np.ndarray]:
    if n <= 15:
        return [np.array([i]) for i in range(n)]
    perm = np.random.default_rng(seed).permutation(n)
    return [perm[k::10] for k in range(10)]


def bootstrap_ci(values: np.ndarray, stat, B: int, rng) -> tuple[float, float]:
    n = len(values)
    if n < 2:
        return (math.nan, math.nan)
    bs = [stat(values[rng.integers(0, n, n)]) for _ in range(B)]
    return float(np.percentile(bs, 2.5)), float(np.percentile(bs, 97.5))


def slices(V: dict, names) -> dict:
    out, a = {}, 0
    for k in names:
        q = V[k].shape[-1]
        out[k] = slice(a, a + q)
        a += q
    return out


def evaluate(y, S0, y0, models, n: int, st: Settings, sl: dict, sys=None, spread=None) -> dict:
    """Calibrated significance, per-candidate held-out fit, ranking, ambiguity set, outcome."""
    N = y.size
    chi0 = float(chi2(y, y0, S0).sum())
    thr = float(stats.chi2.ppf(1 - st.alpha, N))
    F = folds(n, st.seed)
    rows = []
    for mdl in models:
        S = np.sqrt(S0**2 + mdl.interp**2)
        pred = np.zeros_like(y)
        th_folds = []
        for te in F:
            tr = np.setdiff1d(np.arange(n), te)
            th_k = mdl.fit(y, S, tr)
            th_folds.append(th_k)
            pred[te] = mdl.predict(th_k)[te]
        held = ((y - pred) / S) ** 2
        ssr_cv = float(held.sum())
        th = mdl.fit(y, S, np.arange(n))
        own = mdl.own_delta(th) if (spread is not None and hasattr(mdl, "own_delta")) else None
        modes = sys if own is None else [sys[0], spread * own]
        ci_lik = with_systematic(mdl, y, S, th, mdl.interval(y, S, th), modes)
        ci_jk = jackknife_interval(mdl, th, np.array(th_folds))
        ci = [(min(a[0], b[0]), max(a[1], b[1])) for a, b in zip(ci_lik, ci_jk)] if ci_jk else ci_lik
        f = mdl.predict(th)
        rows.append(
            {
                "effect": mdl.name,
                "members": mdl.labels,
                "stage": mdl.stage,
                "unit": mdl.unit,
                "n_params": mdl.k,
                "magnitude": [float(t) for t in th],
                "magnitude_ci": [list(c) for c in ci],
                "magnitude_ci_likelihood": [list(c) for c in ci_lik],
                "magnitude_ci_jackknife": [list(c) for c in ci_jk] if ci_jk else None,
                "nominal": mdl.nominal(),
                "units": mdl.units(),
                "ssr_cv": ssr_cv,
                "chi2_fit": float(chi2(y, f, S).sum()),
                "explained_fraction": 1.0 - ssr_cv / chi0 if chi0 > 0 else 0.0,
                "reduced_chi2_cv": ssr_cv / N,
                "passes": bool(ssr_cv <= thr),
                "p_value_cv": float(stats.chi2.sf(ssr_cv, N)),
                "chi2_cv_by_view": {k: float(held[:, s].sum()) for k, s in sl.items()},
                "score": ssr_cv + mdl.k * math.log(N),
                "at_grid_edge": mdl.at_edge(th),
                "dropped_magnitudes": getattr(getattr(mdl, "c", None), "dropped", []),
                "_model": mdl,
                "_theta": th,
                "_S": S,
            }
        )
    rows.sort(key=lambda r: r["score"])
    significant = chi0 > thr
    best = rows[0] if rows else None
    ambiguity, reported = [], {}
    if not significant:
        outcome = "no significant gap"
    elif best and best["passes"]:
        reported = reported_set([r for r in rows if r["score"] - best["score"] <= st.ambiguity_margin], rows)
        ambiguity = list(reported)
        outcome = "explained" if len(ambiguity) == 1 else "ambiguous"
    else:
        outcome = "unexplained"
    for r in rows:
        r["delta_score"] = r["score"] - best["score"]
    return {
        "chi2_baseline": chi0,
        "n_terms": N,
        "chi2_threshold": thr,
        "alpha": st.alpha,
        "reduced_chi2_baseline": chi0 / N,
        "p_value_baseline": float(stats.chi2.sf(chi0, N)),
        "significant": significant,
        "ranking": rows,
        "outcome": outcome,
        "winner": ambiguity[0] if outcome == "explained" else None,
        "ambiguous_set": ambiguity if outcome in ("explained", "ambiguous") else [],
        "reported": reported,
        "best": best["effect"] if best else None,
        "runner_up": rows[1]["effect"] if len(rows) > 1 else None,
    }


def isolated_member(row: dict) -> str | None:
    """The member a family's fit names alone: the only member whose 95 % interval excludes its
    nominal magnitude while every other member's interval holds its nominal (None for a single
    effect, or when no member or several are off)."""
    members = row.get("members", [])
    if len(members) < 2:
        return None
    off = [not (lo <= nom <= hi) for (lo, hi), nom in zip(row["magnitude_ci"], row["nominal"])]
    return members[off.index(True)] if sum(off) == 1 else None


def common_factor(row: dict) -> tuple[str, tuple[float, float]] | None:
    """The nested single effect a family's fit names when it moves every member by one common
    factor (``Family.common``, e.g. ``probe_moduli`` in ``probe_layers_E``): the members' 95 %
    intervals as ratios to their nominal values, [lo_l/m_l, hi_l/m_l], have a common part that
    excludes 1 (so every member is off, all by a factor the data cannot tell apart).  Returns
    (that effect, the common part), or None."""
    fam = fx.FAMILIES.get(row.get("effect"))
    if fam is None or fam.common is None or list(row.get("members", [])) != list(fam.members):
        return None
    if any(nom <= 0 for nom in row["nominal"]):
        return None
    lo = max(a / nom for (a, _), nom in zip(row["magnitude_ci"], row["nominal"]))
    hi = min(b / nom for (_, b), nom in zip(row["magnitude_ci"], row["nominal"]))
    if lo > hi or lo <= 1.0 <= hi:
        return None
    return fam.common, (float(lo), float(hi))


def reported_set(rows: list[dict], ranking: list[dict] | None = None) -> dict:
    """The reported effects of the rows that cannot be told apart (best first), by name:
    magnitude, interval, unit and the ranking row they come from.  A family whose fit isolates
    one member (:func:`isolated_member`) is reported as that member with the family's fitted
    magnitude ("via" the family): its other parameters add nothing the data ask for, so the
    nested single effect is the statement (the family's extra freedom may still fit the
    model-form error better, which is why it can outscore the member's own fit).  A name
    reported twice keeps its first (better-scored) entry.  Likewise a family whose fit moves
    all members by one factor (:func:`common_factor`) is reported as its nested common-factor
    effect, with that effect's own fit from ``ranking`` (all rows) when it was a candidate, else
    with the members' geometric-mean ratio and the common part of their intervals."""
    out: dict[str, dict] = {}
    own = {r["effect"]: r for r in (ranking or rows)}
    for r in rows:
        cf = common_factor(r)
        if cf is not None and cf[0] not in out:
            name, (lo, hi) = cf
            o = own.get(name)
            if o is not None:
                mag, ci, units = o["magnitude"], o["magnitude_ci"], o["units"]
            else:
                ratios = [t / nom for t, nom in zip(r["magnitude"], r["nominal"])]
                g = float(np.exp(np.mean(np.log(np.maximum(ratios, 1e-300)))))
                mag, ci, units = [float(np.clip(g, lo, hi))], [[lo, hi]], [fx.get(name).unit]
            out[name] = {
                "magnitude": list(mag),
                "magnitude_ci": [list(c) for c in ci],
                "members": [name],
                "units": list(units),
                "via": r["effect"],
                "via_kind": "common factor",
                "_row": o if o is not None else r,
            }
            continue
        if cf is not None:
            continue
        m = isolated_member(r)
        i = r["members"].index(m) if m is not None else 0
        name = m if m is not None else r["effect"]
        if name in out:
            continue
        out[name] = {
            "magnitude": r["magnitude"] if m is None else [r["magnitude"][i]],
            "magnitude_ci": r["magnitude_ci"] if m is None else [r["magnitude_ci"][i]],
            "members": r["members"] if m is None else [m],
            "units": r["units"] if m is None else [r["units"][i]],
            "via": r["effect"] if m is not None else None,
            "via_kind": "member" if m is not None else None,
            "_row": r,
        }
    return out


def view_baselines(mv: dict, V0: dict, me: dict, st: Settings) -> dict:
    """Per view: χ² of the baseline with noise only and with noise + model error (a view table)."""
    out = {}
    for k, (v, se) in mv.items():
        S = np.sqrt(se**2 + me["sigma"][k] ** 2)
        S = np.maximum(S, 1e-12 * np.maximum(np.abs(V0[k]), 1e-300))
        Sn = np.maximum(se, 1e-12 * np.maximum(np.abs(V0[k]), 1e-300))
        N = v.size
        c = float(chi2(v, V0[k], S).sum())
        out[k] = {
            "n_terms": N,
            "chi2_noise_only": float(chi2(v, V0[k], Sn).sum()),
            "chi2": c,
            "threshold": float(stats.chi2.ppf(1 - st.alpha, N)),
            "significant": bool(c > stats.chi2.ppf(1 - st.alpha, N)),
            "model_error_relative_median": np.median(
                me["sigma"][k] / np.maximum(np.abs(V0[k]), 1e-300), axis=0
            ).tolist(),
            "noise_relative_median": np.median(se / np.maximum(np.abs(v), 1e-300), axis=0).tolist(),
        }
    return out


def where(meas: Measured, mv: dict, V0: dict, D0, me: dict, st: Settings) -> dict:
    """Where the gap lies: by feature, by (d, h, E) region, by stage, by image region."""
    y, n = meas.y, meas.n
    y0 = V0["features"]
    S = np.sqrt(meas.se**2 + me["sigma"]["features"] ** 2)
    S = np.maximum(S, 1e-12)
    rng = np.random.default_rng(st.seed + 1)
    rel = (y - y0) / np.where(np.abs(y0) > 0, np.abs(y0), 1.0)
    r = (y - y0) / S
    by_feature = {}
    for j, k in enumerate(FEATURES):
        by_feature[k] = {
            "relative_gap_mean": float(rel[:, j].mean()),
            "relative_gap_ci": bootstrap_ci(rel[:, j], np.mean, st.bootstrap, rng),
            "noise_units_rms": float(np.sqrt(np.mean(r[:, j] ** 2))),
            "noise_floor_relative": float(np.median(meas.se[:, j] / np.maximum(np.abs(y[:, j]), 1e-300))),
            "model_error_relative": float(
                np.median(me["sigma"]["features"][:, j] / np.maximum(np.abs(y0[:, j]), 1e-300))
            ),
        }
    rms_i = np.sqrt(np.mean(r**2, axis=1))
    by_region = {}
    for q, name in enumerate(("d", "h", "E")):
        v = meas.dhe[:, q]
        edges = np.quantile(v, [0, 1 / 3, 2 / 3, 1])
        bins = []
        for b in range(3):
            sel = (v >= edges[b]) & ((v <= edges[b + 1]) if b == 2 else (v < edges[b + 1]))
            if sel.sum() == 0:
                continue
            bins.append(
                {
                    "range": [float(edges[b]), float(edges[b + 1])],
                    "n": int(sel.sum()),
                    "rms_noise_units": float(np.sqrt(np.mean(rms_i[sel] ** 2))),
                    "rms_ci": bootstrap_ci(rms_i[sel], lambda a: float(np.sqrt(np.mean(a**2))), st.bootstrap, rng),
                    "relative_gap_mean": {k: float(rel[sel, j].mean()) for j, k in enumerate(FEATURES)},
                }
            )
        by_region[name] = bins
    ssr0 = float(np.sum(r**2))
    held = 0.0
    for te in folds(n, st.seed):
        tr = np.setdiff1d(np.arange(n), te)
        pred = np.empty((len(te), 3))
        for j in range(3):
            A = np.column_stack([y0[tr, j], np.ones(len(tr))])
            coef, *_ = np.linalg.lstsq(A, y[tr, j], rcond=None)
            pred[:, j] = coef[0] * y0[te, j] + coef[1]
        held += float(np.sum(((y[te] - pred) / S[te]) ** 2))
    affine_share = float(np.clip(1 - held / ssr0, 0, 1)) if ssr0 > 0 else 0.0
    out = {
        "by_feature": by_feature,
        "by_region": by_region,
        "per_phantom_rms_noise_units": rms_i.tolist(),
        "stage": {"optics_like_affine_share": affine_share, "mechanics_like_share": 1 - affine_share},
        "relative_gap": rel,
        "normalised_residual": r,
    }
    if meas.has_images and D0 is not None and meas.difference[0].shape == D0[0].shape:
        out["image"] = image_residual(meas, D0, me, None)
    return out


def image_residual(meas: Measured, Dsim, me: dict, sensor) -> dict:
    """Mean residual map over the phantoms with its noise band, and its annulus table."""
    n = meas.n
    R = np.array([meas.difference[i] - Dsim[i] for i in range(n)])
    if all(s is not None for s in meas.difference_se):
        se = np.sqrt(np.sum([s**2 for s in meas.difference_se], axis=0)) / n
        noise_kind = "per-pixel, from the frame scatter"
    else:
        ring = np.zeros(R.shape[1:], bool)
        w = max(2, R.shape[1] // 10)
        ring[:w, :] = ring[-w:, :] = ring[:, :w] = ring[:, -w:] = True
        se = np.full(R.shape[1:], float(np.std(R[:, ring])) / math.sqrt(n))
        noise_kind = "uniform, from the window's outer ring"
    mer = np.mean(me["image_sigma"], axis=0)
    band = np.sqrt(se**2 + mer**2)
    mean = R.mean(axis=0)
    pix = meas.sensor_model().pixel_mm
    rings = []
    for a, b, msk in zip(vw.EDGES[:-1], vw.EDGES[1:], vw._bins(mean.shape, pix)):
        if not msk.any():
            continue
        n_eff = max(1.0, msk.sum() / (4 * math.pi * max(meas.settings().smooth_px, 0.5) ** 2))
        bnd = float(np.sqrt((se[msk].mean() / math.sqrt(n_eff)) ** 2 + mer[msk].mean() ** 2))
        rings.append(
            {
                "r_mm": [a, b],
                "mean_residual": float(mean[msk].mean()),
                "band": bnd,
                "noise_units": float(mean[msk].mean() / bnd) if bnd > 0 else 0.0,
            }
        )
    return {
        "n": n,
        "mean_residual": mean,
        "band": band,
        "z": mean / np.maximum(band, 1e-300),
        "noise_kind": noise_kind,
        "mean_measured": np.mean(meas.difference, axis=0),
        "mean_simulated": Dsim.mean(axis=0),
        "rings": rings,
        "max_abs_z": float(np.max(np.abs(mean) / np.maximum(band, 1e-300))),
        "noise_px": float(np.median(se) * math.sqrt(n)),
    }


# ------------------------------------------------------------------ ambiguity: what separates
def _sep(fa, fb, S) -> float:
    return float(np.sqrt(np.sum(((fa - fb) / S) ** 2)))


def propose(
    meas: Measured, rows_set: list[dict], V0: dict, me: dict, names, sim: Simulator, sensor, settings, st: Settings
) -> dict:
    """Predicted separation (noise units) of every pair of the ambiguity set by (i) the plate force,
    (ii) a second indentation depth, (iii) new phantoms in the design box."""
    mods = [(r["effect"], r["_model"], r["_theta"], r["_S"]) for r in rows_set]
    pairs = list(itertools.combinations(range(len(mods)), 2))
    out = {"set": [m[0] for m in mods], "now": {}, "force": {}, "second_depth": {}, "phantoms": []}
    for a, b in pairs:
        na, nb = mods[a][0], mods[b][0]
        out["now"][f"{na} vs {nb}"] = _sep(mods[a][1].predict(mods[a][2]), mods[b][1].predict(mods[b][2]), mods[a][3])
    S_all = mods[0][3]
    # (i) plate force at the measured phantoms (unless it is measured already)
    F0 = V0["force"][:, 0]
    sF = np.sqrt((st.force_noise * F0) ** 2 + me["sigma"]["force"][:, 0] ** 2)
    Fp = [m.predict(t, ["force"])[:, 0] for _, m, t, _ in mods]
    for a, b in pairs:
        if "force" not in names:
            out["force"][f"{mods[a][0]} vs {mods[b][0]}"] = _sep(Fp[a], Fp[b], sF)
    out["force_note"] = (
        f"plate force at the {meas.n} phantoms, gauge error {100 * st.force_noise:g} % "
        "(assumed) plus the force's model error"
    )
    # (ii) a second indentation depth (solved) at the phantoms with the largest signal
    if st.propose_solves and st.propose_phantoms > 0:
        idx = np.argsort(-V0["features"][:, 0])[: st.propose_phantoms]
        p0 = [phantom_params(meas, sim.mesh)[i] for i in idx]
        import dataclasses

        pd_ = [p.replace(loading=dataclasses.replace(p.loading, delta=st.second_delta)) for p in p0]
        plist, ok = [], True
        try:
            for _, m, t, _ in mods:
                plist += [m.params_at(p, t).validate() for p in pd_]
        except UserError:
            ok = False
        if ok:
            recs = sim.run(plist)
            img = [k for k in names if k != "force"]
            sl = slices(V0, names)
            cols = np.concatenate([np.arange(S_all.shape[1])[sl[k]] for k in img])
            Pv = []
            for j, (_, m, t, _) in enumerate(mods):
                V, _ = sim_views(recs[j * len(idx) : (j + 1) * len(idx)], m.sensor_at(sensor, t), settings)
                Pv.append(cat(V, img))
            Sd = S_all[idx][:, cols]
            for a, b in pairs:
                out["second_depth"][f"{mods[a][0]} vs {mods[b][0]}"] = _sep(Pv[a], Pv[b], Sd)
            out["second_depth_note"] = (
                f"indentation {st.second_delta:g} mm at phantoms "
                f"{[meas.ids[i] for i in idx]} (solved), noise as measured at 3 mm"
            )
    # (iii) new phantoms: linear emulator of z = (f - y0)/S over (ln d, h, ln E)
    y0 = cat(V0, names)
    S = mods[0][3]
    X = np.column_stack([np.ones(meas.n), np.log(meas.dhe[:, 0]), meas.dhe[:, 1], np.log(meas.dhe[:, 2])])
    Z = [(m.predict(t) - y0) / S for _, m, t, _ in mods]
    coefs = [np.linalg.lstsq(X, z, rcond=None)[0] for z in Z]
    from .synth import phantom_design

    pool = phantom_design(200, st.seed + 7)
    Xp = np.column_stack([np.ones(len(pool)), np.log(pool[:, 0]), pool[:, 1], np.log(pool[:, 2])])
    seps = np.full(len(pool), np.inf)
    for a, b in pairs:
        dz = Xp @ (coefs[a] - coefs[b])
        seps = np.minimum(seps, np.sqrt(np.sum(dz**2, axis=1)))
    top = np.argsort(-seps)[:3]
    for i in top:
        out["phantoms"].append(
            {
                "d": float(pool[i, 0]),
                "h": float(pool[i, 1]),
                "E": float(pool[i, 2]),
                "predicted_min_pair_separation": float(seps[i]),
            }
        )
    out["phantoms_note"] = (
        "new phantom (d, h, E) within the design box (d 5-12 mm, E 30-150 kPa, valid depths); "
        "separation emulated by a linear fit of each candidate's effect over the measured phantoms"
    )
    if st.propose_solves and out["phantoms"]:
        best = out["phantoms"][0]
        p = base_params(sim.mesh, best["d"], best["h"], best["E"])
        try:
            plist = [p] + [m.params_at(p, t).validate() for _, m, t, _ in mods]
            recs = sim.run(plist)
            Vb, _ = sim_views(recs[:1], sensor, settings)
            f = []
            for j, (_, m, t, _) in enumerate(mods):
                V, _ = sim_views(recs[j + 1 : j + 2], m.sensor_at(sensor, t), settings)
                f.append(cat(V, names)[0])
            Sm = np.median(S, axis=0)
            best["solved_pair_separation"] = {f"{mods[a][0]} vs {mods[b][0]}": _sep(f[a], f[b], Sm) for a, b in pairs}
        except UserError:
            pass
    opts = [("plate force at the same phantoms", min(out["force"].values()))] if out["force"] else []
    if out["second_depth"]:
        opts.append((f"second indentation depth {st.second_delta:g} mm", min(out["second_depth"].values())))
    if out["phantoms"]:
        ph = out["phantoms"][0]
        sv = ph.get("solved_pair_separation")
        opts.append(
            (
                f"one more phantom d {ph['d']:.3g} mm, h {ph['h']:.3g} mm, E {ph['E']:.3g} kPa",
                min(sv.values()) if sv else ph["predicted_min_pair_separation"],
            )
        )
    opts.sort(key=lambda t: -t[1])
    out["recommendation"] = {"measurement": opts[0][0], "min_pair_separation_noise_units": opts[0][1]}
    out["options"] = [{"measurement": a, "min_pair_separation_noise_units": b} for a, b in opts]
    return out


# ------------------------------------------------------------------ shrink
def withheld_split(n: int) -> tuple[np.ndarray, np.ndarray]:
    te = np.arange(n)[1::3]
    return np.setdiff1d(np.arange(n), te), te


def shrink_features(meas: Measured, y, y0, S, mdl, names) -> dict:
    """Gap before/after on withheld phantoms, magnitude fitted on the rest (decision view), and
    the relative gap of the three features."""
    tr, te = withheld_split(meas.n)
    th = mdl.fit(y, S, tr)
    f = mdl.predict(th)
    before = float(np.sqrt(np.mean(((y[te] - y0[te]) / S[te]) ** 2)))
    after = float(np.sqrt(np.mean(((y[te] - f[te]) / S[te]) ** 2)))
    ff = mdl.predict(th, ["features"])
    yf = meas.y
    y0f = mdl.predict(np.asarray(mdl.nominal(), float), ["features"])
    relb = np.mean(np.abs(yf[te] - y0f[te]) / np.abs(yf[te]), axis=0)
    rela = np.mean(np.abs(yf[te] - ff[te]) / np.abs(yf[te]), axis=0)
    return {
        "fit_phantoms": [meas.ids[i] for i in tr],
        "withheld": [meas.ids[i] for i in te],
        "magnitude": [float(t) for t in th],
        "views": list(names),
        "rms_noise_units_before": before,
        "rms_noise_units_after": after,
        "shrink": 1 - after / before if before > 0 else 0.0,
        "relative_gap_before": {k: float(relb[j]) for j, k in enumerate(FEATURES)},
        "relative_gap_after": {k: float(rela[j]) for j, k in enumerate(FEATURES)},
    }


def training_design(meas: Measured, n: int, seed: int, aspect_hi: float = 1.0) -> np.ndarray:
    """LHS of (d, h, E) over the phantoms' bounding box (E log-uniform), depths kept valid."""
    from scipy.stats import qmc

    from elastimap.dataset.schema import THICKNESS, depth_range

    u = qmc.LatinHypercube(d=3, rng=np.random.default_rng(seed)).random(n)
    lo, hi = meas.dhe.min(0), meas.dhe.max(0)
    d = lo[0] + u[:, 0] * (hi[0] - lo[0])
    a, b = depth_range(d, THICKNESS, aspect_hi)
    hl, hh = np.maximum(a, lo[1]), np.minimum(b, hi[1])
    hh = np.maximum(hh, hl)
    h = hl + u[:, 1] * (hh - hl)
    E = np.exp(np.log(lo[2]) + u[:, 2] * (np.log(hi[2]) - np.log(lo[2])))
    return np.column_stack([d, h, E])


def _train_inverse(X, T, st: Settings):
    import pandas as pd

    from elastimap.training.api import fit_ensemble

    df = pd.DataFrame({"O1": X[:, 0], "O2": X[:, 1], "O3": X[:, 2], "d": T[:, 0], "h": T[:, 1], "E": T[:, 2]})
    return fit_ensemble(df, algo="scg", repeats=st.train_repeats, epochs=st.train_epochs, hidden=(10,), seed=st.seed)


def shrink_inverse(meas: Measured, mdl, th, sim: Simulator, sensor, settings, st: Settings) -> dict:
    """(d, h, E) error on the withheld phantoms: inverse trained on baseline sims vs on sims with
    the effect at ``th`` (camera features -> (d, h, E), ``fit_ensemble`` SCG)."""
    tr, te = withheld_split(meas.n)
    aspect_hi = max(
        1.0, max(float(t) for t, n in zip(th, mdl.labels) if n == "aspect") if "aspect" in mdl.labels else 1.0
    )
    T = training_design(meas, st.n_train, st.seed, aspect_hi)
    p_base = [base_params(sim.mesh, *t) for t in T]
    p_eff = [mdl.params_at(p, th) for p in p_base]
    ok = []
    for i, p in enumerate(p_eff):
        try:
            p.validate()
            ok.append(i)
        except UserError:
            pass
    ok = np.array(ok)
    recs = sim.run([p_base[i] for i in ok] + [p_eff[i] for i in ok])
    k = len(ok)
    Vb, _ = sim_views(recs[:k], sensor, settings)
    Ve, _ = sim_views(recs[k:], mdl.sensor_at(sensor, th), settings)
    Xb, Xe = Vb["features"], Ve["features"]
    fin = np.all(np.isfinite(Xb), axis=1) & np.all(np.isfinite(Xe), axis=1)
    Xb, Xe, Tk = Xb[fin], Xe[fin], T[ok][fin]
    ens_b = _train_inverse(Xb, Tk, st)
    ens_e = _train_inverse(Xe, Tk, st)
    truth = meas.dhe[te]
    out = {
        "n_train": int(fin.sum()),
        "n_failed_solves": int(k - fin.sum()),
        "withheld": [meas.ids[i] for i in te],
        "magnitude": [float(t) for t in th],
    }
    own, _ = sim_views(sim.run(phantom_params(meas.subset(te), sim.mesh)), sensor, settings)
    for name, ens, X in (
        ("inverse_own", ens_b, own["features"]),
        ("before", ens_b, meas.y[te]),
        ("after", ens_e, meas.y[te]),
    ):
        est = ens.predict(X).mean(axis=0)
        err = np.abs(est - truth) / truth
        out[name] = {
            "mean_relative_error": {q: float(err[:, j].mean()) for j, q in enumerate(("d", "h", "E"))},
            "estimates": est.tolist(),
        }
    b = np.mean(list(out["before"]["mean_relative_error"].values()))
    a = np.mean(list(out["after"]["mean_relative_error"].values()))
    out["mean_error_before"], out["mean_error_after"] = float(b), float(a)
    out["shrink"] = float(1 - a / b) if b > 0 else 0.0
    return out


# ------------------------------------------------------------------ driver
def diagnose(
    meas: Measured,
    cands: list[fx.Effect],
    sim: Simulator,
    st: Settings | None = None,
    sim_fine: Simulator | None = None,
) -> dict:
    """The whole diagnosis.  ``sim_fine``: the simulator of the next finer mesh level for the
    measured model error (None: the assumed floor ``model_floor``)."""
    t0 = time.perf_counter()
    SOLVE_SECONDS.clear()
    st = st or Settings()
    if not cands:
        raise UserError("effects", "no candidate effects to test")
    sensor, settings = meas.sensor_model(), meas.settings()
    solved0 = sim.stats["solved"]
    timing = {}
    tt = time.perf_counter()
    V0, D0, C = simulate_candidates(meas, cands, sim, sensor, settings, adaptive=st.adaptive)
    timing["candidates"] = time.perf_counter() - tt
    tt = time.perf_counter()
    me = model_error(meas, sim, sim_fine, sensor, settings, V0, D0, st)
    if st.richardson and me["kind"] == "measured":
        V0, D0 = richardson_correct(V0, D0, C, me, st)
        me["note"] += (
            "; predictions extrapolated by it, σ = the spread of that extrapolation over orders "
            f"p in {list(st.order_range_image)} (image), {list(st.order_range_force)} (force)"
        )
    timing["model_error"] = time.perf_counter() - tt
    mv = measured_views(meas, sensor, settings)
    names = decision_views(mv)
    sl = slices(V0, names)
    y = cat({k: v for k, (v, _) in mv.items()}, names)
    se = cat({k: s for k, (_, s) in mv.items()}, names)
    y0 = cat(V0, names)
    S0 = np.sqrt(se**2 + cat(me["sigma"], names) ** 2)
    S0 = np.maximum(S0, 1e-12 * np.maximum(np.abs(y0), 1e-300))

    def evaluate_now():
        modes, spread = systematic_modes(me, names)
        return evaluate(y, S0, y0, build_models(C, names, V0, st), meas.n, st, sl, modes, spread)

    tt = time.perf_counter()
    ref_solves, ref_rounds = (
        refine(meas, C, sim, sensor, settings, me, st, evaluate_now, sim_fine) if st.adaptive else (0, 0)
    )
    timing["refine"] = time.perf_counter() - tt
    tt = time.perf_counter()
    ev = evaluate_now()
    timing["evaluate"] = time.perf_counter() - tt
    tt = time.perf_counter()
    for r in ev["ranking"]:
        cs = [c for c in C if c.effect.name in r["members"]]
        r["adaptive"] = any(c.adaptive for c in cs)
        r["solved_magnitudes"] = {c.effect.name: [float(x) for x in c.grid] for c in cs if c.adaptive}
        r["refined"] = all(len(c.refinements) > 0 for c in cs if c.adaptive) if r["adaptive"] else None
        r["own_model_error_at"] = {c.effect.name: list(c.own_error) for c in cs if c.own_error}
        r["extended_to"] = {c.effect.name: list(c.extended) for c in cs if c.extended}
    ev["views"] = names
    ev["by_view"] = view_baselines(mv, V0, me, st)
    wh = where(meas, mv, V0, D0, me, st)
    rows = {r["effect"]: r for r in ev["ranking"]}
    best = rows[ev["best"]] if ev["best"] else None
    shrink = shrink_features(meas, y, y0, best["_S"], best["_model"], names) if best else None
    prop = None
    if ev["outcome"] == "ambiguous":
        prop = propose(
            meas, [ev["reported"][n]["_row"] for n in ev["ambiguous_set"]], V0, me, names, sim, sensor, settings, st
        )
    inv = None
    if st.inverse and best is not None and ev["outcome"] not in ("no significant gap",):
        inv = shrink_inverse(meas, best["_model"], shrink["magnitude"], sim, sensor, settings, st)
    stage = wh["stage"]
    bm = [r for r in ev["ranking"] if r["stage"] == "mechanics"]
    bo = [r for r in ev["ranking"] if r["stage"] == "optics"]
    stage["best_mechanics_candidate"] = (bm[0]["effect"], bm[0]["explained_fraction"]) if bm else None
    stage["best_optics_candidate"] = (bo[0]["effect"], bo[0]["explained_fraction"]) if bo else None
    if inv:
        stage["inverse_own_error"] = inv["inverse_own"]["mean_relative_error"]
        stage["inverse_error_on_measured"] = inv["before"]["mean_relative_error"]
    if best is not None and "image" in wh:
        Dw = best["_model"].image(best["_theta"])
        if Dw is not None:
            wh["image_after"] = image_residual(meas, Dw, me, sensor)
            wh["image_after"]["effect"] = best["effect"]
    timing["rest"] = time.perf_counter() - tt
    lin = not any(p.nonlinear for p in phantom_params(meas, sim.mesh))
    solves_by_effect = {
        c.effect.name: meas.n * sum(1 for m in c.grid if not c.effect.is_nominal(m))
        for c in C
        if needs_solves(c.effect, lin)
    }
    return {
        "solves_by_effect": solves_by_effect,
        "solve_seconds_by_effect": dict(SOLVE_SECONDS),
        "timing": timing,
        "refinement": {"solves": ref_solves, "rounds": ref_rounds, "adaptive": st.adaptive},
        "measured": {
            "source": meas.source,
            "n": meas.n,
            "synthetic": meas.synthetic,
            "description": meas.description,
            "mesh": sim.mesh,
            "ids": meas.ids,
            "dhe": meas.dhe.tolist(),
            "views_available": list(mv),
        },
        "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in st.__dict__.items()},
        "candidates": [c.effect.to_dict() for c in C],
        "model_error": {k: v for k, v in me.items() if k in ("kind", "note", "fine_mesh", "ratio", "relative_median")},
        "_model_error": me,
        "_views": mv,
        "_V0": V0,
        "baseline": V0["features"],
        "evaluation": ev,
        "where": wh,
        "shrink_features": shrink,
        "shrink_inverse": inv,
        "proposal": prop,
        "simulator": dict(
            sim.stats,
            backend=sim.backend,
            mesh=sim.mesh,
            solved_this_diagnosis=sim.stats["solved"] - solved0,
            fine_solved=(sim_fine.stats["solved"] if sim_fine is not None else 0),
            fine_mesh=(sim_fine.mesh if sim_fine is not None else None),
        ),
        "seconds": time.perf_counter() - t0,
    }
