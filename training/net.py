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
the tests.  :func:`gauss_newton` forms ``JᵀJ`` without the Jacobian, from the
exact per-sample Kronecker structure of an MLP's Jacobian (see there); it is
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
_ALIASES = {"tanh": "tansig", "sigmoid": "logsig", "logistic": "logsig", "linear": "purelin",
            "lin": "purelin", "identity": "purelin"}
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
        return {"n_in": self.n_in, "n_out": self.n_out,
                "hidden": [{"size": s, "activation": a} for s, a in self.hidden],
                "output_activation": "purelin", "n_params": self.n_params}

    @classmethod
    def from_json(cls, obj: dict) -> "Arch":
        return cls(n_in=int(obj["n_in"]), n_out=int(obj["n_out"]),
                   hidden=tuple((int(h["size"]), str(h["activation"])) for h in obj["hidden"]))

    def describe(self) -> str:
        parts = [f"{s} {a}" for s, a in self.hidden] + [f"{self.n_out} purelin"]
        return f"{self.n_in} -> " + " -> ".join(parts)


def parse_hidden(spec: str | tuple | list, activation: str = "tansig", param: str = "--hidden") -> tuple[tuple[int, str], ...]:
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
            raise UserError(param, f"layer sizes must be positive integers, e.g. 25,10 or 25,10,7:purelin (got {spec!r})") from None
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
    blocks = [(dl.unsqueeze(-1) * _augment(acts[li])[:, :, None, None, :]).reshape(B, n, K, -1)
              for li, dl in enumerate(deltas)]
    return r, torch.cat(blocks, dim=3).reshape(B, n * K, arch.n_params)


_SYM_CACHE: dict = {}
_EW = 50  # cost of one elementwise tensor op per element, in matrix-product flops (CPU measurement)


