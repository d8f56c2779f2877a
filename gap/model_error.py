"""The baseline's model error, measured on two mesh levels, and the Richardson extrapolation of
every prediction to the converged mesh (docs/gap.md, 'Method').

With Δ_iq = y0_iq(h) − y0_iq(h/r) (the diagnosis mesh minus the error mesh, r the ratio of
their element sizes) and the convergence order p of the view, κ = 1 / (1 − r^(−p)) and

    σ_disc,iq = κ · max(|Δ_iq|, median_i(|Δ_iq| / |y0_iq|) · |y0_iq|).

Without a second level σ = ρ |y0| (``Settings.model_floor``, reported as "assumed").
:func:`richardson_correct` moves every prediction by −κΔ and replaces σ by the spread of that
correction over the bracketing orders; :func:`correct` and :func:`correct_own` apply it to one
prediction; :func:`render_corrected` extrapolates an effect that costs no solves with its own
two levels.
"""

from __future__ import annotations

import numpy as np

from elastimap.solver.geometry import LEVELS

from .candidates import Candidate, phantom_params
from .measured import Measured
from .settings import Settings
from .simulate import Simulator
from .views import sim_views


def model_error(
    meas: Measured, sim: Simulator, sim_fine: Simulator | None, sensor, settings, V0: dict, D0, st: Settings
) -> dict:
    """Per-phantom, per-quantity model error of the baseline (module docstring): a dict with
    "kind" ("measured" or "assumed"), "sigma" {view: (n, q)}, "image_sigma" and, when measured,
    the level differences, κ, the error mesh's records and "_solve_seconds" (its solves)."""
    if sim_fine is None or sim_fine.mesh == sim.mesh:
        sig = {k: st.model_floor * np.abs(v) for k, v in V0.items()}
        return {
            "kind": "assumed",
            "sigma": sig,
            "image_sigma": st.model_floor * np.abs(D0),
            "note": f"assumed floor {100 * st.model_floor:g} % of each quantity (no second mesh level)",
        }
    recs1 = sim_fine.run(phantom_params(meas, sim_fine.mesh))
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
        "_solve_seconds": sum(r.seconds for r in recs1),
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
    its own correction at its refined magnitudes (:func:`elastimap.gap.adaptive.refine`)."""
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
