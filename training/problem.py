"""Batched training problems: ``B`` networks, each with its own rows and scaling.

:func:`mapminmax_fit` / :func:`mapminmax_apply` / :func:`mapminmax_reverse`
follow MATLAB's ``mapminmax`` with the default output range ``[-1, 1]``:
``y = (ymax - ymin) (x - xmin) / (xmax - xmin) + ymin`` per column.

:class:`NetObjective` is the optimiser-facing objective (see
:mod:`elastimap.training.optim`): training rows ``w_train``, optional validation rows
``w_val`` (early stopping) and test rows ``w_test`` (only monitored).
"""

from __future__ import annotations

import numpy as np
import torch

from . import net as _net
from .net import Arch

YMIN, YMAX = -1.0, 1.0


def mapminmax_fit(A: np.ndarray, mask: np.ndarray | None = None, axis: int = -2):
    """Column minima and maxima of ``A`` over the rows where ``mask`` is true.

    ``A``: ``(..., n, c)``; ``mask``: broadcastable ``(..., n)``.  Returns
    ``(lo, hi)`` of shape ``(..., c)``.
    """
    A = np.asarray(A, dtype=np.float64)
    if mask is None:
        return A.min(axis=axis), A.max(axis=axis)
    m = np.asarray(mask, dtype=bool)[..., None]
    lo = np.where(m, A, np.inf).min(axis=axis)
    hi = np.where(m, A, -np.inf).max(axis=axis)
    return lo, hi


def mapminmax_apply(A, lo, hi):
    """Scale columns to ``[-1, 1]`` (``lo``/``hi`` broadcast over the row axis)."""
    lo = np.asarray(lo)[..., None, :]
    hi = np.asarray(hi)[..., None, :]
    return (YMAX - YMIN) * (np.asarray(A) - lo) / (hi - lo) + YMIN


def mapminmax_reverse(S, lo, hi):
    lo = np.asarray(lo)[..., None, :]
    hi = np.asarray(hi)[..., None, :]
    return (np.asarray(S) - YMIN) * (hi - lo) / (YMAX - YMIN) + lo


def compact_rows(mask: torch.Tensor):
    """``(B, n)`` 0/1 mask -> row indices ``(B, m)`` and weights ``(B, m)``, ``m`` = most rows of any network."""
    m = int(mask.sum(1).max().item()) if mask.numel() else 0
    m = max(m, 1)
    idx = torch.argsort(-mask, dim=1, stable=True)[:, :m]
    return idx, mask.gather(1, idx)


class NetObjective:
    """MLP training objective for ``B`` networks (performance = training MSE).

    ``X``: ``(B, n, n_in)`` scaled inputs; ``T``: ``(B, n, n_out)`` scaled
    targets; ``w_train``/``w_val``/``w_test``: ``(B, n)`` 0/1 row selections.
    Validation and test rows are monitored on gathered rows only (cheap for
    LOOCV's single test row).  ``work_bytes`` bounds the intermediate memory
    of one ``JᵀJ`` block (networks are processed in sub-chunks).
    """

    def __init__(self, arch: Arch, X, T, w_train, w_val=None, w_test=None, work_bytes: int = 64 << 20, _rows=None):
        self.arch = arch
        self.X, self.T, self.w = X, T, w_train
        self.w_val, self.w_test = w_val, w_test
        self.work_bytes = work_bytes
        self.n_elem = w_train.sum(1) * arch.n_out
        self.has_val = w_val is not None
        if _rows is None:
            _rows = {k: compact_rows(v) for k, v in (("val", w_val), ("test", w_test)) if v is not None}
        self._rows = _rows

    @property
    def B(self) -> int:
        return self.X.shape[0]

    def subset(self, idx) -> NetObjective:
        sel = lambda t: None if t is None else t[idx]
        return NetObjective(
            self.arch,
            self.X[idx],
            self.T[idx],
            self.w[idx],
            sel(self.w_val),
            sel(self.w_test),
            self.work_bytes,
            {k: (i[idx], w[idx]) for k, (i, w) in self._rows.items()},
        )

    def sse(self, theta):
        return _net.sse(theta, self.X, self.T, self.w, self.arch)

    def perf(self, theta):
        return self.sse(theta) / self.n_elem

    def perf_grad(self, theta):
        E, g = _net.sse_grad(theta, self.X, self.T, self.w, self.arch)
        return E / self.n_elem, g / self.n_elem[:, None]

    def sse_jj_je(self, theta):
        """Training SSE, ``JᵀJ`` and ``Jᵀr`` (= ∇SSE / 2) by :func:`elastimap.training.net.gn_system`.

        Only the upper triangle of ``JᵀJ`` is defined (all the Cholesky factorisation of
        Levenberg–Marquardt reads).  Networks go through in sub-chunks whose temporaries
        stay within ``work_bytes``.
        """
        B, n, _ = self.X.shape
        P = self.arch.n_params
        K = self.arch.n_out
        lay = self.arch.layers
        el = theta.element_size()
        # largest temporaries per network: each hidden layer's deltas, pair products, cross
        # products and explicit first-layer Jacobian, over the n samples; plus JᵀJ itself
        per_sample = sum(fo * K + fo * fo + (fi + 1) * (fi + 2) // 2 for fi, fo, _ in lay[:-1])
        per_sample += sum(
            (lay[a][0] + 1) * (lay[b][0] + 1) + lay[a][1] * lay[b][1]
            for a in range(len(lay))
            for b in range(a + 1, len(lay))
        )
        per_sample += lay[0][1] * (lay[0][0] + 1) * K
        per = n * el * per_sample + P * P * el
        step = max(1, int(self.work_bytes // max(per, 1)))
        E = torch.empty(B, dtype=theta.dtype, device=theta.device)
        jj = torch.empty(B, P, P, dtype=theta.dtype, device=theta.device)
        je = torch.empty(B, P, dtype=theta.dtype, device=theta.device)
        for s in range(0, B, step):
            sl = slice(s, min(B, s + step))
            E[sl], _, je[sl] = _net.gn_system(
                theta[sl], self.X[sl], self.T[sl], self.w[sl], self.arch, upper=True, out=jj[sl]
            )
        return E, jj, je

    def monitor(self, theta):
        out = {}
        K = self.arch.n_out
        for name, (idx, wm) in self._rows.items():
            Xg = self.X.gather(1, idx.unsqueeze(-1).expand(-1, -1, self.X.shape[2]))
            Tg = self.T.gather(1, idx.unsqueeze(-1).expand(-1, -1, self.T.shape[2]))
            sq = ((_net.forward(theta, Xg, self.arch) - Tg) ** 2).sum(-1)
            cnt = wm.sum(1) * K
            out[name] = torch.where(cnt > 0, (sq * wm).sum(1) / cnt.clamp(min=1), torch.full_like(cnt, float("nan")))
        return out
