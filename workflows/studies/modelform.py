"""What the model-form error term (:mod:`elastimap.identify.discrepancy`) does to a fit, measured on a
world elastimap did not make.

    python -m elastimap.workflows.studies.modelform --world /work/shared/devdata/independent-fem \\
        --sets none,tissueE65 --model-mesh fine --alt-mesh default --out modelform.json
    python -m elastimap.workflows.studies.modelform --world-level default --model-mesh coarse --alt-mesh tiny
    python -m elastimap.workflows.studies.modelform --calculix /work/shared/devdata/independent-fem/calculix.csv
    python -m elastimap.workflows.studies.modelform --world-level coarse --product tiny --frames 30

``--product LEVEL`` fits each phantom with the product's fit (:func:`product_check`: the maps ``infer
--refine --mesh LEVEL`` uses, closed world and carrying the learnt term) instead of the linearised step.

The world: a folder in the format of ``shared/devdata/independent-fem`` (``sets.csv`` with one row per
phantom, ``raw_*.npy`` / ``ref_*.npy`` the lesion and background press, mm) -- or, with
``--world-level``, elastimap's own remeshing solver at that level, sized by d, with the unilateral
contact interface, at elastimap's nine calibration-phantom designs and three further lesions (a
variant world for choosing settings: it proves self-consistency only).

Per set, the first nine phantoms are the lab's calibration phantoms: their (d, h, E) are known, so their
residual images ``I_i − m(θ_i)`` (world plus frame noise, minus elastimap's map ``--model-mesh`` at the
truth) are what :func:`elastimap.identify.discrepancy.learn` learns the discrepancy from.  Scored: each
calibration phantom with a discrepancy learnt from the other eight, and phantoms 10–12 with the one
learnt from the nine.  For each, a measured image (the world's difference image plus Gaussian pixel
noise of ``--frames`` frames of the nominal camera, :func:`elastimap.camera.optics.deflection_noise_map`,
``--draws`` draws) is fitted **linearised at the truth** (one generalised least-squares step in the
fit's coordinates (d, u, e), :class:`elastimap.identify.coords.FitCoords`, from the map's exact
derivative; :func:`elastimap.identify.discrepancy.linear_fit`):

* ``closed``: the error budget the fit carries today -- the pixel noise and the map's discretisation
  error, the difference from ``--alt-mesh`` as a per-pixel sd (3x3 local rms) and one systematic image
  (``b bᵀ`` in the covariance), as :func:`elastimap.identify.fit.fit_image` does;
* ``open``: the same (per-pixel sd, systematic image, Birge factor) plus the learnt discrepancy (its
  modes marginalised, its remainder correlated).

Reported per set and budget: the estimate's relative error of d, h, E (where "identifiable": the fit's
relative sd ≤ 10 %, E's sd of ln E ≤ 0.1, the threshold inference prints a number at), the 95 %
interval's coverage (``|Δx| ≤ 1.96 sd`` in the fit's coordinates), how often the linearised estimate
leaves the design box (what drives a fit to its edge), and the held-out residual's ``χ²/p`` under the
budget (1 when the budget is the right size).  Linearised at the truth: it measures how the budget
weighs a model-form difference, not the nonlinear fit's path (``--product`` and ``--nonlinear`` fit it).
"""

from __future__ import annotations

import csv
import json
import os

import click
import numpy as np

from elastimap.cli_util import MeshLevel, run

N_CAL = 9  # the first nine phantoms of a set are its calibration phantoms
#: a parameter is reported as a number where its relative sd (d, h) or sd of ln E is at most this
IDENTIFIABLE = 0.10
PIXEL = 0.5  # mm, the image grid of the world's files and of the map


def read_world(folder: str, name: str) -> list[dict]:
    """The phantoms of set ``name`` in ``folder`` (``sets.csv`` order): theta, difference and background
    press images (mm)."""
    from elastimap.errors import UserError

    path = os.path.join(folder, "sets.csv")
    if not os.path.exists(path):
        raise UserError("--world", f"{path}: no such file")
    rows = [r for r in csv.DictReader(open(path)) if r["set"] == name]
    if not rows:
        raise UserError("--sets", f"no set {name!r} in {path}")
    out = []
    for r in rows:
        raw, ref = (np.load(os.path.join(folder, r[k])) for k in ("raw", "ref"))
        th = np.array([float(r["d_mm"]), float(r["h_mm"]), float(r["E_kPa"])])
        out.append({"phantom": r["phantom"], "theta": th, "diff": raw - ref, "ref": ref, "effect": r["effect"]})
    return out


