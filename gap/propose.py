"""What resolves an ambiguity: the predicted separation of every pair of look-alike candidates
by a further measurement (docs/gap.md, 'Method').

For a pair (a, b) and a measurement with noise S the separation in noise units is
sqrt(Σ ((f_a − f_b) / S)²), for (i) the plate force at the same phantoms (gauge error
``Settings.force_noise`` relative, plus the force's model error), (ii) a second indentation
depth (solved) and (iii) new phantoms in the design box, predicted by a linear emulator of
z_c = (f_c − y0)/S in (ln d, h, ln E) over the measured phantoms and checked with solves at the
best proposal.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from elastimap.errors import UserError

from .candidates import phantom_params
from .measured import Measured
from .model_form import Metric
from .settings import Settings
from .simulate import Simulator, base_params
from .synth import phantom_design
from .views import cat, sim_views, slices


def _sep(fa, fb, S) -> float:
    """sqrt(Σ ((fa − fb) / S)²): the separation of two predictions in noise units (``S`` a
    :class:`~elastimap.gap.model_form.Metric`: the whitened difference, so what the model-form level
    can absorb does not count)."""
    if isinstance(S, Metric):
        return float(np.sqrt(np.sum(S.z(np.asarray(fa) - np.asarray(fb)) ** 2)))
    return float(np.sqrt(np.sum(((fa - fb) / S) ** 2)))


def _sd(S) -> np.ndarray:
    """Per-quantity sd of an error model (a new measurement's noise units: the marginal sd, the
    model-form level's included)."""
    return S.sd if isinstance(S, Metric) else S


def propose(
    meas: Measured, rows_set: list[dict], V0: dict, me: dict, names, sim: Simulator, sensor, settings, st: Settings
) -> dict:
    """Predicted separation (noise units) of every pair of the ambiguity set by (i) the plate force,
    (ii) a second indentation depth, (iii) new phantoms in the design box, and the recommended one."""
    mods = [(r["effect"], r["_model"], r["_theta"], r["_S"]) for r in rows_set]
    pairs = list(itertools.combinations(range(len(mods)), 2))
    out = {"set": [m[0] for m in mods], "now": {}, "force": {}, "second_depth": {}, "phantoms": []}
    for a, b in pairs:
        na, nb = mods[a][0], mods[b][0]
        out["now"][f"{na} vs {nb}"] = _sep(mods[a][1].predict(mods[a][2]), mods[b][1].predict(mods[b][2]), mods[a][3])
    _by_force(out, mods, pairs, meas, V0, me, names, st)
    if st.propose_solves and st.propose_phantoms > 0:
        _by_second_depth(out, mods, pairs, meas, V0, names, sim, sensor, settings, st)
    _by_new_phantoms(out, mods, pairs, meas, V0, names, sim, sensor, settings, st)
    _recommend(out, st)
    return out


def _by_force(out: dict, mods, pairs, meas: Measured, V0: dict, me: dict, names, st: Settings) -> None:
    """(i) the plate force at the measured phantoms (unless it is measured already)."""
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


def _by_second_depth(out: dict, mods, pairs, meas: Measured, V0: dict, names, sim, sensor, settings, st) -> None:
    """(ii) a second indentation depth, solved at the phantoms with the largest signal."""
    S_all = _sd(mods[0][3])
    idx = np.argsort(-V0["features"][:, 0])[: st.propose_phantoms]
    p0 = [phantom_params(meas, sim.mesh)[i] for i in idx]
    pd_ = [p.replace(loading=dataclasses.replace(p.loading, delta=st.second_delta)) for p in p0]
    plist = []
    try:
        for _, m, t, _ in mods:
            plist += [m.params_at(p, t).validate() for p in pd_]
    except UserError:
        return
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


def _by_new_phantoms(out: dict, mods, pairs, meas: Measured, V0: dict, names, sim, sensor, settings, st) -> None:
    """(iii) new phantoms: linear emulator of z = (f - y0)/S over (ln d, h, ln E), the best
    proposal checked with solves."""
    y0 = cat(V0, names)
    S = _sd(mods[0][3])
    X = np.column_stack([np.ones(meas.n), np.log(meas.dhe[:, 0]), meas.dhe[:, 1], np.log(meas.dhe[:, 2])])
    Z = [(m.predict(t) - y0) / S for _, m, t, _ in mods]
    coefs = [np.linalg.lstsq(X, z, rcond=None)[0] for z in Z]
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
        p = base_params(sim.mesh, best["d"], best["h"], best["E"], sensor=meas.sensor_description)
        try:  # a proposal the effects cannot be applied to (or solved at) is not checked
            plist = [p] + [m.params_at(p, t).validate() for _, m, t, _ in mods]
            recs = sim.run(plist)
        except UserError:
            return
        f = []
        for j, (_, m, t, _) in enumerate(mods):
            V, _ = sim_views(recs[j + 1 : j + 2], m.sensor_at(sensor, t), settings)
            f.append(cat(V, names)[0])
        Sm = np.median(S, axis=0)
        best["solved_pair_separation"] = {f"{mods[a][0]} vs {mods[b][0]}": _sep(f[a], f[b], Sm) for a, b in pairs}


def _recommend(out: dict, st: Settings) -> None:
    """The options sorted by their smallest pair separation; the first is recommended."""
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
