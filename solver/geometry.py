"""Parametric geometry and mesh: tissue slab, inclusion, three-layer probe (gmsh, OpenCASCADE).

The model (all lengths mm)::

        z = T + H   +-----------+        rigid glass plate, moves down by delta
                    |  layer 3  |        softest PDMS
                    |  layer 2  |
        z = T       |__layer 1__|        hardest PDMS, frictionless on the tissue
    +---------------------------------+  tissue surface (free outside the probe)
    |        (skin layer, optional)   |
    |              ( o )  inclusion   |  centre at depth h below the surface
    |                                 |
    +---------------------------------+  z = 0, rigid chest wall (fixed)

The quarter model keeps x >= 0, y >= 0 (symmetry planes x = 0 and y = 0).

The probe and the tissue are meshed conformingly (fragmented OCC volumes) and
then **split along the probe footprint**: the probe's cells get their own
copies of the footprint nodes.  The result is one mesh with two disconnected
bodies whose footprint nodes coincide pairwise; the interface conditions
(tied normal, unilateral contact, bonded) are imposed on those node pairs by
:mod:`elastimap.solver.interface` and :mod:`elastimap.solver.reduction`.

Mesh size is a function of position: ``h0`` inside the probe and the upper
tissue under it, ``h_inc`` on and near the inclusion, growing linearly with
distance (``grading``) up to ``h_max``.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from .params import SolveParams

# cell markers (CORE: the core of a core/shell inclusion, ``Inclusion.core``; the shell is INCLUSION)
TISSUE, INCLUSION, SKIN, CORE = 1, 2, 3, 4
PROBE_LAYER0 = 10  # layer i (0 = tissue side) gets PROBE_LAYER0 + i

# mesh levels: (h0 probe/footprint mm, h_max mm, grading, inclusion resolution = elements per diameter);
# ``Discretisation.sizing = "fixed"``: the inclusion's element size d / per_d has a 0.25 mm floor and
# the size grows away from the inclusion with the same grading as away from the footprint
LEVELS = {
    "tiny": (3.2, 20.0, 0.6, 6.0),
    "coarse": (2.0, 14.0, 0.45, 10.0),
    "default": (1.6, 12.0, 0.35, 12.0),
    "fine": (1.1, 9.0, 0.28, 16.0),
    "finer": (0.8, 7.0, 0.22, 22.0),
}
#: ``Discretisation.sizing = "by_d"``: (per_d, grading away from the inclusion) per level, no floor
#: but ``MIN_H_INC``.  The zone the inclusion refines scales with d and reaches the surface above
#: it; both gradings shrink further for small inclusions (:func:`by_d_gradings`; O2 converges
#: with them, docs/forward-model.md).
SIZED_BY_D = {
    "tiny": (6.0, 0.45),
    "coarse": (10.0, 0.28),
    "default": (12.0, 0.2),
    "fine": (16.0, 0.14),
    "finer": (22.0, 0.1),
}
MIN_H_INC = 0.05  # mm
#: ``by_d`` below ``BY_D_FULL`` mm: both gradings shrink with the inclusion's size s,
#: g_inc(s) = g_inc · f(s)^a and g(s) = g · f(s)^b with f(s) = min(1, s / BY_D_FULL), (a, b) below;
#: the grading away from the footprint costs fewer dofs per 0.1 % of O2, hence b > a
BY_D_FULL = 6.0  # mm
BY_D_EXPONENTS = (0.3, 1.0)  # (a: away from the inclusion, b: away from the footprint)

_gmsh_lock = threading.Lock()


class MeshError(RuntimeError):
    """gmsh could not build the mesh for these parameters."""


@dataclass
class RawMesh:
    """A tetrahedral mesh as plain arrays (P1 geometry).

    ``x`` (N, 3) node coordinates; ``cells`` (M, 4) node indices; ``markers``
    (M,) cell markers (TISSUE, INCLUSION, SKIN, PROBE_LAYER0 + i).  Probe
    cells reference their own copies of the footprint nodes.
    """

    x: np.ndarray
    cells: np.ndarray
    markers: np.ndarray
    seconds: float


def by_d_gradings(mesh: str, size: float) -> tuple[float, float]:
    """Gradings of ``sizing="by_d"`` for an inclusion of size ``size`` mm (its smallest diameter):
    (away from the footprint, away from the inclusion), both dimensionless (mm of element size per
    mm of distance)::

        f(s) = min(1, s / BY_D_FULL),   g(s) = g_level · f(s)^b,   g_inc(s) = g_inc,level · f(s)^a

    continuous in s, equal to the level's values for s ≥ ``BY_D_FULL`` and finer below it."""
    f = min(1.0, size / BY_D_FULL)
    a, b = BY_D_EXPONENTS
    return LEVELS[mesh][2] * f**b, SIZED_BY_D[mesh][1] * f**a