def variant_designs(seed: int = 99) -> np.ndarray:
    """elastimap's nine calibration-phantom designs and three Latin-hypercube lesions (seed ``seed``)."""
    from elastimap.dataset.phantoms import read_phantoms
    from elastimap.workflows.benchmarks.frames.lesions import draw_lesions

    ph = read_phantoms()
    return np.vstack([ph[["d", "h", "E"]].to_numpy(float), draw_lesions(3, seed)])


def variant_world(level: str, cache: str, seed: int = 99) -> list[dict]:
    """A variant world: the remeshing solver at ``level``, sized by d, contact interface (SYNTHETIC)."""
    import dataclasses

    from elastimap.solver import solve
    from elastimap.solver.params import SolveParams

    os.makedirs(cache, exist_ok=True)
    out = []
    for i, th in enumerate(variant_designs(seed)):
        f = os.path.join(cache, f"world_{level}_{th[0]:.4g}_{th[1]:.4g}_{th[2]:.4g}.npz")
        if not os.path.exists(f):
            p = SolveParams().with_inclusion(d=float(th[0]), h=float(th[1]), E=float(th[2]))
            p = p.replace(disc=dataclasses.replace(p.disc, mesh=level, sizing="by_d", interface="contact"))
            r = solve(p)
            np.savez(f, diff=np.asarray(r.image, float), raw=np.asarray(r.image_raw, float))
        z = np.load(f)
        out.append(
            {"phantom": f"V{i + 1:02d}", "theta": th, "diff": z["diff"], "ref": z["raw"] - z["diff"], "effect": ""}
        )
    return out


def model_at(thetas, mesh: str, cache: str) -> dict:
    """elastimap's morphed map at ``mesh``: ``{key: (image, J)}`` at each design (J ``(3, ny, nx)`` =
    ∂image/∂(d, h, E)), each with its reference press re-solved at the design (cached in ``cache``)."""
    from elastimap.identify.forward_maps import shared_map

    os.makedirs(cache, exist_ok=True)
    out, f = {}, None
    for th in thetas:
        k = key(th)
        path = os.path.join(cache, f"model_{mesh}_{k}.npz")
        if not os.path.exists(path):
            f = f or shared_map(mesh, "morph")
            g = f.pin_exact(*th[:2])
            res, J = g.tangent(*(float(v) for v in th))
            np.savez(path, img=np.asarray(res.image, float), J=np.asarray(J, float))
        z = np.load(path)
        out[k] = (z["img"], z["J"])
    return out


def key(th) -> str:
    return "_".join(f"{float(v):.4g}" for v in th)


def fit_jacobian(th, J) -> tuple[np.ndarray, object]:
    """∂m/∂x ``(p, 3)`` in the fit's coordinates x = (d, u, e) at ``th`` and the coordinates."""
    from elastimap.identify.coords import FitCoords

    X = FitCoords()
    x = X.x(th)
    Jt = np.asarray(J, float).reshape(3, -1).T * np.array([1.0, 1.0, th[2]])  # ∂m/∂(d, h, ln E)
    return Jt @ X.dtheta(x), X


def closed_budget(m_img, alt_img, sigma):
    """Today's budget: per-pixel sd ``hypot(σ, local rms(m − m_alt))`` and the systematic image ``m − m_alt``
    (None without an alternative level)."""
    if alt_img is None:
        return sigma.ravel(), None
    from scipy import ndimage

    dl = (m_img - alt_img).ravel()
    sm = np.sqrt(ndimage.uniform_filter((dl * dl).reshape(m_img.shape), size=3, mode="nearest")).ravel()
    return np.hypot(sigma.ravel(), sm), dl


def step_closed(I, m_img, Jx, s, delta):
    """Gauss–Newton step under today's budget: weights ``1/s``, covariance ``(JᵀJ)⁻¹ max(1, χ²) + b bᵀ``."""
    A = Jx / s[:, None]
    r = (I.ravel() - m_img.ravel()) / s
    JtJi = np.linalg.pinv(A.T @ A)
    dx = JtJi @ A.T @ r
    res = r - A @ dx
    chi2 = float(res @ res) / max(r.size - 3, 1)
    C = JtJi * max(1.0, chi2)
    if delta is not None:
        b = JtJi @ A.T @ (delta / s)
        C = C + np.outer(b, b)
    return dx, C, float(r @ r) / r.size


