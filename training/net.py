"""The paper's multilayer perceptron, written for *batches of independent networks*.

Every function here works on ``B`` networks at once.  The parameters of the
``B`` networks are one tensor ``theta`` of shape ``(B, P)``; layer ``l`` owns a
block ``[W_l | b_l]`` of shape ``out x (in + 1)``, row-major (each neuron's
input weights followed by its bias).
Data come as ``X`` ``(B, n, n_in)`` (each network may see differently scaled
copies of the same rows, e.g. one LOOCV fold per network) and row weights
``w`` ``(B, n)`` in ``{0, 1}`` that select the rows a network trains on.

Forward pass, gradient and the full Jacobian are hand-written batched
back-propagation (``torch.bmm``/``einsum``), checked against ``torch.func`` in
the tests.  :func:`gn_system` forms ``JᵀJ`` and ``Jᵀr`` without the Jacobian, from
the exact per-sample Kronecker structure of an MLP's Jacobian (see there); it is
what makes batched Levenberg–Marquardt affordable on a CPU.

Transfer functions use MATLAB's names (the paper was done with the Neural
Network Toolbox): ``tansig`` (hyperbolic-tangent sigmoid, the toolbox default
for hidden layers), ``logsig`` (logistic sigmoid) and ``purelin`` (identity).
The output layer is always ``purelin``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from elastimap.errors import UserError

ACTIVATIONS = ("tansig", "logsig", "purelin")
_ALIASES = {
    "tanh": "tansig",
    "sigmoid": "logsig",
    "logistic": "logsig",
    "linear": "purelin",
    "lin": "purelin",
    "identity": "purelin",
}
# Output range of each transfer function (the input range of the next layer),
# and the "active" net-input range used by Nguyen-Widrow initialisation.
_OUT_RANGE = {"tansig": (-1.0, 1.0), "logsig": (0.0, 1.0), "purelin": (-math.inf, math.inf)}
_ACTIVE_RANGE = {"tansig": (-2.0, 2.0), "logsig": (-4.0, 4.0), "purelin": (-math.inf, math.inf)}


@dataclass(frozen=True)
class Arch:
    """Layer sizes and transfer functions of one MLP.

    ``hidden`` is a tuple of ``(size, activation)``; the output layer
    (``n_out`` neurons, ``purelin``) is implicit.
    """

    n_in: int = 3
    hidden: tuple[tuple[int, str], ...] = ((25, "tansig"), (10, "tansig"))
    n_out: int = 3

    @property
    def layers(self) -> list[tuple[int, int, str]]:
        """``(fan_in, fan_out, activation)`` for every layer including the output layer."""
        sizes = [self.n_in] + [s for s, _ in self.hidden] + [self.n_out]
        acts = [a for _, a in self.hidden] + ["purelin"]
        return [(sizes[i], sizes[i + 1], acts[i]) for i in range(len(acts))]

    @property
    def n_params(self) -> int:
        return sum(fo * (fi + 1) for fi, fo, _ in self.layers)

    @property
    def slices(self) -> list[slice]:
        """Parameter range of each layer's ``[W | b]`` block in ``theta``."""
        out, o = [], 0
        for fi, fo, _ in self.layers:
            out.append(slice(o, o + fo * (fi + 1)))
            o += fo * (fi + 1)
        return out

    def to_json(self) -> dict:
        return {
            "n_in": self.n_in,
            "n_out": self.n_out,
            "hidden": [{"size": s, "activation": a} for s, a in self.hidden],
            "output_activation": "purelin",
            "n_params": self.n_params,
        }

    @classmethod
    def from_json(cls, obj: dict) -> Arch:
        return cls(
            n_in=int(obj["n_in"]),
            n_out=int(obj["n_out"]),
            hidden=tuple((int(h["size"]), str(h["activation"])) for h in obj["hidden"]),
        )

    def describe(self) -> str:
        parts = [f"{s} {a}" for s, a in self.hidden] + [f"{self.n_out} purelin"]
        return f"{self.n_in} -> " + " -> ".join(parts)