def _sym_plan(ol: int, il: int, device) -> torch.Tensor:
    """Flat gather that rebuilds a diagonal ``(ol*il) x (ol*il)`` block from the product of the
    unique pairs of ``C`` (``ol x ol``) and ``A`` (``il x il``), pairs in ``torch.triu_indices``
    order (as :func:`_pair_products` makes them): ``block[(a, c), (b, d)] = M[pair(a, b), pair(c, d)]``.
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
        _SYM_CACHE[key] = (mo[:, None, :, None] * ni + mi[None, :, None, :]).reshape(-1).to(device)
    return _SYM_CACHE[key]


def _pair_products(a: torch.Tensor, summed: bool = False) -> torch.Tensor:
    """Products of every row pair ``(i <= j)`` of ``a`` ``(B, m, n)`` (``(B, m, K, n)`` with ``summed``:
    summed over ``K``), in ``torch.triu_indices`` order: ``(B, m(m+1)/2, n)``.  One contiguous
    broadcast product per row ``i`` (``a[i] * a[i:]``) instead of two index gathers (~3x faster on
    the CPU)."""
    B, m, n = a.shape[0], a.shape[1], a.shape[-1]
    out = torch.empty(B, m * (m + 1) // 2, n, dtype=a.dtype, device=a.device)
    o = 0
    for i in range(m):
        blk = out[:, o:o + m - i]
        if summed:
            torch.sum(a[:, i:i + 1] * a[:, i:], dim=2, out=blk)
        else:
            torch.mul(a[:, i:i + 1], a[:, i:], out=blk)
        o += m - i
    return out


def gauss_newton(theta: torch.Tensor, X: torch.Tensor, w: torch.Tensor, arch: Arch) -> torch.Tensor:
    """``JᵀJ`` ``(B, P, P)`` of the residuals of :func:`residual_jacobian`, without forming ``J``.

    Exact (not an approximation): row ``(i, k)`` of layer ``l``'s Jacobian
    block is ``δ_l[i,k] ⊗ ã_{l-1}[i]`` (``ã`` = layer input with a trailing 1),
    so the ``(l, m)`` block of ``JᵀJ`` is
    ``Σ_i C_i ⊗ A_i`` with ``C_i = Σ_k δ_l[i,k] δ_m[i,k]ᵀ`` and
    ``A_i = ã_{l-1}[i] ã_{m-1}[i]ᵀ``: one matrix product over the samples
    per block pair, ``K`` (= 3) times fewer flops than ``JᵀJ``, and for
    diagonal blocks only the upper triangles of the symmetric ``C_i`` and
    ``A_i`` enter the product (about 4x fewer again).  Everything is laid
    out samples-last so the gathers copy contiguous rows.
    """
    B, n, _ = X.shape
    K = arch.n_out
    layers = arch.layers
    L = len(layers)
    _, acts = forward(theta, X, arch, keep=True)
    params = unpack(theta, arch)
    ones = torch.ones(B, 1, n, dtype=theta.dtype, device=theta.device)
    augT = [torch.cat([a.transpose(1, 2), ones], dim=1) for a in acts[:-1]]     # (B, in+1, n)
    # deltas[l]: (B, out_l, K, n), w folded in
    d = torch.eye(K, dtype=theta.dtype, device=theta.device)[None, :, :, None] * w[:, None, None, :]
    deltas = [None] * L
    for li in range(L - 1, -1, -1):
        deltas[li] = d
        if li > 0:
            W = params[li][0]
            d = torch.bmm(W.transpose(1, 2), d.reshape(B, W.shape[1], K * n)).reshape(B, W.shape[2], K, n)
            der = _dact(acts[li].transpose(1, 2), layers[li - 1][2])
            if der is not None:
                d = d * der.unsqueeze(2)
    P = arch.n_params
    G = torch.empty(B, P, P, dtype=theta.dtype, device=theta.device)
    sl = arch.slices
    for l in range(L):
        dl, al = deltas[l], augT[l]
        ol, il = dl.shape[1], al.shape[1]
        s_l, po, pi = ol * il, ol * (ol + 1) // 2, il * (il + 1) // 2
        if K * s_l * s_l + _EW * K * s_l <= po * pi + _EW * (2 * K * po + pi):
            # small fan-in (first layer): the layer's Jacobian block itself is cheap
            Jl = (dl[:, :, None] * al[:, None, :, None, :]).reshape(B, s_l, K * n)
            G[:, sl[l], sl[l]] = torch.bmm(Jl, Jl.transpose(1, 2))
        else:
            flat = _sym_plan(ol, il, theta.device)
            C = _pair_products(dl, summed=True)                                # (B, #pairs_o, n)
            A = _pair_products(al)                                             # (B, #pairs_i, n)
            M = torch.bmm(C, A.transpose(1, 2)).reshape(B, -1)
            G[:, sl[l], sl[l]] = M.index_select(1, flat).reshape(B, s_l, s_l)
        for m in range(l + 1, L):
            dm, am = deltas[m], augT[m]
            om, im = dm.shape[1], am.shape[1]
            if ol * om >= 100:
                # C_i = δ_l[i] δ_m[i]ᵀ as one batched (ol x K)(K x om) product per sample:
                # fewer passes over memory than the broadcast-multiply-and-sum below
                Dl = dl.permute(0, 3, 1, 2).reshape(B * n, ol, K)
                Dm = dm.permute(0, 3, 2, 1).reshape(B * n, K, om)
                C = torch.bmm(Dl, Dm).reshape(B, n, ol * om).transpose(1, 2)
            else:
                C = (dl[:, :, None] * dm[:, None]).sum(3).reshape(B, ol * om, n)
            A = (al[:, :, None] * am[:, None]).reshape(B, il * im, n)
            M = torch.bmm(C, A.transpose(1, 2)).view(B, ol, om, il, im).permute(0, 1, 3, 2, 4)
            M = M.reshape(B, ol * il, om * im)
            G[:, sl[l], sl[m]] = M
            G[:, sl[m], sl[l]] = M.transpose(1, 2)
    return G


def init_nguyen_widrow(arch: Arch, B: int, generator: torch.Generator, dtype=torch.float64,
                       device="cpu") -> torch.Tensor:
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
