"""Batched Levenberg–Marquardt and scaled conjugate gradient.

Both optimisers advance ``B`` independent problems in lock-step: every
per-problem scalar of the textbook algorithm (``mu``, ``lambda``, step sizes,
success flags, validation counters) is a length-``B`` tensor and every branch
is a mask.  Problems that meet a stopping rule drop out of the active set, so
the remaining work shrinks as networks finish.

An *objective* is any object with

* ``B`` (number of problems), ``subset(idx)`` -> objective for those problems;
* ``perf(theta)`` -> ``(B,)`` and ``perf_grad(theta)`` -> ``(perf, grad)`` (SCG);
* ``sse(theta)`` -> ``(B,)`` and ``sse_jj_je(theta)`` -> ``(sse, JᵀJ, Jᵀr)`` (LM; only the upper
  triangle of ``JᵀJ`` is read),
  ``n_elem`` -> ``(B,)`` number of squared errors in the training SSE;
* ``has_val`` and ``monitor(theta)`` -> ``dict name -> (B,)`` (must contain
  ``"val"`` when ``has_val``); recorded every epoch, ``"val"`` drives early stopping.

:class:`elastimap.training.problem.NetObjective` is the MLP one; the tests use small
analytic ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch


@dataclass
class TrainResult:
    theta: torch.Tensor  # (B, P) final parameters (best-validation ones when validating)
    epochs: torch.Tensor  # (B,) epochs run
    stop: list[str]  # stopping reason per problem
    history: dict[str, torch.Tensor] = field(default_factory=dict)  # name -> (B, epochs+1), NaN after stop
    workers: int = 1  # processes that trained it (set by elastimap.training.experiment.train_batch)


def _new_history(names, B, epochs, dtype):
    return {k: torch.full((B, epochs + 1), float("nan"), dtype=dtype) for k in names}


def _record(hist, active_cpu, epoch, values: dict):
    for k, v in values.items():
        if k not in hist:
            continue
        hist[k][active_cpu, epoch] = v.detach().to("cpu", hist[k].dtype)


class _Validation:
    """MATLAB's validation bookkeeping: remember the best-validation parameters, count failures."""

    def __init__(self, theta):
        B = theta.shape[0]
        self.best_theta = theta.clone()
        self.best = torch.full((B,), float("inf"), dtype=theta.dtype, device=theta.device)
        self.fails = torch.zeros(B, dtype=torch.long, device=theta.device)

    def update(self, active, theta_a, v):
        better = v < self.best[active]
        worse = v > self.best[active]
        ib = active[better]
        self.best[ib] = v[better]
        self.best_theta[ib] = theta_a[better]
        self.fails[ib] = 0
        self.fails[active[worse]] += 1


def _apply_stops(reasons, act_cpu, stop: list, ep_run, epoch: int) -> torch.Tensor:
    """Record the first stopping reason met by each active network (MATLAB's order of checks)
    and its last epoch; returns the mask of networks that go on."""
    done = torch.zeros_like(reasons[0][0], dtype=torch.bool)
    for m, name in reasons:
        for i in act_cpu[(m & ~done).cpu()].tolist():
            stop[i] = name
        done |= m
    ep_run[act_cpu[done.cpu()]] = epoch
    return ~done


class _Bookkeeping:
    """What both optimisers keep per problem across epochs: the history (name -> (B, epochs+1)),
    the validation's best parameters and failure count (when the objective validates), each
    problem's stopping reason and its last epoch."""

    def __init__(self, obj, theta: torch.Tensor, names, epochs: int):
        B = theta.shape[0]
        self.val = _Validation(theta) if obj.has_val else None
        self.stop = [""] * B
        self.ep_run = torch.zeros(B, dtype=torch.long)
        self.hist = _new_history(names, B, epochs, theta.dtype)

    def check(self, active, th, epoch: int, values: dict, reasons: list, max_fail: int) -> torch.Tensor:
        """Record this epoch's ``values`` (``"val"`` among them when validating) of the ``active``
        problems at parameters ``th``, update the validation's best, and apply the stopping
        ``reasons`` (mask, name) in order, the validation failures (>= ``max_fail``) last;
        returns the mask of the problems that go on."""
        act_cpu = active.cpu()
        _record(self.hist, act_cpu, epoch, values)
        if self.val is not None:
            self.val.update(active, th, values["val"])
            reasons = reasons + [(self.val.fails[active] >= max_fail, "val_fail")]
        return _apply_stops(reasons, act_cpu, self.stop, self.ep_run, epoch)

    def result(self, theta: torch.Tensor) -> TrainResult:
        """The result: the best-validation parameters when validating, else ``theta``."""
        final = self.val.best_theta if self.val is not None else theta
        return TrainResult(final, self.ep_run, self.stop, self.hist)