def score_one(ph, m_img, J, alt_img, disc, frames, rng, draws):
    """Linearised fits of one phantom's world image under both budgets, ``draws`` noise draws."""
    from elastimap.camera.optics import deflection_noise_map
    from elastimap.identify import discrepancy as dy

    th = ph["theta"]
    Jx, X = fit_jacobian(th, J)
    x = X.x(th)
    from elastimap.dataset.schema import DESIGN_BOX

    lb, ub = X.box(DESIGN_BOX["d"], DESIGN_BOX["E"])
    sigma = deflection_noise_map(ph["ref"], PIXEL, frames)
    s_closed, delta = closed_budget(m_img, alt_img, sigma)
    out = {"closed": [], "open": []}
    for _ in range(draws):
        I = ph["diff"] + sigma * rng.standard_normal(sigma.shape)
        dxc, Cc, chi_c = step_closed(I, m_img, Jx, s_closed, delta)
        # the open budget: today's per-pixel sd as the noise, plus the discrepancy
        syst = () if delta is None else (delta,)
        lf = dy.linear_fit(I, m_img, Jx, s_closed.reshape(m_img.shape), PIXEL, disc, syst, birge=True)
        held = dy.linear_fit(I, m_img, np.zeros((I.size, 0)), s_closed.reshape(m_img.shape), PIXEL, disc)
        for name, dx, C, chi in (
            ("closed", dxc, Cc, chi_c),
            ("open", lf.dx, lf.cov, held.chi2 / I.size),
        ):
            sd = np.sqrt(np.clip(np.diag(C), 0, None))
            xh = x + dx
            G = X.dtheta(x)
            sd_t = np.sqrt(np.clip(np.diag(G @ C @ G.T), 0, None))  # (d, h, ln E)
            rel = np.array([sd_t[0] / th[0], sd_t[1] / th[1], sd_t[2]])
            th_hat = X.theta(np.clip(xh, lb, ub))
            out[name].append(
                {
                    "z": (dx / sd).tolist(),
                    "covered": (np.abs(dx) <= 1.96 * sd).tolist(),
                    "outside_box": bool(((xh < lb) | (xh > ub)).any()),
                    "outside": ((xh < lb) | (xh > ub)).tolist(),
                    "rel_err": (np.abs(th_hat - th) / th).tolist(),
                    "relsd": rel.tolist(),
                    "identifiable": (rel <= IDENTIFIABLE).tolist(),
                    "chi2_px": chi,
                }
            )
    return out


def score_set(world, model, alt, frames, draws, seed, which, prior_weight, ell_grid=None):
    """Learn from the calibration phantoms (each left out in turn), score every phantom (module docstring)."""
    from elastimap.camera.optics import deflection_noise_map
    from elastimap.identify import discrepancy as dy

    ell_grid = dy.ELL_GRID if ell_grid is None else ell_grid
    rng = np.random.default_rng(seed)
    cal = world[:N_CAL]
    res_cal = []
    for ph in cal:  # the calibration phantoms' measured residuals (one noise draw each, as a lab has)
        m_img = model[key(ph["theta"])][0]
        sigma = deflection_noise_map(ph["ref"], PIXEL, frames)
        alt_img = alt[key(ph["theta"])][0] if alt else None
        s_c, _ = closed_budget(m_img, alt_img, sigma)
        I = ph["diff"] + sigma * rng.standard_normal(sigma.shape)
        res_cal.append((I - m_img, m_img, s_c.reshape(m_img.shape)))

    def learnt(skip=None):
        use = [r for i, r in enumerate(res_cal) if i != skip]
        return dy.learn(*zip(*use, strict=True), PIXEL, which=which, prior_weight=prior_weight, ell_grid=ell_grid)

    rows = []
    full = learnt()
    for i, ph in enumerate(world):
        disc = learnt(i) if i < N_CAL else full
        m_img, J = model[key(ph["theta"])]
        alt_img = alt[key(ph["theta"])][0] if alt else None
        sc = score_one(ph, m_img, J, alt_img, disc, frames, rng, draws)
        rows.append({"phantom": ph["phantom"], "theta": ph["theta"].tolist(), "calibration": i < N_CAL, **sc})
    return rows, full


