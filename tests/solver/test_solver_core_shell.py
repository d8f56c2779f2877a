"""The core/shell inclusion switch (``Inclusion.core``, ``Inclusion.core_ratio``): a concentric core
of its own modulus inside the inclusion.  Tiny meshes."""

import math

import numpy as np
import pytest

from elastimap.errors import UserError
from elastimap.solver.params import Discretisation, Inclusion, SolveParams

pytestmark = pytest.mark.xdist_group("test_solver_core_shell")


def lesion(E=30.0, presses="shared", **core):
    from elastimap.solver import solve

    p = SolveParams(inclusion=Inclusion(d=8, h=7, E=E, **core), disc=Discretisation(mesh="tiny")).validate()
    return solve(p, presses=presses)


@pytest.fixture(scope="module")
def cores():
    return {k: lesion(core=0.6, core_ratio=k) for k in (0.3, 1.0, 3.0)}


def test_core_switch_validation_and_serialisation():
    d = SolveParams().to_dict()
    assert "core" not in d["inclusion"] and "core_ratio" not in d["inclusion"]  # stored keys unchanged
    p = SolveParams(inclusion=Inclusion(core=0.5, core_ratio=2.0))
    assert SolveParams.from_dict(p.to_dict()) == p
    for bad, param in (
        (dict(core=0.95), "inclusion.core"),
        (dict(core=0.5, core_ratio=0.0), "inclusion.core_ratio"),
        (dict(core=0.5, E=5.0), "inclusion.core"),  # the shell's modulus equals the tissue's
    ):
        with pytest.raises(UserError) as e:
            SolveParams(inclusion=Inclusion(**bad)).validate()
        assert e.value.param == param
    with pytest.raises(UserError) as e:
        SolveParams(inclusion=Inclusion(core=0.5), disc=Discretisation(geometry="morph")).validate()
    assert e.value.param == "inclusion.core"


def test_the_core_is_meshed_with_its_own_marker():
    from elastimap.solver.geometry import CORE, INCLUSION, build_mesh

    p = SolveParams(inclusion=Inclusion(d=8, h=7, core=0.6), disc=Discretisation(mesh="tiny"))
    raw = build_mesh(p)
    x, cells = raw.x, raw.cells

    def volume(marker):
        t = x[cells[raw.markers == marker]]
        return float(
            np.abs(np.einsum("ij,ij->i", t[:, 1] - t[:, 0], np.cross(t[:, 2] - t[:, 0], t[:, 3] - t[:, 0]))).sum() / 6
        )

    quarter_sphere = lambda r: math.pi * r**3 / 3  # (4/3) π r³ / 4
    # tiny meshes the core (2.4 mm radius) with ten tetrahedra: a faceted core, 75 % of the sphere's volume
    assert volume(CORE) == pytest.approx(quarter_sphere(0.6 * 4), rel=0.3)
    assert volume(CORE) + volume(INCLUSION) == pytest.approx(quarter_sphere(4), rel=0.05)


def test_reference_press_is_the_tissue_and_the_core_stiffens_monotonically(cores):
    # the reference press (inclusion modulus = the tissue's) holds no core either
    assert cores[0.3].force_ref == cores[1.0].force_ref == cores[3.0].force_ref
    assert cores[0.3].O1 < cores[1.0].O1 < cores[3.0].O1
    assert cores[0.3].force < cores[1.0].force < cores[3.0].force
    # a core as stiff as its shell is the uniform inclusion, up to the two meshes
    uniform = lesion()
    assert cores[1.0].O2 == pytest.approx(uniform.O2, rel=0.03)
    # and lies between the uniform inclusions of the shell's and the core's moduli
    assert uniform.O1 < cores[3.0].O1 < lesion(E=90.0).O1


def test_shared_presses_carry_the_core(cores):
    # the difference press on the reference press's factors, the core's matrix updated with the weight
    # w of materials.core_weight, equals assembling and factorising each press whole
    separate = lesion(core=0.6, core_ratio=3.0, presses="separate")
    shared = cores[3.0]
    for f in ("O1", "O2", "force", "force_ref"):
        assert getattr(shared, f) == pytest.approx(getattr(separate, f), rel=1e-6), f
    np.testing.assert_allclose(shared.image, separate.image, rtol=0, atol=1e-6 * np.abs(separate.image).max())
