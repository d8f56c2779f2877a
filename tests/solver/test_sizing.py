"""The ``sizing="by_d"`` rule (elastimap.solver.geometry.by_d_gradings): finer gradings for small
inclusions, the level's own at and above ``BY_D_FULL``, continuous in d, ordered by level.

Pure checks of the sizing function plus one tiny gmsh mesh; the convergence it buys is measured by
``python -m elastimap.solver.verify_morph --checks convergence`` (docs/forward-model.md), not here.
"""

import numpy as np
import pytest

from elastimap.solver import geometry
from elastimap.solver.geometry import BY_D_FULL, LEVELS, SIZED_BY_D, by_d_gradings
from elastimap.solver.params import Discretisation, SolveParams

ORDER = ("tiny", "coarse", "default", "fine", "finer")


@pytest.mark.parametrize("mesh", ORDER)
def test_large_inclusions_keep_the_level_gradings(mesh):
    for s in (BY_D_FULL, 8.0, 15.0):
        assert by_d_gradings(mesh, s) == pytest.approx((LEVELS[mesh][2], SIZED_BY_D[mesh][1]))


@pytest.mark.parametrize("mesh", ORDER)
def test_small_inclusions_get_finer_gradings_growing_continuously_with_d(mesh):
    s = np.linspace(0.5, 2 * BY_D_FULL, 2001)
    g = np.array([by_d_gradings(mesh, v) for v in s])
    small = s < BY_D_FULL - 1e-9
    full = np.array([LEVELS[mesh][2], SIZED_BY_D[mesh][1]])
    assert np.all(g[small] < full) and np.all(g > 0)
    assert np.all(np.diff(g, axis=0) >= -1e-15)  # never coarser for a smaller inclusion
    # continuous: no step anywhere (in particular none at BY_D_FULL); on this grid (0.0055 mm
    # apart) a step of 1 % of the level's grading would show
    assert np.max(np.abs(np.diff(g, axis=0)) / full) < 0.01


def test_finer_levels_are_finer_at_every_d():
    for s in (1.0, 2.0, 3.0, 4.0, 6.0, 10.0):
        g = [by_d_gradings(m, s) for m in ORDER]
        assert all(a[0] > b[0] and a[1] > b[1] for a, b in zip(g, g[1:])), (s, g)


def test_fixed_sizing_is_unchanged_by_the_rule():
    for d in (2.0, 8.0):
        p = SolveParams().with_inclusion(d=d, h=d / 2 + 3)
        h0, hmax, grading, h_inc, grading_inc = geometry._sizes(p)
        assert (h0, hmax, grading) == LEVELS["default"][:3] and grading_inc == grading


def _mean_edge_between(raw, centre, r_in, r_out):
    c = raw.cells[raw.markers < geometry.PROBE_LAYER0]
    r = np.linalg.norm(raw.x[c].mean(axis=1) - centre, axis=1)
    near = (r > r_in) & (r < r_out)
    x = raw.x[c[near]]
    edges = [np.linalg.norm(x[:, i] - x[:, j], axis=1) for i in range(4) for j in range(i + 1, 4)]
    return float(np.mean(edges))


def test_a_small_inclusion_refines_the_tissue_around_it(monkeypatch):
    """tiny mesh, d = 2 mm: the rule makes the tissue 3-8 mm from the inclusion's centre finer than
    the level's gradings would (the rule switched off by BY_D_FULL = 2 mm)."""
    p = SolveParams(disc=Discretisation(mesh="tiny", sizing="by_d")).with_inclusion(d=2.0, h=4.0)
    centre = np.array([0.0, 0.0, p.tissue.thickness - 4.0])
    with_rule = geometry.build_mesh(p)
    monkeypatch.setattr(geometry, "BY_D_FULL", 2.0)
    without = geometry.build_mesh(p)
    assert _mean_edge_between(with_rule, centre, 3.0, 8.0) < 0.9 * _mean_edge_between(without, centre, 3.0, 8.0)
    assert len(with_rule.x) > len(without.x)


def _python_size(T, half, centre, r, aspect, sizes):
    """The size function as the Python callback that meshed every sample before the MathEval field."""
    import math

    h0, hmax, grading, h_inc, grading_inc = sizes
    cx, cy, cz = centre

    def size(dim, tag, x, y, zz, lc):
        dx = max(abs(x) - half, 0.0)
        dy = max(abs(y) - half, 0.0)
        dz = max(T - 2.0 - zz, 0.0)
        s = h0 + grading * math.sqrt(dx * dx + dy * dy + dz * dz)
        rr = math.sqrt((x - cx) ** 2 + (y - cy) ** 2 + ((zz - cz) / aspect) ** 2)
        s = min(s, h_inc + grading_inc * abs(rr - r))
        return min(s, hmax)

    return size


@pytest.mark.parametrize(
    ("mesh", "d", "h", "aspect", "sizing"),
    [("default", 8.0, 7.0, 1.0, "fixed"), ("tiny", 3.0, 5.0, 0.7, "fixed"), ("tiny", 2.5, 6.0, 1.0, "by_d")],
)
def test_the_size_field_meshes_as_the_python_size_function(monkeypatch, mesh, d, h, aspect, sizing):
    """gmsh evaluates the size as a MathEval background field (``size_expression``); the same function
    as a Python callback (how every sample was meshed before) gives the same mesh: every cell and
    marker equal, node coordinates within 1e-12 mm."""
    import gmsh

    p = SolveParams(disc=Discretisation(mesh=mesh, sizing=sizing)).with_inclusion(d=d, h=h, aspect=aspect)
    field = geometry.build_mesh(p)
    made = []
    expression = geometry.size_expression

    def record(*args):
        made.append(args)
        return expression(*args)

    def callback_instead(tag):
        gmsh.model.mesh.field.remove(tag)
        gmsh.model.mesh.setSizeCallback(_python_size(*made[-1]))

    monkeypatch.setattr(geometry, "size_expression", record)
    monkeypatch.setattr(gmsh.model.mesh.field, "setAsBackgroundMesh", callback_instead)
    python = geometry.build_mesh(p)
    assert made and made[-1][-1] == geometry._sizes(p)
    assert np.array_equal(field.cells, python.cells) and np.array_equal(field.markers, python.markers)
    assert np.abs(field.x - python.x).max() <= 1e-12