def lm_step(jj: torch.Tensor, je: torch.Tensor, mu: torch.Tensor, idx: torch.Tensor | None = None):
    """Levenberg–Marquardt steps ``Δθ = -(JᵀJ + μ I)⁻¹ Jᵀr`` by Cholesky factorisation.

    ``jj`` ``(B, P, P)`` (only its upper triangle is read, and it is left unchanged), ``je``
    ``(B, P)``; ``mu`` has one value per selected problem, ``idx`` selects problems (None = all).
    Returns ``(Δθ, factorised)``; ``factorised`` is False where ``JᵀJ + μ I`` was not numerically
    positive definite (that trial counts as failed).  On the CPU each network goes through
    LAPACK ``potrf``/``potrs`` (scipy's OpenBLAS; faster here than torch's batched MKL path for
    these 393 x 393 systems), on the column-major transpose of its row-major upper triangle,
    which is a plain copy; elsewhere torch's batched Cholesky.
    """
    if jj.device.type != "cpu":
        return _lm_step_torch(jj, je, mu, idx)
    from scipy.linalg import lapack

    rows = range(jj.shape[0]) if idx is None else idx.tolist()
    J, G, m = jj.numpy(), je.numpy(), mu.numpy()
    potrf, potrs = lapack.get_lapack_funcs(("potrf", "potrs"), dtype=J.dtype)
    P = J.shape[-1]
    buf = np.empty((P, P), dtype=J.dtype, order="F")
    out = np.empty((len(rows), P), dtype=J.dtype)
    ok = np.zeros(len(rows), dtype=bool)
    for t, b in enumerate(rows):
        np.copyto(buf, J[b].T)  # Fortran order: buf's lower triangle is JᵀJ's upper one
        buf.T.flat[:: P + 1] += m[t]
        c, info = potrf(buf, lower=1, clean=0, overwrite_a=1)
        if info == 0:
            x, info = potrs(c, G[b], lower=1)
        ok[t] = info == 0
        out[t] = -x if info == 0 else 0.0
    return torch.from_numpy(out), torch.from_numpy(ok)


def _lm_step_torch(jj, je, mu, idx=None):
    """:func:`lm_step` by torch's batched Cholesky (any device)."""
    A = jj.clone() if idx is None else jj[idx]
    A.diagonal(dim1=-2, dim2=-1).add_(mu[:, None])
    U, info = torch.linalg.cholesky_ex(A, upper=True)
    g = je if idx is None else je[idx]
    return -torch.cholesky_solve(g.unsqueeze(-1), U, upper=True).squeeze(-1), info == 0


def _lm_trials(o, system, theta: torch.Tensor, mu_t: torch.Tensor, gidx: torch.Tensor, mus) -> None:
    """One epoch's Levenberg–Marquardt trials for the problems ``gidx`` (global indices) whose
    ``system`` = (JᵀJ, Jᵀr, θ, E) was just computed: each tries Δθ = -(JᵀJ + μI)⁻¹Jᵀr and
    accepts it when it lowers E (θ updated in ``theta``, μ *= mu_dec, floored at 1e-20), else
    μ *= mu_inc and tries again, until accepted or μ > mu_max (``mus`` = (mu_dec, mu_inc,
    mu_max)); ``mu_t`` is updated in place."""
    jj, je, th, E = system
    mu_dec, mu_inc, mu_max = mus
    searching = torch.ones(gidx.numel(), dtype=torch.bool, device=theta.device)
    while True:
        q = searching.nonzero().squeeze(1)
        if q.numel() == 0:
            return
        m_q = mu_t[gidx[q]]
        dx, info = lm_step(jj, je, m_q, None if q.numel() == jj.shape[0] else q)
        cand = th[q] + dx
        E2 = o.subset(q).sse(cand)
        ok = info & torch.isfinite(E2) & (E2 < E[q])
        acc = q[ok]
        theta[gidx[acc]] = cand[ok]
        mu_t[gidx[acc]] = torch.clamp(m_q[ok] * mu_dec, min=1e-20)
        searching[acc] = False
        rej = q[~ok]
        mu_t[gidx[rej]] = m_q[~ok] * mu_inc
        searching[rej[mu_t[gidx[rej]] > mu_max]] = False