def summary(rows, budget) -> dict:
    rs = [r for row in rows for r in row[budget]]
    cov = np.mean([r["covered"] for r in rs], axis=0)
    ident = np.array([r["identifiable"] for r in rs])
    err = np.array([r["rel_err"] for r in rs])
    mre = [float(err[ident[:, j], j].mean()) if ident[:, j].any() else float("nan") for j in range(3)]
    return {
        "n": len(rs),
        "coverage_pct": (100 * cov).tolist(),
        "mre_identifiable_pct": [100 * v for v in mre],
        "n_identifiable": ident.sum(axis=0).tolist(),
        "outside_box": int(sum(r["outside_box"] for r in rs)),
        # the linearised estimate beyond the box in a coordinate the budget calls identifiable: a fit
        # driven to the design edge and printed as a number (flagged ones are fine)
        "outside_identifiable": int(
            sum(any(o and i for o, i in zip(r.get("outside", []), r["identifiable"], strict=False)) for r in rs)
        ),
        "chi2_px_median": float(np.median([r["chi2_px"] for r in rs])),
    }


def fit_nonlinear(I, sigma, th0, fmap, disc, systematic=(), max_iter: int = 8) -> dict:
    """A check, not the product's fit: projected Gauss–Newton of (d, u, e) on the box with the map's exact
    derivative at each iterate (``fmap.pin_exact(d, h).tangent``), each step the generalised
    least-squares step of :func:`elastimap.identify.discrepancy.linear_fit` under ``disc`` (None: the
    closed budget), halved until the misfit falls (at most 3 times); stops when no parameter moves by
    more than 0.2 sd.  Returns the estimate, its covariance in x, the box flags and the solves."""
    from scipy import ndimage

    from elastimap.dataset.schema import DESIGN_BOX
    from elastimap.identify import discrepancy as dy

    X = fit_jacobian(th0, np.zeros((3, 1)))[1]
    # the discrepancy's modes and envelope from the measured image (smoothed over 1 pixel), fixed for
    # the whole fit: built from each trial image they grow with it and the misfit drifts toward larger
    # images (docs/model-form.md, 'The nonlinear check')
    Ib = ndimage.gaussian_filter(np.asarray(I, float), 1.0, mode="nearest")
    lb, ub = X.box(DESIGN_BOX["d"], DESIGN_BOX["E"])
    pad = 1e-3 * (ub - lb)
    x = np.clip(X.x(th0), lb + pad, ub - pad)
    n_solves, converged = 0, False

    def at(x):
        th = X.theta(x)
        res, J = fmap.pin_exact(th[0], th[1]).tangent(*(float(v) for v in th))
        return th, np.asarray(res.image, float), J

    th, m, J = at(x)
    n_solves += 1
    for _ in range(max_iter):
        Jx, _ = fit_jacobian(th, J)
        lf = dy.linear_fit(I, m, Jx, sigma, PIXEL, disc, systematic, birge=True, basis_image=Ib)
        cost0 = dy.linear_fit(I, m, np.zeros((m.size, 0)), sigma, PIXEL, disc, basis_image=Ib).chi2
        sd = np.sqrt(np.clip(np.diag(lf.cov), 0, None))
        step, better = lf.dx, False
        for _ in range(4):
            xn = np.clip(x + step, lb, ub)
            thn, mn, Jn = at(xn)
            n_solves += 1
            if dy.linear_fit(I, mn, np.zeros((m.size, 0)), sigma, PIXEL, disc, basis_image=Ib).chi2 <= cost0:
                better = True
                break
            step = step / 2
        if not better:  # no step along the Gauss–Newton direction lowers the misfit: stop here
            converged = True
            break
        moved = np.abs(xn - x) > 0.2 * sd
        x, th, m, J = xn, thn, mn, Jn
        if not moved.any():
            converged = True
            break
    Jx, _ = fit_jacobian(th, J)
    lf = dy.linear_fit(I, m, Jx, sigma, PIXEL, disc, systematic, birge=True, basis_image=Ib)
    tol = 1e-3 * (ub - lb)
    at_bound = ((x <= lb + tol) | (x >= ub - tol)).tolist()
    return {
        "x": x,
        "theta": th,
        "cov": lf.cov,
        "X": X,
        "at_bound": at_bound,
        "converged": converged,
        "solves": n_solves,
    }