def parse_hidden(
    spec: str | tuple | list, activation: str = "tansig", param: str = "hidden"
) -> tuple[tuple[int, str], ...]:
    """Parse ``"25,10"`` or ``"25,10,7:purelin"`` (per-layer ``:activation`` suffix).

    Also accepts a sequence of ints or ``(size, activation)`` pairs.
    """
    activation = _canon_act(activation, "--activation")
    if isinstance(spec, str):
        items = [s.strip() for s in spec.split(",")] if spec.strip() else []
    else:
        items = list(spec)
    out = []
    for it in items:
        if isinstance(it, (tuple, list)):
            size, act = it
        elif isinstance(it, str) and ":" in it:
            size, act = it.split(":", 1)
        else:
            size, act = it, activation
        try:
            n = int(size)
        except (TypeError, ValueError):
            raise UserError(
                param, f"layer sizes must be positive integers, e.g. 25,10 or 25,10,7:purelin (got {spec!r})"
            ) from None
        if n < 1:
            raise UserError(param, f"layer sizes must be positive integers (got {n})")
        out.append((n, _canon_act(act, param)))
    if not out:
        raise UserError(param, "need at least one hidden layer, e.g. 25,10")
    return tuple(out)


def _canon_act(name: str, param: str) -> str:
    key = str(name).strip().lower()
    key = _ALIASES.get(key, key)
    if key not in ACTIVATIONS:
        raise UserError(param, f"unknown transfer function {name!r}; use one of {', '.join(ACTIVATIONS)}")
    return key


def _act(z: torch.Tensor, name: str) -> torch.Tensor:
    if name == "tansig":
        # MATLAB's tansig formula 2/(1+exp(-2n)) - 1: equal to tanh to rounding, and faster
        # than torch.tanh in float64 on the CPU
        s = torch.sigmoid(z * 2.0)
        return s * 2.0 - 1.0 if s.requires_grad else s.mul_(2.0).sub_(1.0)
    if name == "logsig":
        return torch.sigmoid(z)
    return z


def _dact(a: torch.Tensor, name: str) -> torch.Tensor | None:
    """Derivative of the transfer function expressed through its output ``a`` (None = 1)."""
    if name == "tansig":
        return 1.0 - a * a
    if name == "logsig":
        return a * (1.0 - a)
    return None