def train_lm(
    obj,
    theta0: torch.Tensor,
    *,
    epochs: int = 100,
    mu: float = 1e-3,
    mu_dec: float = 0.1,
    mu_inc: float = 10.0,
    mu_max: float = 1e10,
    min_grad: float = 1e-7,
    max_fail: int = 6,
    goal: float = 0.0,
    progress=None,
) -> TrainResult:
    """Levenberg–Marquardt back-propagation, batched (MATLAB ``trainlm`` semantics).

    References: K. Levenberg (1944); D. W. Marquardt (1963); M. T. Hagan and
    M. B. Menhaj, "Training feedforward networks with the Marquardt
    algorithm", IEEE Trans. Neural Networks 5(6):989–993, 1994; MATLAB Neural
    Network Toolbox ``trainlm``.

    Each epoch, per problem: compute the training SSE ``E = Σ r²``, ``JᵀJ`` and
    ``Jᵀr``; stop if ``perf <= goal``, the epoch limit is reached, ``mu > mu_max``,
    ``‖∇E‖ = 2‖Jᵀr‖ < min_grad`` or (with validation) the validation error
    has failed to improve ``max_fail`` times in a row.  Otherwise try
    ``Δθ = -(JᵀJ + mu I)⁻¹ Jᵀr`` (Cholesky); accept it if it lowers ``E``
    (then ``mu *= mu_dec``, floored at 1e-20), else ``mu *= mu_inc`` and
    retry while ``mu <= mu_max``.  With validation the parameters with the
    lowest validation error are returned (as MATLAB does).

    ``perf`` in the history is the training MSE ``E / n_elem``.
    """
    theta = theta0.clone()
    B, P = theta.shape
    dev, dt = theta.device, theta.dtype
    mu_t = torch.full((B,), float(mu), dtype=dt, device=dev)
    book = _Bookkeeping(obj, theta, ["train", "val", "test", "mu"], epochs)
    active = torch.arange(B, device=dev)

    for epoch in range(epochs + 1):
        if active.numel() == 0:
            break
        o = obj.subset(active)
        th = theta[active]
        E, jj, je = o.sse_jj_je(th)
        perf = E / o.n_elem
        grad = 2.0 * je.norm(dim=1)
        reasons = [
            (perf <= goal, "goal"),
            (torch.full_like(perf, epoch == epochs, dtype=torch.bool), "epochs"),
            (mu_t[active] > mu_max, "mu_max"),
            (grad < min_grad, "min_grad"),
        ]
        keep = book.check(active, th, epoch, {"train": perf, "mu": mu_t[active], **o.monitor(th)}, reasons, max_fail)
        if not keep.any():
            active = active[keep]
            break
        # --- Levenberg–Marquardt trials for the problems still running
        loc = keep.nonzero().squeeze(1)
        if loc.numel() < keep.numel():  # (indexing copies; skip it while every network runs)
            jj, je, th, E = jj[loc], je[loc], th[loc], E[loc]
            o = o.subset(loc)
        _lm_trials(o, (jj, je, th, E), theta, mu_t, active[loc], (mu_dec, mu_inc, mu_max))
        active = active[keep]
        if progress is not None:
            progress(epoch)
    return book.result(theta)