def _sizes(p: SolveParams) -> tuple[float, float, float, float, float]:
    """(h0, h_max, grading away from the footprint, h_inc, grading away from the inclusion), mm."""
    h0, hmax, grading, per_d = LEVELS[p.disc.mesh]
    inc = p.inclusion
    size = inc.d * min(1.0, inc.aspect)
    if p.disc.sizing == "by_d":
        per_d = SIZED_BY_D[p.disc.mesh][0]
        grading, grading_inc = by_d_gradings(p.disc.mesh, size)
        return h0, hmax, grading, min(h0, max(size / per_d, MIN_H_INC)), grading_inc
    h_inc = min(h0, max(size / per_d, 0.25))
    return h0, hmax, grading, h_inc, grading


def size_expression(T: float, half: float, centre, r: float, aspect: float, sizes) -> str:
    r"""The element size (mm) at (x, y, z) as a gmsh MathEval expression: ``h0`` at the probe
    footprint region (|x|, |y| ≤ ``half``, z ≥ T − 2 mm), growing by ``g`` per mm of distance
    from it, ``h_inc`` on the inclusion's surface, growing by ``g_inc`` per mm of (scaled)
    distance from it, at most ``h_max``::

        s = min(h0 + g · dist_footprint, h_inc + g_inc · |ρ − r|, h_max),
        ρ = √((x − cx)² + (y − cy)² + ((z − cz)/aspect)²)

    ``sizes`` = (h0, h_max, g, h_inc, g_inc) of :func:`_sizes`; every number is written exactly
    (``repr``).  gmsh evaluates it in C++ as the background field, not by a Python callback per
    point (a quarter of the meshing time); the meshes equal those of the same function as a
    Python callback in every cell, node coordinates within about 1e-14 mm
    (tests/solver/test_sizing.py; docs/forward-model.md, 'Shared presses')."""
    h0, hmax, grading, h_inc, grading_inc = (repr(float(v)) for v in sizes)
    cx, cy, cz = (repr(float(v)) for v in centre)
    T, half, r, a = (repr(float(v)) for v in (T, half, r, aspect))
    dx = f"Max(Fabs(x) - {half}, 0.0)"
    dy = f"Max(Fabs(y) - {half}, 0.0)"
    dz = f"Max({T} - 2.0 - z, 0.0)"
    ez = f"((z - {cz}) / {a})"
    footprint = f"{h0} + {grading} * Sqrt({dx} * {dx} + {dy} * {dy} + {dz} * {dz})"
    rho = f"Sqrt((x - {cx}) * (x - {cx}) + (y - {cy}) * (y - {cy}) + {ez} * {ez})"
    return f"Min(Min({footprint}, {h_inc} + {grading_inc} * Fabs({rho} - {r})), {hmax})"


def build_mesh(p: SolveParams) -> RawMesh:
    """Mesh the geometry of ``p`` with gmsh and split the probe from the tissue.

    The steps: gmsh's options (:func:`_set_options`), the OCC volumes fragmented into one
    conforming set (:func:`_add_volumes`), a marker per volume (:func:`_classify_volumes`), the
    graded size field and the 3D mesh (:func:`_generate`), the tetrahedra as arrays
    (:func:`_tetrahedra`), then the probe split off along its footprint (:func:`split_probe`).
    Any gmsh failure is a :class:`MeshError`."""
    import time

    import gmsh

    t0 = time.perf_counter()
    with _gmsh_lock:
        in_main = threading.current_thread() is threading.main_thread()
        gmsh.initialize(interruptible=in_main)
        try:
            _set_options(gmsh)
            gmsh.model.add("elastimap")
            _add_volumes(gmsh.model.occ, p)
            gmsh.model.occ.synchronize()
            vols = gmsh.model.getEntities(3)
            vol_marker = _classify_volumes(gmsh.model.occ, vols, p)
            _generate(gmsh, p)
            x, cells, markers = _tetrahedra(gmsh, vols, vol_marker)
        except MeshError:
            raise
        except Exception as exc:  # gmsh raises bare Exceptions
            raise MeshError(f"gmsh failed: {exc}") from exc
        finally:
            gmsh.finalize()

    cells = np.concatenate(cells)
    markers = np.concatenate(markers)
    x, cells = split_probe(x, cells, markers >= PROBE_LAYER0)
    return RawMesh(x=x, cells=cells, markers=markers, seconds=time.perf_counter() - t0)


