"""Probe tilt: the rigid plate rotated about the y axis (full model), real tiny-mesh FEM solves."""

import dataclasses

import numpy as np
import pytest

from elastimap.errors import UserError
from elastimap.gap import effects as fx
from elastimap.solver.batch import solve_batch
from elastimap.solver.params import Discretisation, SolveParams


def test_tilt_switch_validation_and_key():
    p = SolveParams(disc=Discretisation(mesh="tiny")).with_inclusion(d=8, h=7, E=50)
    assert "tilt" not in p.to_dict()["loading"]  # tilt 0 is the untilted sample (same store key)
    r = dataclasses.replace
    with pytest.raises(UserError, match="symmetry"):
        p.replace(loading=r(p.loading, tilt=0.01)).validate()  # breaks quarter symmetry
    full = p.replace(disc=r(p.disc, symmetry="full"))
    with pytest.raises(UserError, match="tilt"):
        full.replace(loading=r(p.loading, tilt=0.01, force=1000.0)).validate()
    with pytest.raises(UserError, match="tilt"):
        full.replace(loading=r(p.loading, delta=4.5, tilt=0.09)).validate()  # 4.5 + 0.09 * 12.5 mm > 5 mm
    q = fx.get("tilt").apply_params(p, 1.0)
    assert q.disc.symmetry == "full" and q.loading.tilt == pytest.approx(np.radians(1.0))
    assert "tilt" not in fx.DEFAULT_CANDIDATES


def test_tilted_plate_compresses_the_lower_side_more():
    """u_z = -(δ + θ x) on the probe top, θ > 0: the side x > 0 travels further, so the probe is
    compressed more there; θ = 0 leaves the full model's image symmetric (up to the mesh)."""
    p = SolveParams(disc=Discretisation(mesh="tiny", symmetry="full")).with_inclusion(d=8, h=7, E=50)
    p1 = p.replace(loading=dataclasses.replace(p.loading, tilt=0.02))
    r0, r1 = solve_batch([p, p1])  # one mesh and model: tilt only changes the plate's travel
    nx = r0.image_raw.shape[1]

    def sides(w):
        return float(w[:, : nx // 2].mean()), float(w[:, nx // 2 :].mean())

    l0, rr0 = sides(r0.image_raw)
    l1, rr1 = sides(r1.image_raw)
    asym0 = abs(rr0 - l0)
    assert rr1 - l1 > 10 * asym0  # asymmetric in the expected direction, far beyond the mesh's own
    # each half moves the expected way (most of the extra travel goes into the soft tissue, so the
    # probe's own compression changes by a fraction of θ·x)
    assert rr1 > rr0 and l1 < l0
    # the inclusion's difference image leans towards the more compressed side
    dl, dr = r1.image[:, : nx // 2].sum(), r1.image[:, nx // 2 :].sum()
    assert dr > dl and r1.force > 0
    assert np.allclose(r0.image, r0.image[:, ::-1], atol=0.05 * np.abs(r0.image).max())