def nonlinear_check(world, model_mesh, alt, cache, frames, seed, which, prior_weight, start) -> list[dict]:
    """Each phantom's world image (one noise draw) fitted by :func:`fit_nonlinear` from ``start`` x the
    truth under both budgets (the discrepancy learnt as in :func:`score_set`)."""
    from elastimap.camera.optics import deflection_noise_map
    from elastimap.identify import discrepancy as dy
    from elastimap.identify.forward_maps import shared_map

    rng = np.random.default_rng(seed)
    model = model_at([ph["theta"] for ph in world], model_mesh, cache)
    fmap = shared_map(model_mesh, "morph")
    cal = []
    for ph in world[:N_CAL]:
        m_img = model[key(ph["theta"])][0]
        sigma = deflection_noise_map(ph["ref"], PIXEL, frames)
        I = ph["diff"] + sigma * rng.standard_normal(sigma.shape)
        cal.append((I - m_img, m_img, sigma))
    rows = []
    for i, ph in enumerate(world):
        use = [c for j, c in enumerate(cal) if j != i]
        disc = dy.learn(*zip(*use, strict=True), PIXEL, which=which, prior_weight=prior_weight)
        th = ph["theta"]
        sigma = deflection_noise_map(ph["ref"], PIXEL, frames)
        I = ph["diff"] + sigma * rng.standard_normal(sigma.shape)
        syst = () if alt is None else ((model[key(th)][0] - alt[key(th)][0]).ravel(),)
        row = {"phantom": ph["phantom"], "theta": th.tolist()}
        for name, dsc in (("closed", None), ("open", disc)):
            f = fit_nonlinear(I, sigma, th * np.asarray(start), fmap, dsc, syst)
            X, x = f["X"], f["x"]
            sd = np.sqrt(np.clip(np.diag(f["cov"]), 0, None))
            G = X.dtheta(x)
            sd_t = np.sqrt(np.clip(np.diag(G @ f["cov"] @ G.T), 0, None))
            rel = np.array([sd_t[0] / f["theta"][0], sd_t[1] / f["theta"][1], sd_t[2]])
            row[name] = {
                "theta_hat": f["theta"].tolist(),
                "rel_err": (np.abs(f["theta"] - th) / th).tolist(),
                "covered": (np.abs(X.x(th) - x) <= 1.96 * sd).tolist(),
                "identifiable": (rel <= IDENTIFIABLE).tolist(),
                "at_bound": f["at_bound"],
                "converged": f["converged"],
                "solves": f["solves"],
            }
        rows.append(row)
        click.echo(
            f"{ph['phantom']} θ {np.round(th, 1).tolist()}: "
            + " | ".join(
                f"{b} {np.round(row[b]['theta_hat'], 2).tolist()} cov {row[b]['covered']} id {row[b]['identifiable']}"
                f" bound {row[b]['at_bound']} conv {row[b]['converged']}"
                for b in ("closed", "open")
            )
        )
    return rows