def _centre(p: SolveParams) -> tuple[float, float, float]:
    """The inclusion's centre (cx, cy, cz) in mm: its offsets, depth h below the surface z = T."""
    inc = p.inclusion
    return inc.offset_x, inc.offset_y, p.tissue.thickness - inc.h


def _set_options(gmsh) -> None:
    """gmsh's global options: quiet, one thread, the Delaunay 3D algorithm."""
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", 1)
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay


def _add_volumes(occ, p: SolveParams) -> None:
    """Add the OCC volumes and fragment them into one conforming set: the tissue box
    [x0, L/2]² × [0, T] (x0 = 0 for the quarter model, −L/2 for the full one), the optional skin
    box [T − s, T], the inclusion's sphere of radius r = d/2 (and its core's, radius core · r),
    clipped to the quarter and stretched by ``aspect`` along z, and the probe's layer boxes
    [px0, P/2]² stacked from z = T up (all mm)."""
    T, L = p.tissue.thickness, p.tissue.size
    P = p.probe.size
    inc = p.inclusion
    quarter = p.disc.symmetry == "quarter"
    x0 = 0.0 if quarter else -L / 2
    px0 = 0.0 if quarter else -P / 2
    cx, cy, cz = _centre(p)
    r = inc.d / 2
    tissue = occ.addBox(x0, x0, 0, L / 2 - x0, L / 2 - x0, T)
    parts = [(3, tissue)]
    if p.tissue.skin_thickness > 0:
        s = p.tissue.skin_thickness
        parts.append((3, occ.addBox(x0, x0, T - s, L / 2 - x0, L / 2 - x0, s)))
    for radius in (r, inc.core * r) if inc.core > 0 else (r,):
        sph = occ.addSphere(cx, cy, cz, radius)
        if quarter:
            clip = occ.addBox(0, 0, 0, L / 2, L / 2, T)
            sph_parts, _ = occ.intersect([(3, sph)], [(3, clip)])
        else:
            sph_parts = [(3, sph)]
        if inc.aspect != 1.0:
            # dilate after clipping (the centre lies on the symmetry planes, so they are kept);
            # dilating the whole sphere first left an open seam loop that gmsh could not mesh
            occ.dilate(sph_parts, cx, cy, cz, 1.0, 1.0, inc.aspect)
        parts += sph_parts
    z = T
    for th, _E in p.probe.layers:
        parts.append((3, occ.addBox(px0, px0, z, P / 2 - px0, P / 2 - px0, th)))
        z += th
    occ.fragment(parts[:1], parts[1:])