def unpack(theta: torch.Tensor, arch: Arch) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Views ``(W (B, out, in), b (B, out))`` per layer into ``theta`` ``(B, P)``."""
    B = theta.shape[0]
    out = []
    for (fi, fo, _), sl in zip(arch.layers, arch.slices):
        Wb = theta[:, sl].reshape(B, fo, fi + 1)
        out.append((Wb[:, :, :fi], Wb[:, :, fi]))
    return out


def forward(theta: torch.Tensor, X: torch.Tensor, arch: Arch, keep: bool = False):
    """Network outputs ``(B, n, n_out)``; with ``keep`` also the layer outputs (inputs first)."""
    a = X
    acts = [a]
    for (W, b), (_, _, name) in zip(unpack(theta, arch), arch.layers):
        a = _act(torch.baddbmm(b.unsqueeze(1), a, W.transpose(1, 2)), name)
        if keep:
            acts.append(a)
    return (a, acts) if keep else a


def sse(theta: torch.Tensor, X: torch.Tensor, T: torch.Tensor, w: torch.Tensor, arch: Arch) -> torch.Tensor:
    """Sum of squared errors over the rows with weight ``w`` ``(B, n)``: shape ``(B,)``."""
    r = (forward(theta, X, arch) - T) * w.unsqueeze(-1)
    return (r * r).sum(dim=(1, 2))


def sse_grad(theta: torch.Tensor, X: torch.Tensor, T: torch.Tensor, w: torch.Tensor, arch: Arch):
    """``(sse (B,), d sse / d theta (B, P))`` by batched back-propagation."""
    Y, acts = forward(theta, X, arch, keep=True)
    r = (Y - T) * w.unsqueeze(-1)
    delta = 2.0 * r * w.unsqueeze(-1)  # dL/dY (w is 0/1, so w*w = w)
    params = unpack(theta, arch)
    layers = arch.layers
    B = theta.shape[0]
    g = torch.empty_like(theta)
    for li in range(len(layers) - 1, -1, -1):
        W, _ = params[li]
        fi, fo, _ = layers[li]
        gv = g[:, arch.slices[li]].view(B, fo, fi + 1)
        gv[:, :, :fi] = torch.bmm(delta.transpose(1, 2), acts[li])
        gv[:, :, fi] = delta.sum(dim=1)
        if li > 0:
            delta = torch.bmm(delta, W)
            d = _dact(acts[li], layers[li - 1][2])
            if d is not None:
                delta = delta * d
    return (r * r).sum(dim=(1, 2)), g


def _augment(a: torch.Tensor) -> torch.Tensor:
    """Append the constant bias input: ``(B, n, m) -> (B, n, m + 1)``."""
    return torch.cat([a, torch.ones_like(a[..., :1])], dim=-1)


def _output_deltas(theta, X, w, arch):
    """Forward pass and, per layer, ``delta[b, i, k, j] = w_bi dY[b, i, k] / dz_l[b, i, j]``."""
    B, n, _ = X.shape
    K = arch.n_out
    Y, acts = forward(theta, X, arch, keep=True)
    params = unpack(theta, arch)
    layers = arch.layers
    delta = torch.eye(K, dtype=theta.dtype, device=theta.device).expand(B, n, K, K) * w[:, :, None, None]
    deltas = [None] * len(layers)
    for li in range(len(layers) - 1, -1, -1):
        deltas[li] = delta
        if li > 0:
            delta = torch.einsum("bnko,boi->bnki", delta, params[li][0])
            d = _dact(acts[li], layers[li - 1][2])
            if d is not None:
                delta = delta * d.unsqueeze(2)
    return Y, acts, deltas


def residual_jacobian(theta: torch.Tensor, X: torch.Tensor, T: torch.Tensor, w: torch.Tensor, arch: Arch):
    """Residuals ``r = w (Y - T)`` flattened to ``(B, n*K)`` and their Jacobian ``(B, n*K, P)``.

    Rows of samples with ``w = 0`` are zero.  Row order is sample-major
    (sample ``i``, output ``k`` -> row ``i*K + k``).  Row ``(i, k)`` of layer
    ``l``'s block is ``delta_l[i, k] ⊗ [a_{l-1}[i], 1]``.
    """
    B, n, _ = X.shape
    K = arch.n_out
    Y, acts, deltas = _output_deltas(theta, X, w, arch)
    r = ((Y - T) * w.unsqueeze(-1)).reshape(B, n * K)
    blocks = [
        (dl.unsqueeze(-1) * _augment(acts[li])[:, :, None, None, :]).reshape(B, n, K, -1)
        for li, dl in enumerate(deltas)
    ]
    return r, torch.cat(blocks, dim=3).reshape(B, n * K, arch.n_params)


_SYM_CACHE: dict = {}
_EW = 50  # cost of one elementwise tensor op per element, in matrix-product flops (CPU measurement)


def _sym_plan(ol: int, il: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Gathers for a diagonal ``(ol*il) x (ol*il)`` block built from the unique pairs of ``C``
    (``ol x ol``) and ``A`` (``il x il``), pairs in ``torch.triu_indices`` order (as
    :func:`_pair_products` makes them): the flat indices of ``C``'s upper triangle, and the flat
    gather ``block[(a, c), (b, d)] = M[pair(a, b), pair(c, d)]`` from their product ``M``.
    """
    key = (ol, il, str(device))
    if key not in _SYM_CACHE:

        def maps(m):
            iu = torch.triu_indices(m, m)
            mp = torch.empty(m, m, dtype=torch.long)
            ar = torch.arange(iu.shape[1])
            mp[iu[0], iu[1]] = ar
            mp[iu[1], iu[0]] = ar
            return mp, iu.shape[1]

        mo, _ = maps(ol)
        mi, ni = maps(il)
        iu = torch.triu_indices(ol, ol)
        _SYM_CACHE[key] = (
            (iu[0] * ol + iu[1]).to(device),
            (mo[:, None, :, None] * ni + mi[None, :, None, :]).reshape(-1).to(device),
        )
    return _SYM_CACHE[key]


