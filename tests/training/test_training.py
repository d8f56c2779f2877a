"""Training stage: network maths, optimisers against independent references, batching.

All data here are SYNTHETIC (analytic toy maps or random teachers), not FEM results.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from elastimap.training.net import (
    Arch,
    forward,
    gn_system,
    init_nguyen_widrow,
    parse_hidden,
    residual_jacobian,
    sse,
    sse_grad,
)
from elastimap.training.optim import _lm_step_torch, lm_step, train_lm, train_scg
from elastimap.training.problem import NetObjective, mapminmax_apply, mapminmax_fit, mapminmax_reverse

torch.set_num_threads(1)
F64 = torch.float64


class FnObjective:
    """A batched scalar function with autograd gradients (for the SCG reference problems)."""

    has_val = False

    def __init__(self, f):
        self.f = f

    def subset(self, idx):
        return self

    def perf(self, th):
        return self.f(th)

    def perf_grad(self, th):
        th = th.detach().requires_grad_(True)
        v = self.f(th)
        (g,) = torch.autograd.grad(v.sum(), th)
        return v.detach(), g

    def monitor(self, th):
        return {}


def _small_problem(B=3, n=9, seed=0, arch=None):
    arch = arch or Arch(3, ((5, "tansig"), (4, "logsig"), (3, "purelin")), 2)
    g = torch.Generator().manual_seed(seed)
    th = init_nguyen_widrow(arch, B, g)
    X = torch.randn(B, n, 3, generator=g, dtype=F64)
    T = torch.randn(B, n, arch.n_out, generator=g, dtype=F64)
    w = (torch.rand(B, n, generator=g) > 0.3).to(F64)
    return arch, th, X, T, w


def test_parse_hidden_and_arch():
    assert parse_hidden("25,10") == ((25, "tansig"), (10, "tansig"))
    assert parse_hidden("25,10,7:purelin") == ((25, "tansig"), (10, "tansig"), (7, "purelin"))
    assert parse_hidden((25, 10), "logsig") == ((25, "logsig"), (10, "logsig"))
    arch = Arch()
    assert arch.n_params == 25 * 4 + 10 * 26 + 3 * 11 == 393
    assert Arch(3, parse_hidden("25,10,7:purelin"), 3).n_params == 393 + 7 * 11 - 3 * 11 + 3 * 8
    from elastimap.errors import UserError

    for bad in ("", "25,x", "0,10", "25:relu"):
        with pytest.raises(UserError):
            parse_hidden(bad)


def test_gradient_jacobian_gauss_newton_match_torch_func():
    from torch.func import grad, jacrev, vmap

    arch, th, X, T, w = _small_problem()
    E, G = sse_grad(th, X, T, w, arch)
    r, J = residual_jacobian(th, X, T, w, arch)

    def f1(t, x, tt, ww):
        return sse(t[None], x[None], tt[None], ww[None], arch)[0]

    def r1(t, x, tt, ww):
        return ((forward(t[None], x[None], arch) - tt[None]) * ww[None, :, None]).reshape(-1)

    torch.testing.assert_close(G, vmap(grad(f1))(th, X, T, w), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(J, vmap(jacrev(r1))(th, X, T, w), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(E, (r * r).sum(1))
    torch.testing.assert_close(gn_system(th, X, None, w, arch)[1], J.transpose(1, 2) @ J, rtol=1e-11, atol=1e-11)
    # the paper-sized network too (exercises both diagonal-block strategies)
    arch2 = Arch()
    _, th2, X2, T2, w2 = _small_problem(B=2, n=20, arch=arch2)
    _, J2 = residual_jacobian(th2, X2, T2, w2, arch2)
    torch.testing.assert_close(gn_system(th2, X2, None, w2, arch2)[1], J2.transpose(1, 2) @ J2, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("hidden", ["25,10", "25,10,7:purelin", "4,3:logsig", "6", "5:purelin,4"])
def test_gn_system_matches_explicit_jacobian(hidden):
    """SSE, JᵀJ (full and upper-triangle-only) and Jᵀr against the explicit Jacobian, for every
    structural case of gn_system: explicit and pair-product diagonal blocks, one to three hidden
    layers, tansig / logsig / purelin hidden layers."""
    arch = Arch(3, parse_hidden(hidden), 3)
    _, th, X, T, w = _small_problem(B=2, n=17, seed=3, arch=arch)
    r, J = residual_jacobian(th, X, T, w, arch)
    JJ = J.transpose(1, 2) @ J
    E, G, je = gn_system(th, X, T, w, arch)
    torch.testing.assert_close(G, JJ, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(je, (J.transpose(1, 2) @ r.unsqueeze(-1)).squeeze(-1), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(E, (r * r).sum(1))
    out = torch.full_like(G, float("nan"))
    E2, G2, je2 = gn_system(th, X, T, w, arch, upper=True, out=out)
    assert G2 is out
    torch.testing.assert_close(G2.triu(), JJ.triu(), rtol=1e-10, atol=1e-10)
    assert torch.equal(E2, E) and torch.equal(je2, je)


def test_lm_step_matches_dense_solve_and_flags_indefinite():
    g = torch.Generator().manual_seed(5)
    for dt in (torch.float32, F64):
        a = torch.randn(4, 12, 30, generator=g, dtype=F64)
        jj = (a @ a.transpose(1, 2)).to(dt)
        jj[2] = -torch.eye(12, dtype=dt)  # not positive definite at mu = 0.5
        je = torch.randn(4, 12, generator=g, dtype=F64).to(dt)
        mu = torch.tensor([1e-3, 1.0, 0.5, 10.0], dtype=dt)
        garbage = jj + torch.tril(torch.full_like(jj, float("nan")), -1)  # only the upper triangle is read
        before = garbage.clone()
        dx, ok = lm_step(garbage, je, mu)
        assert torch.equal(garbage.isnan(), before.isnan()) and torch.equal(garbage.nan_to_num(), before.nan_to_num())
        assert ok.tolist() == [True, True, False, True]
        for b in (0, 1, 3):
            ref = -torch.linalg.solve(jj[b].double() + mu[b].double() * torch.eye(12, dtype=F64), je[b].double())
            torch.testing.assert_close(
                dx[b].double(),
                ref,
                rtol=1e-3 if dt == torch.float32 else 1e-10,
                atol=1e-4 if dt == torch.float32 else 1e-10,
            )
        idx = torch.tensor([3, 0])
        dx2, ok2 = lm_step(garbage, je, mu[idx], idx)
        assert ok2.all() and torch.equal(dx2, dx[idx])
        # the torch path (used on GPUs) gives the same steps
        dx3, ok3 = _lm_step_torch(garbage, je, mu)
        assert torch.equal(ok3, ok)
        tol = dict(rtol=1e-4, atol=1e-5) if dt == torch.float32 else dict(rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(dx3[ok3], dx[ok], **tol)
        assert torch.equal(garbage.isnan(), before.isnan())


def test_mapminmax_matches_matlab_convention():
    A = np.array([[1.0, 10.0], [3.0, 30.0], [2.0, 20.0]])
    lo, hi = mapminmax_fit(A)
    S = mapminmax_apply(A, lo, hi)
    np.testing.assert_allclose(S, [[-1, -1], [1, 1], [0, 0]])
    np.testing.assert_allclose(mapminmax_reverse(S, lo, hi), A)
    lo2, hi2 = mapminmax_fit(A, mask=np.array([True, False, True]))  # training rows only
    np.testing.assert_allclose(hi2, [2.0, 20.0])


def test_nguyen_widrow_init_shapes_and_ranges():
    arch = Arch()
    th = init_nguyen_widrow(arch, 4, torch.Generator().manual_seed(0))
    assert th.shape == (4, 393) and torch.isfinite(th).all()
    from elastimap.training.net import unpack

    W1, b1 = unpack(th, arch)[0]
    # tansig layer: |w| = 2 * 0.7 * 25^(1/3) per row (inputs in [-1, 1])
    torch.testing.assert_close(W1.norm(dim=2), torch.full((4, 25), 2 * 0.7 * 25 ** (1 / 3), dtype=F64))
    Wo, bo = unpack(th, arch)[2]
    assert Wo.abs().max() <= 1 and bo.abs().max() <= 1


def test_lm_reaches_scipy_least_squares_loss():
    """Same start, same network: our LM and MINPACK's LM end at the same sum of squares."""
    from scipy.optimize import least_squares

    arch = Arch(3, ((4, "tansig"),), 2)
    g = torch.Generator().manual_seed(0)
    n = 150
    X = torch.rand(1, n, 3, generator=g, dtype=F64) * 2 - 1
    teacher = init_nguyen_widrow(arch, 1, g)
    T = forward(teacher, X, arch) + 0.02 * torch.randn(1, n, 2, generator=g, dtype=F64)
    w = torch.ones(1, n, dtype=F64)
    obj = NetObjective(arch, X, T, w)

    def fun(th):
        return (forward(torch.as_tensor(th)[None], X, arch) - T).reshape(-1).numpy()

    def jac(th):
        return residual_jacobian(torch.as_tensor(th)[None], X, T, w, arch)[1][0].numpy()

    for _ in range(2):
        th0 = teacher + 0.5 * torch.randn(teacher.shape, generator=g, dtype=F64)
        res = train_lm(obj, th0, epochs=100, min_grad=1e-12)
        ref = least_squares(fun, th0[0].numpy(), jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        ours = obj.sse(res.theta).item()
        assert ours == pytest.approx(2 * ref.cost, rel=1e-9)
        # same fitted function (parameters may differ by hidden-unit symmetries)
        np.testing.assert_allclose(
            forward(res.theta, X, arch)[0].numpy(), (fun(ref.x).reshape(n, 2) + T[0].numpy()), atol=1e-6
        )


def test_lm_trainlm_semantics_mu_and_stops():
    arch, th, X, T, w = _small_problem(B=2, n=30, arch=Arch(3, ((3, "tansig"),), 2))
    obj = NetObjective(arch, X, T, w)
    res = train_lm(obj, th, epochs=5)
    mu = res.history["mu"]
    assert mu[:, 0].tolist() == [1e-3, 1e-3]
    ratios = (mu[:, 1:6] / mu[:, 0:5]).flatten()
    # each epoch mu is multiplied by 0.1 once after some number of x10 failures
    logs = torch.log10(ratios)
    assert torch.allclose(logs, logs.round()) and (logs >= -1 - 1e-9).all()
    assert res.stop == ["epochs", "epochs"] and res.epochs.tolist() == [5, 5]
    tr = res.history["train"]
    assert (tr[:, 1:] <= tr[:, :-1]).all(), "LM only accepts steps that lower the error"
    # min_grad stop
    res = train_lm(obj, th, epochs=50, min_grad=1e6)
    assert res.stop == ["min_grad", "min_grad"] and res.epochs.tolist() == [0, 0]


def test_validation_early_stop_returns_best_network():
    arch = Arch(3, ((10, "tansig"),), 2)
    g = torch.Generator().manual_seed(3)
    n = 40
    X = torch.randn(1, n, 3, generator=g, dtype=F64)
    T = torch.randn(1, n, 2, generator=g, dtype=F64)  # pure noise: overfits at once
    val = torch.zeros(1, n, dtype=F64)
    val[0, :12] = 1
    obj = NetObjective(arch, X, T, 1 - val, w_val=val)
    th0 = init_nguyen_widrow(arch, 1, g)
    for fn in (train_lm, train_scg):
        res = fn(obj, th0, epochs=200)
        assert res.stop == ["val_fail"]
        v = res.history["val"][0]
        best = int(torch.argmin(torch.nan_to_num(v, nan=np.inf)))
        assert res.epochs.item() == best + 6
        assert obj.monitor(res.theta)["val"].item() == pytest.approx(v[best].item())


def test_scg_solves_quadratic_in_n_steps():
    P = 10
    g = torch.Generator().manual_seed(1)
    Q, _ = torch.linalg.qr(torch.randn(P, P, generator=g, dtype=F64))
    A = Q @ torch.diag(torch.linspace(1, 10, P, dtype=F64)) @ Q.T
    b = torch.randn(3, P, generator=g, dtype=F64)  # three problems in one batch
    obj = FnObjective(lambda th: 0.5 * ((th @ A) * th).sum(1) - (th * b).sum(1))
    res = train_scg(obj, torch.zeros(3, P, dtype=F64), epochs=P, min_grad=0.0, goal=-np.inf)
    xs = torch.linalg.solve(A, b.T).T
    assert ((res.theta - xs).norm(dim=1) / xs.norm(dim=1)).max() < 1e-6
    # and not before: after P - 3 steps a generic problem is still unsolved
    early = train_scg(obj, torch.zeros(3, P, dtype=F64), epochs=P - 3, min_grad=0.0, goal=-np.inf)
    assert ((early.theta - xs).norm(dim=1) / xs.norm(dim=1)).min() > 1e-4


def test_scg_minimises_rosenbrock():
    def rosen(th):
        return 100 * (th[:, 1] - th[:, 0] ** 2) ** 2 + (1 - th[:, 0]) ** 2

    starts = torch.tensor([[-1.2, 1.0], [2.0, -1.0], [0.0, 0.0]], dtype=F64)
    res = train_scg(FnObjective(rosen), starts, epochs=1000, min_grad=1e-9)
    torch.testing.assert_close(res.theta, torch.ones(3, 2, dtype=F64), atol=1e-5, rtol=0)
    assert all(s == "min_grad" for s in res.stop)


@pytest.mark.parametrize("algo", ["lm", "scg"])
def test_batched_equals_unbatched(algo):
    """LOOCV-style batch (different rows per network) == each network trained alone."""
    arch = Arch(3, ((6, "tansig"), (3, "tansig")), 3)
    g = torch.Generator().manual_seed(5)
    B, n = 4, 25
    X = torch.rand(B, n, 3, generator=g, dtype=F64) * 2 - 1
    T = torch.rand(B, n, 3, generator=g, dtype=F64) * 2 - 1
    w = torch.ones(B, n, dtype=F64)
    w[torch.arange(B), torch.arange(B)] = 0
    test = 1 - w
    th0 = init_nguyen_widrow(arch, B, g)
    fn = train_lm if algo == "lm" else train_scg
    batched = fn(NetObjective(arch, X, T, w, w_test=test), th0, epochs=30)
    for b in range(B):
        s = slice(b, b + 1)
        alone = fn(NetObjective(arch, X[s], T[s], w[s], w_test=test[s]), th0[s], epochs=30)
        torch.testing.assert_close(batched.theta[s], alone.theta, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(
            batched.history["train"][s], alone.history["train"], rtol=1e-9, atol=1e-12, equal_nan=True
        )
        assert batched.stop[b] == alone.stop[0]


def test_chunked_training_equals_one_chunk():
    from elastimap.training.data import FEATURES, TARGETS, synthetic_table
    from elastimap.training.experiment import TrainConfig, make_batch, train_batch

    df = synthetic_table(40, seed=2, phantoms=False)
    X, T = df[list(FEATURES)].to_numpy(), df[list(TARGETS)].to_numpy()
    fit = ~np.eye(40, dtype=bool)[:6]
    cfg = TrainConfig(hidden=((4, "tansig"),), epochs=15, progress=False)
    b = make_batch(X, T, fit, ~fit, cfg, np.random.default_rng(0), torch.Generator().manual_seed(0))
    whole = train_batch("lm", b.obj, b.theta0, cfg)
    cfg_small = TrainConfig(hidden=((4, "tansig"),), epochs=15, progress=False, mem_bytes=1)  # one net per chunk
    pieces = train_batch("lm", b.obj, b.theta0, cfg_small)
    torch.testing.assert_close(whole.theta, pieces.theta, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("algo", ["lm", "scg"])
def test_worker_processes_give_the_serial_result(algo):
    """Chunks shared out to two spawned processes reproduce the serial loop exactly."""
    from elastimap.training.data import FEATURES, TARGETS, synthetic_table
    from elastimap.training.experiment import TrainConfig, make_batch, train_batch

    df = synthetic_table(40, seed=3, phantoms=False)
    X, T = df[list(FEATURES)].to_numpy(), df[list(TARGETS)].to_numpy()
    fit = ~np.eye(40, dtype=bool)[:6]
    kw = dict(hidden=((4, "tansig"),), epochs=12, progress=False, mem_bytes=1)  # one net per chunk
    b = make_batch(X, T, fit, ~fit, TrainConfig(**kw), np.random.default_rng(0), torch.Generator().manual_seed(0))
    assert TrainConfig(**kw, workers=2).n_workers(6) == 2
    serial = train_batch(algo, b.obj, b.theta0, TrainConfig(**kw, workers=1))
    parallel = train_batch(algo, b.obj, b.theta0, TrainConfig(**kw, workers=2))
    torch.testing.assert_close(parallel.theta, serial.theta, rtol=1e-12, atol=1e-12)
    assert parallel.stop == serial.stop
    assert torch.equal(parallel.epochs, serial.epochs)
    torch.testing.assert_close(
        parallel.history["train"], serial.history["train"], rtol=1e-12, atol=1e-12, equal_nan=True
    )