def train_scg(
    obj,
    theta0: torch.Tensor,
    *,
    epochs: int = 100,
    sigma: float = 5e-5,
    lambda_: float = 5e-7,
    min_grad: float = 1e-6,
    max_fail: int = 6,
    goal: float = 0.0,
    progress=None,
) -> TrainResult:
    """Scaled conjugate gradient, batched (Møller 1993; MATLAB ``trainscg``).

    Reference: M. F. Møller, "A scaled conjugate gradient algorithm for fast
    supervised learning", Neural Networks 6(4):525–533, 1993; MATLAB Neural
    Network Toolbox ``trainscg`` (defaults ``sigma = 5e-5``, ``lambda = 5e-7``,
    ``min_grad = 1e-6``, ``max_fail = 6``).

    Per problem, with ``r = -∇E`` and search direction ``p`` (initially ``r``):

    1. if the last step succeeded: ``σ_k = σ/|p|``,
       ``s = (∇E(θ + σ_k p) − ∇E(θ))/σ_k``, ``δ = pᵀs``;
    2. scale: ``δ += (λ − λ̄)|p|²``; if ``δ <= 0``: ``λ̄ = 2(λ − δ/|p|²)``,
       ``δ = −δ + λ|p|²``, ``λ = λ̄``;
    3. ``μ = pᵀr``, ``α = μ/δ``, comparison ``Δ = 2δ(E(θ) − E(θ+αp))/μ²``;
    4. if ``Δ >= 0``: accept ``θ += αp``, ``λ̄ = 0``; restart ``p = r`` every
       ``P`` iterations, else ``β = (|r'|² − r'ᵀr)/μ``, ``p = r' + βp``;
       if ``Δ >= 0.75``: ``λ /= 4``.  Else ``λ̄ = λ`` (failure);
    5. if ``Δ < 0.25``: ``λ += δ(1 − Δ)/|p_k|²`` (``p_k`` the direction of this iteration).

    Stopping rules as :func:`train_lm` (goal, epochs, ``|∇E| < min_grad``,
    validation failures).  ``E`` is the objective's ``perf`` (the training MSE
    for networks, as in MATLAB).
    """
    state = _ScgState.start(obj, theta0, lambda_)
    B, P = state.theta.shape
    book = _Bookkeeping(obj, state.theta, ["train", "val", "test"], epochs)
    active = torch.arange(B, device=state.theta.device)

    for epoch in range(epochs + 1):
        if active.numel() == 0:
            break
        o = obj.subset(active)
        th = state.theta[active]
        pa, ga = state.perf[active], state.r[active]
        reasons = [
            (pa <= goal, "goal"),
            (torch.full_like(pa, epoch == epochs, dtype=torch.bool), "epochs"),
            (ga.norm(dim=1) < min_grad, "min_grad"),
        ]
        keep = book.check(active, th, epoch, {"train": pa, **o.monitor(th)}, reasons, max_fail)
        loc = keep.nonzero().squeeze(1)
        active = active[keep]
        if active.numel() == 0:
            break
        state.step(o.subset(loc), active, th[loc], pa[loc], ga[loc], sigma, P)
        if progress is not None:
            progress(epoch)
    return book.result(state.theta)