def product_check(world, fit_mesh, correct, frames, seed, which, prior_weight, start) -> dict:
    """The product's fit (:func:`elastimap.identify.fit.fit_image` on the maps ``infer --refine --mesh
    fit_mesh --refine-correct correct`` uses) of each phantom's world image (one noise draw of
    ``frames`` frames) from ``start`` x the truth, closed world (the calibrated or Gauss–Newton interval
    as inference reports it) and carrying the discrepancy learnt from the calibration phantoms (each of
    the nine left out of its own).  Returns ``{"rows", "summary"}``; "reported" is what inference prints
    as a number: relative sd (of the reported interval) ≤ 10 % and not on the design box's edge."""
    import time

    from elastimap.camera.optics import deflection_noise_map
    from elastimap.errors import UserError
    from elastimap.identify import discrepancy as dy
    from elastimap.identify.fit import fit_on_maps
    from elastimap.identify.forward_maps import fit_maps

    rng = np.random.default_rng(seed)
    maps = fit_maps(fit_mesh, correct)
    level = maps.forward_fine or maps.forward
    models, depths = dy.forward_images(level, [ph["theta"] for ph in world])
    models = [m.reshape(ph["diff"].shape) for m, ph in zip(models, world, strict=True)]
    if dy.DEPTH in which and depths is None:
        raise UserError("--modes", "the depth mode needs a map with an exact derivative (a morphed map)")
    cal = []
    for ph, m in zip(world[:N_CAL], models, strict=False):
        sigma = deflection_noise_map(ph["ref"], PIXEL, frames)
        cal.append((ph["diff"] + sigma * rng.standard_normal(sigma.shape) - m, m, sigma))
    rows = []
    for i, ph in enumerate(world):
        rest = [j for j in range(len(cal)) if j != i]
        disc = dy.learn(
            *zip(*[cal[j] for j in rest], strict=True),
            PIXEL,
            which=which,
            prior_weight=prior_weight,
            depths=[depths[j] for j in rest] if dy.DEPTH in which else None,
        )
        th = np.asarray(ph["theta"], float)
        sigma = deflection_noise_map(ph["ref"], PIXEL, frames)
        I = ph["diff"] + sigma * rng.standard_normal(sigma.shape)
        row = {"phantom": ph["phantom"], "theta": th.tolist()}
        for name, dsc in (("closed", None), ("open", disc)):
            t0 = time.process_time()
            r = fit_on_maps(
                I, sigma, th * np.asarray(start), maps, intervals=maps.intervals, discrepancy=dsc, pixel=PIXEL
            )
            rel = r.relstd_calibrated
            row[name] = {
                "theta_hat": r.theta.tolist(),
                "rel_err": (np.abs(r.theta - th) / th).tolist(),
                "covered": ((r.lo <= th) & (th <= r.hi)).tolist(),
                "reported": [bool(rel[j] <= IDENTIFIABLE and not r.at_bound) for j in range(3)],
                "at_bound": r.at_bound,
                "converged": r.converged,
                "cpu_s": time.process_time() - t0,
            }
        rows.append(row)
        click.echo(
            f"{ph['phantom']} θ {np.round(th, 1).tolist()}: "
            + " | ".join(
                f"{b} {np.round(row[b]['theta_hat'], 2).tolist()} cov {row[b]['covered']} rep {row[b]['reported']}"
                f" bound {row[b]['at_bound']}"
                for b in ("closed", "open")
            )
        )
    return {"rows": rows, "summary": {b: product_summary(rows, b) for b in ("closed", "open")}}


def product_summary(rows, budget) -> dict:
    """Coverage (% of all), printed-as-a-number counts and their MRE (%), printed-and-missed counts, E on the
    design edge, converged count and mean CPU s of :func:`product_check`'s rows under ``budget``."""
    v = [r[budget] for r in rows]
    cov = np.array([x["covered"] for x in v], bool)
    rep = np.array([x["reported"] for x in v], bool)
    err = np.array([x["rel_err"] for x in v], float)
    return {
        "n": len(v),
        "coverage_pct": (100 * cov.mean(axis=0)).tolist(),
        "reported": rep.sum(axis=0).tolist(),
        "mre_reported_pct": [
            float(100 * err[rep[:, j], j].mean()) if rep[:, j].any() else float("nan") for j in range(3)
        ],
        "reported_missed": (rep & ~cov).sum(axis=0).tolist(),
        "E_at_edge": int(sum("E" in x["at_bound"] for x in v)),
        "converged": int(sum(x["converged"] for x in v)),
        "cpu_s_mean": float(np.mean([x["cpu_s"] for x in v])),
    }


