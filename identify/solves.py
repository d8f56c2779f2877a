"""Cached forward solves for the local study (finite-difference checks, indentation check).

Each solve is stored once under ``<cache>/<key>.npz`` (key = hash of the solve parameters), so
reruns of the study and of the tests cost nothing.  Only this module imports the solver.
"""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np

DEFAULT_CACHE = "data/identify/solves"


def _key(p) -> str:
    return hashlib.sha256(json.dumps(p.to_dict(), sort_keys=True).encode()).hexdigest()[:20]


def cached_solve(d: float, h: float, E: float, *, mesh: str = "default", delta: float = 3.0,
                 nonlinearity: float = 0.0, cache: str = DEFAULT_CACHE) -> dict:
    """One forward solve (tied interface, quarter model) -> dict of image, image_raw, features, force."""
    import dataclasses

    from elastimap.solver import SolveParams

    p = SolveParams().with_inclusion(d=float(d), h=float(h), E=float(E))
    p = p.replace(disc=dataclasses.replace(p.disc, mesh=mesh),
                  loading=dataclasses.replace(p.loading, delta=float(delta)),
                  tissue=dataclasses.replace(p.tissue, nonlinearity=float(nonlinearity)))
    path = os.path.join(cache, _key(p) + ".npz")
    if os.path.exists(path):
        z = np.load(path)
        return {k: z[k] for k in z.files}
    from elastimap.solver import solve

    r = solve(p)
    out = {"image": r.image.astype(np.float64), "image_raw": r.image_raw.astype(np.float64),
           "O": np.array([r.O1, r.O2, r.O3]), "force": np.array(r.force), "force_ref": np.array(r.force_ref),
           "theta": np.array([d, h, E]), "delta": np.array(r.delta), "seconds": np.array(r.seconds)}
    os.makedirs(cache, exist_ok=True)
    tmp = path + f".tmp{os.getpid()}.npz"
    np.savez(tmp, **out)
    os.replace(tmp, path)
    return out