@dataclass
class _ScgState:
    """The per-problem state of :func:`train_scg` (B problems, P parameters): ``theta`` θ (B, P),
    ``perf`` E(θ), ``r`` = −∇E(θ) and the search direction ``p`` (B, P), ``nrm`` = |p|², ``success``
    whether the last step was accepted, ``lam``/``lamb``/``delta`` λ, λ̄, δ, ``k`` the accepted
    steps so far."""

    theta: torch.Tensor
    perf: torch.Tensor
    r: torch.Tensor
    p: torch.Tensor
    nrm: torch.Tensor
    success: torch.Tensor
    lam: torch.Tensor
    lamb: torch.Tensor
    delta: torch.Tensor
    k: torch.Tensor

    @classmethod
    def start(cls, obj, theta0: torch.Tensor, lambda_: float) -> _ScgState:
        """The state at θ₀: ``p = r = −∇E(θ₀)``, λ = ``lambda_``, λ̄ = δ = 0, every last step a success."""
        theta = theta0.clone()
        B = theta.shape[0]
        dev, dt = theta.device, theta.dtype
        perf, g = obj.perf_grad(theta)
        r = -g
        p = r.clone()
        return cls(
            theta=theta,
            perf=perf,
            r=r,
            p=p,
            nrm=(p * p).sum(1),
            success=torch.ones(B, dtype=torch.bool, device=dev),
            lam=torch.full((B,), float(lambda_), dtype=dt, device=dev),
            lamb=torch.zeros(B, dtype=dt, device=dev),
            delta=torch.zeros(B, dtype=dt, device=dev),
            k=torch.zeros(B, dtype=torch.long, device=dev),
        )

    def step(self, o, a, th, pa, ga, sigma: float, P: int) -> None:
        """One SCG iteration (:func:`_scg_step`) of the problems ``a`` (global indices; ``o`` their
        objective, ``th``/``pa``/``ga`` their θ, E, r): θ, E, r and p change where the step is
        accepted, |p|² with p, and k, success, λ, λ̄, δ everywhere."""
        st = _scg_step(
            o,
            th,
            pa,
            ga,
            self.p[a],
            self.nrm[a],
            self.lam[a],
            self.lamb[a],
            self.delta[a],
            self.success[a],
            self.k[a],
            sigma,
            P,
        )
        ok, okc = st["ok"], st["ok"][:, None]
        self.theta[a] = torch.where(okc, st["theta"], th)
        self.perf[a] = torch.where(ok, st["perf"], pa)
        self.r[a] = torch.where(okc, st["r"], ga)
        self.p[a] = torch.where(okc, st["p"], self.p[a])
        self.nrm[a] = torch.where(ok, (st["p"] * st["p"]).sum(1), self.nrm[a])
        self.k[a], self.success[a] = st["k"], ok
        self.lam[a], self.lamb[a], self.delta[a] = st["lam"], st["lamb"], st["delta"]


def _scg_step(o, th, pa, ga, p, nr, lk, lb, dk, succ, k, sigma: float, P: int) -> dict:
    """One iteration of Møller's SCG (steps 1-5 of :func:`train_scg`) for the active problems:
    ``th`` parameters, ``pa`` their objective, ``ga`` = ``r`` = −∇E, ``p`` the search direction and
    ``nr`` = |p|², ``lk``/``lb``/``dk`` λ, λ̄, δ, ``succ`` whether the last step succeeded, ``k``
    the successful steps so far.  Returns the trial point and its objective and ``r``, ``ok``
    (accepted), the next direction ``p`` (to keep only where accepted), ``k`` and the new λ, λ̄, δ.
    """
    # 1. second-order information (only used where the last step succeeded)
    if succ.any():
        sig = sigma / nr.sqrt()
        _, g_t = o.perf_grad(th + sig[:, None] * p)
        s = (g_t - (-ga)) / sig[:, None]
        dk = torch.where(succ, (p * s).sum(1), dk)
    # 2. scale
    dk = dk + (lk - lb) * nr
    neg = dk <= 0
    lb = torch.where(neg, 2.0 * (lk - dk / nr), lb)
    dk = torch.where(neg, -dk + lk * nr, dk)
    lk = torch.where(neg, lb, lk)
    # 3. step size and comparison parameter
    muk = (p * ga).sum(1)
    alpha = muk / dk
    th_new = th + alpha[:, None] * p
    perf_new, g_new = o.perf_grad(th_new)
    dif = 2.0 * dk * (pa - perf_new) / (muk * muk)
    ok = (dif >= 0) & torch.isfinite(perf_new)
    dif = torch.where(torch.isfinite(dif), dif, torch.zeros_like(dif))
    # 4. success: move, new direction (restart every P successful steps)
    k_new = k + ok.long()
    r_new = -g_new
    beta = ((r_new * r_new).sum(1) - (r_new * ga).sum(1)) / muk
    restart = (k_new % P) == 0
    p_new = torch.where(restart[:, None], r_new, r_new + beta[:, None] * p)
    lb = torch.where(ok, torch.zeros_like(lb), lk)
    # 5. adapt the scale parameter (Møller step 7 uses the |p_k|² of this iteration)
    lk = torch.where(dif < 0.25, lk + dk * (1.0 - dif) / nr, lk)
    lk = torch.where(dif >= 0.75, 0.25 * lk, lk)
    return {
        "theta": th_new,
        "perf": perf_new,
        "r": r_new,
        "ok": ok,
        "p": p_new,
        "k": k_new,
        "lam": lk,
        "lamb": lb,
        "delta": dk,
    }