def calculix_check(path: str, mesh: str, cache: str) -> list[dict]:
    """elastimap's map at ``mesh`` against a third model's features (``calculix.csv`` of the independent
    references: O1 mm, O2 mm, plate forces mN at five designs): the relative differences, the scale of
    a model-form difference between two faithful models of the same sensor."""
    from elastimap.solver.image import features

    rows = list(csv.DictReader(open(path)))
    thetas = [np.array([float(r["d_mm"]), float(r["h_mm"]), float(r["E_kPa"])]) for r in rows]
    model = model_at(thetas, mesh, cache)
    out = []
    for r, th in zip(rows, thetas, strict=True):
        O1, O2, _ = features(model[key(th)][0], PIXEL)
        out.append(
            {
                "theta": th.tolist(),
                "O1_rel_pct": 100 * (O1 / float(r["O1_mm"]) - 1),
                "O2_rel_pct": 100 * (O2 / float(r["O2_mm"]) - 1),
            }
        )
    return out


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--world", default=None, type=click.Path(file_okay=False), help="Folder of the world's phantoms (sets.csv)."
)
@click.option("--world-level", type=MeshLevel(), default=None, help="Or: elastimap's variant world at this level.")
@click.option("--sets", default="none", show_default=True, help="Sets of --world, comma-separated.")
@click.option("--model-mesh", type=MeshLevel(), default="fine", show_default=True, help="Level of the fit's map.")
@click.option(
    "--alt-mesh", default="default", show_default=True, help="Its neighbouring level (today's budget), or none."
)
@click.option("--frames", default=30, show_default=True, type=click.IntRange(2, 1000), help="Camera frames per press.")
@click.option("--draws", default=20, show_default=True, type=click.IntRange(1, 1000), help="Noise draws per phantom.")
@click.option("--seed", default=0, show_default=True, type=int, help="Noise seed.")
@click.option(
    "--modes",
    default="amplitude,width",
    show_default=True,
    help="The discrepancy's modes: amplitude, width, tail; depth (h dm/dh) with --product only.",
)
@click.option("--prior-weight", default=2.0, show_default=True, type=float, help="ν₀ of the prior scale.")
@click.option(
    "--ell-grid", default=None, help="The remainder's correlation lengths to choose from, mm (default ELL_GRID)."
)
@click.option("--cache", default="runs/modelform-cache", show_default=True, help="Folder of the solves.")
@click.option(
    "--calculix", default=None, type=click.Path(dir_okay=False), help="Only compare the map with this calculix.csv."
)
@click.option(
    "--nonlinear",
    is_flag=True,
    help="Fit each phantom with the (nonlinear) projected Gauss–Newton check instead of the linearised step.",
)
@click.option(
    "--product",
    "product_mesh",
    type=MeshLevel(),
    default=None,
    help="Fit each phantom with the product's fit (infer --refine's maps at this --mesh, corrected by "
    "--product-correct) closed-world and carrying the discrepancy, from --start x the truth.",
)
@click.option("--product-correct", default="none", show_default=True, help="--product: the correcting level, or none.")
@click.option("--start", default="0.9,1.05,1.5", show_default=True, help="--product: the start, d,h,E x the truth.")
@click.option(
    "--out", default=None, type=click.Path(dir_okay=False), help="Write the rows here (.json; must not exist)."
)
def main(
    world,
    world_level,
    sets,
    model_mesh,
    alt_mesh,
    frames,
    draws,
    seed,
    modes,
    prior_weight,
    ell_grid,
    cache,
    calculix,
    nonlinear,
    product_mesh,
    product_correct,
    start,
    out,
):
    """The fit's error budget with and without the learnt model-form error, on another model's phantoms."""
    from elastimap.errors import UserError
    from elastimap.identify import discrepancy as dy

    if calculix:
        for r in calculix_check(calculix, model_mesh, cache):
            d, h, E = r["theta"]
            click.echo(
                f"d={d:g} h={h:g} E={E:g}: {model_mesh} vs CalculiX O1 {r['O1_rel_pct']:+.2f} %, O2 {r['O2_rel_pct']:+.2f} %"
            )
        return
    if (world is None) == (world_level is None):
        raise UserError("--world", "give --world FOLDER or --world-level LEVEL (one of them)")
    if out and os.path.exists(out):
        raise UserError("--out", f"{out} exists; choose another name")
    which = tuple(v.strip() for v in modes.split(",") if v.strip())
    bad = [v for v in which if v not in (*dy.ALL_MODES, dy.DEPTH)]
    if not which or bad:
        raise UserError("--modes", f"comma-separated among {', '.join((*dy.ALL_MODES, dy.DEPTH))} (got {modes!r})")
    if dy.DEPTH in which and product_mesh is None:
        raise UserError("--modes", "the depth mode is scored by the product's fit only (--product)")
    try:
        grid = None if ell_grid is None else tuple(float(v) for v in ell_grid.split(","))
    except ValueError:
        grid = ()
    if grid is not None and (not grid or min(grid) < 0):
        raise UserError("--ell-grid", f"comma-separated lengths >= 0 mm (got {ell_grid!r})")
    names = [v.strip() for v in sets.split(",") if v.strip()] if world else ["variant"]
    worlds = {n: read_world(world, n) if world else variant_world(world_level, cache) for n in names}
    if product_mesh is not None:
        try:
            st = tuple(float(v) for v in start.split(","))
        except ValueError:
            st = ()
        if len(st) != 3 or min(st) <= 0:
            raise UserError("--start", f"three factors > 0, d,h,E (got {start!r})")
        corr = None if product_correct == "none" else product_correct
        from elastimap.identify.forward_maps import check_correct

        check_correct(product_mesh, corr)
        result = {"world": world or f"elastimap remesh {world_level}, by_d, contact (SYNTHETIC)", "frames": frames}
        result.update(seed=seed, modes=list(which), prior_weight=prior_weight, sets={})
        result.update(product=product_mesh, product_correct=corr, start=list(st))
        for n, w in worlds.items():
            result["sets"][n] = res = product_check(w, product_mesh, corr, frames, seed, which, prior_weight, st)
            for b, v in res["summary"].items():
                click.echo(
                    f"[{n}] {b:6s} coverage d/h/E {v['coverage_pct'][0]:.0f}/{v['coverage_pct'][1]:.0f}/"
                    f"{v['coverage_pct'][2]:.0f} %  printed d/h/E {v['reported']} MRE {np.round(v['mre_reported_pct'], 1).tolist()} %"
                    f"  printed+missed {v['reported_missed']}  E at edge {v['E_at_edge']}  converged {v['converged']}/{v['n']}"
                    f"  CPU {v['cpu_s_mean']:.1f} s"
                )
        if out:
            with open(out, "w") as fh:
                json.dump(result, fh, indent=1)
        return
    thetas = {key(ph["theta"]): ph["theta"] for w in worlds.values() for ph in w}
    model = model_at(thetas.values(), model_mesh, cache)
    alt = None if alt_mesh == "none" else model_at(thetas.values(), alt_mesh, cache)
    result = {"world": world or f"elastimap remesh {world_level}, by_d, contact (SYNTHETIC)", "model_mesh": model_mesh}
    result.update(alt_mesh=alt_mesh, frames=frames, draws=draws, seed=seed, modes=list(which), sets={})
    result.update(prior_weight=prior_weight, ell_grid=list(grid or dy.ELL_GRID))
    if nonlinear:
        start = (0.9, 1.05, 1.5)  # d, h, E times the truth: a start off the answer, along the valley
        result.update(nonlinear=True, start=list(start))
        for n, w in worlds.items():
            result["sets"][n] = nonlinear_check(w, model_mesh, alt, cache, frames, seed, which, prior_weight, start)
        if out:
            with open(out, "w") as fh:
                json.dump(result, fh, indent=1)
        return
    for n, w in worlds.items():
        rows, disc = score_set(w, model, alt, frames, draws, seed, which, prior_weight, grid)
        s = {b: summary(rows, b) for b in ("closed", "open")}
        result["sets"][n] = {"discrepancy": disc.to_dict(), "summary": s, "rows": rows}
        click.echo(
            f"[{n}] learnt from 9: mean {np.round(disc.mean, 4).tolist()} tau {np.round(disc.tau, 4).tolist()}"
            f" rho {disc.rho:.4f} ell {disc.ell:g} mm; beyond the model-form level: {', '.join(disc.beyond()) or 'no'}"
        )
        for b in ("closed", "open"):
            v = s[b]
            click.echo(
                f"  {b:6s} coverage d/h/E {v['coverage_pct'][0]:.0f}/{v['coverage_pct'][1]:.0f}/{v['coverage_pct'][2]:.0f} %"
                f"  MRE where identifiable d/h/E {v['mre_identifiable_pct'][0]:.1f}/{v['mre_identifiable_pct'][1]:.1f}/"
                f"{v['mre_identifiable_pct'][2]:.1f} % (n {v['n_identifiable']} of {v['n']})"
                f"  outside box {v['outside_box']} (identifiable {v['outside_identifiable']})"
                f"  held-out chi2/px {v['chi2_px_median']:.2f}"
            )
    if out:
        with open(out, "w") as fh:
            json.dump(result, fh, indent=1)


if __name__ == "__main__":
    import sys

    run(main, sys.argv[1:], prog_name="python -m elastimap.workflows.studies.modelform")