def _pair_products(a: torch.Tensor) -> torch.Tensor:
    """Products of every row pair ``(i <= j)`` of ``a`` ``(B, m, n)``, in ``torch.triu_indices``
    order: ``(B, m(m+1)/2, n)``.  One contiguous broadcast product per row ``i``
    (``a[i] * a[i:]``) instead of two index gathers (~3x faster on the CPU)."""
    B, m, n = a.shape
    out = torch.empty(B, m * (m + 1) // 2, n, dtype=a.dtype, device=a.device)
    o = 0
    for i in range(m):
        torch.mul(a[:, i : i + 1], a[:, i:], out=out[:, o : o + m - i])
        o += m - i
    return out


def gn_system(
    theta: torch.Tensor,
    X: torch.Tensor,
    T: torch.Tensor | None,
    w: torch.Tensor,
    arch: Arch,
    upper: bool = False,
    out: torch.Tensor | None = None,
):
    """Training SSE ``E = Σ r²`` ``(B,)``, ``JᵀJ`` ``(B, P, P)`` and ``Jᵀr`` ``(B, P)`` from one
    forward pass, without forming ``J`` (residuals and ``J`` as in :func:`residual_jacobian`).

    Exact (not an approximation).  Row ``(i, k)`` of layer ``l``'s Jacobian block is
    ``δ_l[i,k] ⊗ ã_{l-1}[i]`` (``ã`` = layer input with a trailing 1), so the ``(l, m)``
    block of ``JᵀJ`` is ``Σ_i C_i ⊗ A_i`` with ``C_i = Σ_k δ_l[i,k] δ_m[i,k]ᵀ`` and
    ``A_i = ã_{l-1}[i] ã_{m-1}[i]ᵀ``: one matrix product over the samples per block pair,
    ``K`` (= 3) times fewer flops than ``JᵀJ``.  The structure of the network supplies the
    ``C_i`` cheaply:

    * output layer (``purelin``): ``δ_L[i] = w_i I_K``, so its diagonal block is
      ``I_K ⊗ Σ_i w_i ã ãᵀ`` and its cross blocks have ``C_i = δ_l[i]`` (``w`` is 0/1);
    * last hidden layer: ``S_i = Σ_k δ δᵀ = w_i D_i (W_Lᵀ W_L) D_i`` (``D_i`` = diag of the
      transfer-function derivative);
    * hidden cross blocks by the back-propagation recursion
      ``C_{l,m} = D_l W_{l+1}ᵀ C_{l+1,m}``, ``C_{m,m} = S_m``.

    Diagonal hidden blocks use only the upper triangles of the symmetric ``C_i`` and ``A_i``
    (about 4x fewer flops), or, for a small fan-in (the first layer), the Gram matrix of the
    layer's explicit Jacobian block.  With ``upper`` only the blocks on and above the diagonal
    are written (the lower off-diagonal blocks are left undefined): all a Cholesky
    factorisation reads.  ``T = None`` skips ``E`` and ``Jᵀr`` (returned as None); ``out``
    (``(B, P, P)``, contiguous) receives ``JᵀJ``.
    """
    B, n, _ = X.shape
    layers, q = arch.layers, len(arch.layers) - 1  # q: the output layer
    dt, dev = theta.dtype, theta.device
    Y, acts = forward(theta, X, arch, keep=True)
    ones = torch.ones(B, 1, n, dtype=dt, device=dev)
    net = _Pass(
        K=arch.n_out,
        layers=layers,
        params=unpack(theta, arch),
        aT=[torch.cat([a.transpose(1, 2), ones], dim=1) for a in acts[:-1]],  # ã_l: (B, in_l + 1, n)
        der=[_dact(acts[l + 1].transpose(1, 2), layers[l][2]) for l in range(q)],  # (B, out_l, n), None = 1
        w=w,
    )
    E = je = None
    if T is not None:
        r = (Y - T) * w.unsqueeze(-1)  # (B, n, K)
        E = (r * r).sum(dim=(1, 2))
        je = net.gradient(r.transpose(1, 2), arch.n_params, arch.slices)
    P, sl = arch.n_params, arch.slices
    G = torch.empty(B, P, P, dtype=dt, device=dev) if out is None else out
    net.output_block(G[:, sl[q], sl[q]])
    for l in range(q):
        G[:, sl[l], sl[l]] = net.diagonal_block(l)
        for m in range(l + 1, q + 1):  # cross blocks with the later layers, the output layer last
            M = net.cross_block(l, m)  # (B, out_l, out_m, in_l, in_m)
            s_l, s_m = M.shape[1] * M.shape[3], M.shape[2] * M.shape[4]
            G[:, sl[l], sl[m]] = M.permute(0, 1, 3, 2, 4).reshape(B, s_l, s_m)
            if not upper:
                G[:, sl[m], sl[l]] = M.permute(0, 2, 4, 1, 3).reshape(B, s_m, s_l)
    return E, G, je


class _Pass:
    """One forward pass's quantities that the blocks of ``JᵀJ`` (:func:`gn_system`) share: the
    layer inputs ``ã_l`` (``aT``), the transfer-function derivatives ``D_l`` (``der``), the
    back-propagated ``δ_l`` (B, out_l, K, n) with the sample weights ``w`` folded in, and the
    per-sample ``S_m = Σ_k δ_m δ_mᵀ`` of the hidden layers whose diagonal block needs them."""

    def __init__(self, K, layers, params, aT, der, w):
        self.K, self.layers, self.params, self.aT, self.der, self.w = K, layers, params, aT, der, w
        self.q = len(layers) - 1
        self.B, self.n = w.shape
        self.deltas = self._deltas()
        self.explicit = [self._explicit(m) for m in range(self.q)]
        self.S = [None if (m == 0 and self.explicit[0]) else self._S(m) for m in range(self.q)]

    def _back(self, l: int, d: torch.Tensor) -> torch.Tensor:
        """``D_{l-1} W_lᵀ d`` for ``d`` (B, out_l, ...): one step of back-propagation."""
        fo = self.layers[l][1]
        Wt = self.params[l][0].transpose(1, 2)  # (B, out_{l-1}, out_l)
        shape = d.shape
        d = torch.bmm(Wt, d.reshape(self.B, fo, -1)).reshape(self.B, Wt.shape[1], *shape[2:])
        if self.der[l - 1] is not None:
            dl = self.der[l - 1]
            d.mul_(dl.reshape(self.B, dl.shape[1], *([1] * (len(shape) - 3)), self.n))
        return d

    def _deltas(self) -> list[torch.Tensor]:
        K, q = self.K, self.q
        d = torch.eye(K, dtype=self.w.dtype, device=self.w.device)[None, :, :, None] * self.w[:, None, None, :]
        out = [None] * (q + 1)
        for l in range(q, -1, -1):
            out[l] = d
            if l > 0:
                d = self._back(l, d)
        return out

    def gradient(self, e: torch.Tensor, P: int, sl) -> torch.Tensor:
        """``Jᵀr`` (B, P) for the weighted residuals ``e`` (B, K, n), back-propagated alike."""
        je = torch.empty(self.B, P, dtype=e.dtype, device=e.device)
        for l in range(self.q, -1, -1):
            je[:, sl[l]] = torch.bmm(e, self.aT[l].transpose(1, 2)).reshape(self.B, -1)
            if l > 0:
                e = self._back(l, e)
        return je

    def _explicit(self, m: int) -> bool:
        """Whether layer ``m``'s diagonal block is cheaper as the Gram matrix of its explicit
        Jacobian block than from the upper triangles of ``C_i`` and ``A_i``."""
        fi, fo, _ = self.layers[m]
        K = self.K
        s_m, po, pi = fo * (fi + 1), fo * (fo + 1) // 2, (fi + 1) * (fi + 2) // 2
        return K * s_m * s_m + _EW * K * s_m <= po * pi + _EW * (2 * K * po + pi)

    def _S(self, m: int) -> torch.Tensor:
        """``S_m`` (B, out_m, out_m, n); for the last hidden layer ``w_i D_i (W_Lᵀ W_L) D_i``."""
        if m == self.q - 1:
            Wq = self.params[self.q][0]
            S = torch.bmm(Wq.transpose(1, 2), Wq).unsqueeze(-1) * self.w[:, None, None, :]
            if self.der[m] is not None:
                S.mul_(self.der[m].unsqueeze(2)).mul_(self.der[m].unsqueeze(1))
            return S
        dm = self.deltas[m]
        return (dm.unsqueeze(2) * dm.unsqueeze(1)).sum(3)

    def output_block(self, Gq: torch.Tensor) -> None:
        """The output layer's (``purelin``) diagonal block ``I_K ⊗ Σ_i w_i ã ãᵀ`` into ``Gq``."""
        a = self.aT[self.q]
        iq = a.shape[1]
        H = torch.bmm(a * self.w[:, None, :], a.transpose(1, 2))
        Gq.zero_()
        for k in range(self.K):
            Gq[:, k * iq : (k + 1) * iq, k * iq : (k + 1) * iq] = H

    def diagonal_block(self, l: int) -> torch.Tensor:
        """Hidden layer ``l``'s diagonal block (B, s_l, s_l)."""
        dl, al = self.deltas[l], self.aT[l]
        ol, il = dl.shape[1], al.shape[1]
        s_l, B = ol * il, self.B
        if self.explicit[l]:
            Jl = (dl.unsqueeze(2) * al[:, None, :, None, :]).reshape(B, s_l, self.K * self.n)
            return torch.bmm(Jl, Jl.transpose(1, 2))
        pairs, flat = _sym_plan(ol, il, al.device)
        C = self.S[l].reshape(B, ol * ol, self.n)[:, pairs]  # (B, #pairs_o, n)
        A = _pair_products(al)  # (B, #pairs_i, n)
        M = torch.bmm(C, A.transpose(1, 2)).reshape(B, -1)
        return M.index_select(1, flat).reshape(B, s_l, s_l)

    def cross_block(self, l: int, m: int) -> torch.Tensor:
        """The ``(l, m)`` block, ``l < m``, as (B, out_l, out_m, in_l, in_m): ``Σ_i C_i ⊗ A_i`` with
        ``C_{l,m}`` from ``S_m`` by ``C_{p,m} = D_p W_{p+1}ᵀ C_{p+1,m}`` (hidden ``m``) or
        ``C_i = δ_l[i]`` (``m`` the output layer)."""
        B, n = self.B, self.n
        al, am = self.aT[l], self.aT[m]
        ol, il, im = self.deltas[l].shape[1], al.shape[1], am.shape[1]
        if m == self.q:
            C, om = self.deltas[l], self.K
        else:
            C, om = self.S[m], self.layers[m][1]
            for p in range(m - 1, l - 1, -1):
                C = self._back(p + 1, C)
        A = (al.unsqueeze(2) * am.unsqueeze(1)).reshape(B, il * im, n)
        return torch.bmm(C.reshape(B, ol * om, n), A.transpose(1, 2)).view(B, ol, om, il, im)


def init_nguyen_widrow(
    arch: Arch, B: int, generator: torch.Generator, dtype=torch.float64, device="cpu"
) -> torch.Tensor:
    """Initial parameters ``(B, P)``, MATLAB ``initnw`` style.

    Nguyen & Widrow (1990), "Improving the learning speed of 2-layer neural
    networks by choosing initial values of the adaptive weights", IJCNN: for a
    layer with ``S`` neurons and ``R`` inputs, weight rows are random unit
    vectors of magnitude ``0.7 S^(1/R)``, biases spread evenly over
    ``[-mag, mag]`` (sign of the first weight), then both are mapped so the net
    inputs cover the transfer function's active range (``[-2, 2]`` tansig,
    ``[-4, 4]`` logsig) for inputs in the previous layer's output range
    (``[-1, 1]`` for the mapminmax-scaled inputs).  Layers with an unbounded
    active range (``purelin``, including the output layer) get uniform
    ``[-1, 1]`` weights and biases (``rands``), as ``initnw`` does.
    Draws are made on the CPU from ``generator`` so results do not depend on the device.
    """
    cols = []
    in_range = (-1.0, 1.0)
    for fi, fo, name in arch.layers:
        lo, hi = _ACTIVE_RANGE[name]
        if math.isinf(lo) or math.isinf(in_range[0]):
            W = torch.rand(B, fo, fi, generator=generator, dtype=torch.float64) * 2 - 1
            b = torch.rand(B, fo, generator=generator, dtype=torch.float64) * 2 - 1
        else:
            mag = 0.7 * fo ** (1.0 / fi)
            d = torch.randn(B, fo, fi, generator=generator, dtype=torch.float64)
            d = d / d.norm(dim=2, keepdim=True)
            W = mag * d
            if fo == 1:
                b = torch.zeros(B, 1, dtype=torch.float64)
            else:
                b = mag * torch.linspace(-1, 1, fo, dtype=torch.float64) * torch.sign(W[:, :, 0])
            x, y = 0.5 * (hi - lo), 0.5 * (hi + lo)
            W, b = x * W, x * b + y
            # inputs in [in_lo, in_hi] instead of [-1, 1]
            ilo, ihi = in_range
            gx = 2.0 / (ihi - ilo)
            gy = 1.0 - ihi * gx
            b = b + W.sum(dim=2) * gy
            W = W * gx
        cols.append(torch.cat([W, b.unsqueeze(-1)], dim=2).reshape(B, -1))
        in_range = _OUT_RANGE[name]
    return torch.cat(cols, dim=1).to(dtype=dtype, device=device)