def _classify_volumes(occ, vols, p: SolveParams) -> dict[int, int]:
    """The cell marker of each fragmented volume (gmsh tag -> marker), by its centre of mass c:
    above the surface (c_z > T) the probe layer it lies in; inside the inclusion's ellipsoid
    (((c − centre) / (r, r, r · aspect))² < 1, volume below 1.01 · (4/3) π r³ · aspect) CORE or
    INCLUSION (:func:`_inside_core`); in the skin (c_z > T − s) SKIN; else TISSUE.  The centre of
    mass of a quarter sphere is off-centre but inside it.  A :class:`MeshError` if no volume is
    the inclusion (it was lost in the boolean fragment)."""
    T = p.tissue.thickness
    inc = p.inclusion
    cx, cy, cz = _centre(p)
    r = inc.d / 2
    layer_tops = np.cumsum([0.0] + [th for th, _ in p.probe.layers]) + T
    vol_marker = {}
    for dim, tag in vols:
        c = np.array(occ.getCenterOfMass(dim, tag))
        if c[2] > T:
            k = int(np.searchsorted(layer_tops, c[2]) - 1)
            vol_marker[tag] = PROBE_LAYER0 + k
        else:
            rel = (c - np.array([cx, cy, cz])) / np.array([r, r, r * inc.aspect])
            if float(np.sum(rel**2)) < 1.0 and occ.getMass(dim, tag) < 1.01 * (4 / 3) * math.pi * r**3 * inc.aspect:
                vol_marker[tag] = CORE if _inside_core(occ.getBoundingBox(dim, tag), inc, cz) else INCLUSION
            elif p.tissue.skin_thickness > 0 and c[2] > T - p.tissue.skin_thickness:
                vol_marker[tag] = SKIN
            else:
                vol_marker[tag] = TISSUE
    if INCLUSION not in vol_marker.values():
        raise MeshError("the inclusion volume was lost in the boolean fragment")
    return vol_marker


def _generate(gmsh, p: SolveParams) -> None:
    """Generate the 3D mesh with the element size of :func:`size_expression` as the background
    field (mm), nothing taken from the boundary, the points or the curvature."""
    field = gmsh.model.mesh.field.add("MathEval")
    gmsh.model.mesh.field.setString(
        field,
        "F",
        size_expression(
            p.tissue.thickness, p.probe.size / 2, _centre(p), p.inclusion.d / 2, p.inclusion.aspect, _sizes(p)
        ),
    )
    gmsh.model.mesh.field.setAsBackgroundMesh(field)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.model.mesh.generate(3)


def _tetrahedra(gmsh, vols, vol_marker: dict[int, int]):
    """The mesh as arrays: node coordinates x (N, 3) mm, and per volume its 4-node tetrahedra
    (node indices into x) and their markers (lists of arrays, one per volume and element type)."""
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    x = coords.reshape(-1, 3)
    index = np.zeros(int(node_tags.max()) + 1, dtype=np.int64)
    index[node_tags.astype(np.int64)] = np.arange(node_tags.size)
    cells, markers = [], []
    for _dim, tag in vols:
        etypes, _etags, enodes = gmsh.model.mesh.getElements(3, tag)
        for et, en in zip(etypes, enodes):
            if et != 4:  # 4-node tetrahedron
                continue
            c = index[en.astype(np.int64)].reshape(-1, 4)
            cells.append(c)
            markers.append(np.full(len(c), vol_marker[tag], dtype=np.int32))
    return x, cells, markers


def _inside_core(box, inc, cz: float) -> bool:
    """Whether a volume with bounding box ``box`` (gmsh's x0, y0, z0, x1, y1, z1) lies within the
    core of a core/shell inclusion (its half-widths at most core · d/2, 1 % slack): the core and the
    shell both have their centre of mass at the inclusion's centre, their extents tell them apart."""
    if inc.core <= 0:
        return False
    rc = 1.01 * inc.core * inc.d / 2
    x0, y0, z0, x1, y1, z1 = box
    return (
        max(abs(x0 - inc.offset_x), abs(x1 - inc.offset_x), abs(y0 - inc.offset_y), abs(y1 - inc.offset_y)) <= rc
        and max(abs(z0 - cz), abs(z1 - cz)) <= rc * inc.aspect
    )


def split_probe(x: np.ndarray, cells: np.ndarray, is_probe: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Give the probe cells their own copies of the nodes they share with the tissue."""
    # nodes used by both bodies, ascending (boolean marks, not np.unique: NumPy's unique imports
    # numpy.ma, 0.02 s of a `solve` process; docs/forward-model.md, 'Speed')
    in_probe = np.zeros(len(x), dtype=bool)
    in_probe[cells[is_probe]] = True
    in_other = np.zeros(len(x), dtype=bool)
    in_other[cells[~is_probe]] = True
    shared = np.flatnonzero(in_probe & in_other)
    remap = np.arange(len(x))
    remap[shared] = len(x) + np.arange(len(shared))
    cells = cells.copy()
    cells[is_probe] = remap[cells[is_probe]]
    return np.concatenate([x, x[shared]]), cells
