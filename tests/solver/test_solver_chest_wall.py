"""The chest-wall compliance switch (``Tissue.wall_compliance``): the slab's bottom on a Winkler
foundation instead of fixed.  Tiny meshes; the rigid wall (0) stays the model before, bit for bit."""

import numpy as np
import pytest

from elastimap.errors import UserError
from elastimap.sensor import Sensor, SlabSpec
from elastimap.solver.params import Discretisation, SolveParams, Tissue, from_sensor, to_sensor

pytestmark = pytest.mark.xdist_group("test_solver_chest_wall")


def tiny(c_w: float = 0.0, **disc) -> SolveParams:
    return SolveParams(tissue=Tissue(wall_compliance=c_w), disc=Discretisation(mesh="tiny", **disc))


@pytest.fixture(scope="module")
def solve():
    from elastimap.solver import solve as _solve

    return _solve


def test_validation_names_the_field_and_the_rigid_wall_keeps_every_key():
    for bad in (-0.1, 11.0, float("nan")):
        with pytest.raises(UserError) as e:
            tiny(bad).validate()
        assert e.value.param == "tissue.wall_compliance" and "\n" not in str(e.value)
    # the rigid wall is left out of the solve's key and of the sensor's description and hash
    assert "wall_compliance" not in SolveParams().to_dict()["tissue"]
    assert "wall_compliance" not in Sensor().to_dict()["tissue"]
    soft = Sensor(tissue=SlabSpec(wall_compliance=0.4))
    assert soft.validate().hash() != Sensor().hash()
    assert from_sensor(soft).tissue.wall_compliance == 0.4 and to_sensor(from_sensor(soft), soft) == soft
    p = tiny(0.3)
    assert SolveParams.from_dict(p.to_dict()) == p


def test_rigid_wall_is_the_default_solve_exactly(solve):
    base = solve(tiny())
    zero = solve(tiny(0.0))
    assert zero.O1 == base.O1 and zero.force == base.force and np.array_equal(zero.image_raw, base.image_raw)


@pytest.mark.parametrize("interface", ["tied", "contact"])
def test_a_soft_wall_lowers_the_force_and_moves_the_bottom(interface):
    from elastimap.solver.fem import Model
    from elastimap.solver.geometry import build_mesh

    out = {}
    for c in (0.0, 1e-4, 0.5):
        p = tiny(c, interface=interface).validate()
        m = Model(build_mesh(p), p)
        try:
            sol, _ = m.solve(p.tissue.E, p.loading.delta)
            u_bottom = sol.u.reshape(-1, 3)[m.space.bottom]
            out[c] = (m.plate_force(sol), np.abs(u_bottom).max(), -u_bottom[:, 2].min())
        finally:
            m.destroy()
    rigid, stiff, soft = out[0.0], out[1e-4], out[0.5]
    assert rigid[1] == 0.0
    # a nearly rigid wall approaches the fixed bottom (the spring's limit k_w -> infinity)
    assert stiff[0] == pytest.approx(rigid[0], rel=1e-3) and 0 < stiff[1] < 1e-3
    # c_w = 0.5 mm/kPa under the ~1.1 kPa the bottom carries: it sinks by about half a mm
    assert soft[0] < 0.95 * rigid[0]
    assert 0.3 < soft[2] < 0.7


def test_a_soft_wall_weakens_the_inclusion_image(solve):
    rigid, soft = solve(tiny()), solve(tiny(0.5))
    assert soft.O1 < 0.9 * rigid.O1 and soft.O2 < rigid.O2 and soft.force < rigid.force
    assert np.all(np.isfinite(soft.image))


def test_finite_strain_carries_the_wall_spring():
    """The spring's energy ½ k_w |u|² enters the Newton residual: at a small plate travel the
    finite-strain press equals the linear one (the small-strain limit) with the wall soft."""
    from elastimap.solver import solve as _solve
    from elastimap.solver.params import Loading

    lin = _solve(
        SolveParams(tissue=Tissue(wall_compliance=0.5), disc=Discretisation(mesh="tiny"), loading=Loading(delta=0.05))
    )
    nl = _solve(
        SolveParams(
            tissue=Tissue(wall_compliance=0.5, nonlinearity=1.0),
            disc=Discretisation(mesh="tiny"),
            loading=Loading(delta=0.05),
        )
    )
    assert nl.force == pytest.approx(lin.force, rel=2e-2) and nl.O1 == pytest.approx(lin.O1, rel=3e-2)
