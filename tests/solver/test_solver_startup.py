"""What a `solve` process loads before the physics (docs/forward-model.md, 'Speed'): the DOLFINx
wheel's environment guard run with the distribution names read from the metadata folders, no
``dolfinx.fem.petsc`` on the linear path, and the PETSc matrices that replace its assembly."""

import collections
import importlib.metadata
import os
import re
import subprocess
import sys

import numpy as np

from elastimap.solver.params import Discretisation, SolveParams

TINY = SolveParams(disc=Discretisation(mesh="tiny"))


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def test_distribution_names_from_folders_are_those_of_the_metadata():
    """The guard's input: the same names, as often, as ``importlib.metadata`` reads from every
    METADATA file (the guard's own way)."""
    from elastimap.solver import _boot

    by_metadata = collections.Counter(
        _canonical(d.metadata["Name"]) for d in importlib.metadata.distributions() if d.metadata["Name"]
    )
    assert collections.Counter(_boot._distribution_names()) == by_metadata
    assert "dolfinx-solver-real" in by_metadata


def _python(code: str, drop: tuple[str, ...] = (), **env) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in {**os.environ, **env}.items() if k not in drop}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=environ)


def test_guard_still_refuses_a_petsc4py_distribution(tmp_path):
    """A petsc4py distribution beside the wheel (here a metadata folder on the path) is refused
    with the wheel's own message, before DOLFINx is imported."""
    dist = tmp_path / "petsc4py-3.20.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: petsc4py\nVersion: 3.20.0\n")
    r = _python("import elastimap.solver._boot", PYTHONPATH=str(tmp_path))
    assert r.returncode != 0
    assert "ImportError" in r.stderr and "petsc4py is installed in this environment" in r.stderr, r.stderr[-800:]


def test_a_linear_solve_loads_neither_the_wheel_package_nor_dolfinx_fem_petsc():
    """Nor scipy, nor numpy.ma (imported by the first plain ``np.unique``: 0.02 s)."""
    code = (
        "import sys\nfrom elastimap.solver import solve\nfrom elastimap.solver.params import Discretisation, SolveParams\n"
        "solve(SolveParams(disc=Discretisation(mesh='tiny')).with_inclusion(d=8.0, h=7.0, E=50.0))\n"
        "print('LOADED', sorted(m for m in ('dolfinx_solver', 'dolfinx.fem.petsc', 'cffi.cparser', 'scipy', 'numpy.ma')"
        " if m in sys.modules))\n"
    )
    r = _python(code)
    assert r.returncode == 0, r.stderr[-800:]
    assert "LOADED []" in r.stdout, r.stdout[-500:]


def test_petsc_matrix_is_dolfinx_petsc_assembly_bit_for_bit():
    """A₁ (the inclusion's cells at unit modulus) and M_Γ's form assembled into
    :func:`~elastimap.solver.space.petsc_matrix` equal DOLFINx's PETSc assembly: pattern, values,
    block size."""
    import ufl
    from dolfinx import fem
    from dolfinx import mesh as dmesh
    from dolfinx.fem import petsc as fpetsc

    from elastimap.solver.fem import Model
    from elastimap.solver.geometry import build_mesh
    from elastimap.solver.space import petsc_matrix

    p = TINY.with_inclusion(d=8.0, h=7.0, E=50.0)
    model = Model(build_mesh(p), p)
    try:
        A1 = model._unit_inclusion()
        ds_tags = dmesh.meshtags(
            model.mesh,
            2,
            np.arange(model.mesh.topology.index_map(2).size_local, dtype=np.int32)[:50],
            np.ones(50, dtype=np.int32),
        )
        u, v = ufl.TrialFunction(model.V), ufl.TestFunction(model.V)
        surface = fem.form(u[2] * v[2] * ufl.Measure("ds", domain=model.mesh, subdomain_data=ds_tags)(1))
        values, M = petsc_matrix(surface)
        fem.assemble_matrix(values, surface)
        M.assemble()
        for mine, form in ((A1, model._a1), (M, surface)):
            ref = fpetsc.assemble_matrix(form)
            ref.assemble()
            for a, b in zip(mine.getValuesCSR(), ref.getValuesCSR()):
                assert np.array_equal(a, b)
            assert mine.getBlockSizes() == ref.getBlockSizes()
            ref.destroy()
        M.destroy()
    finally:
        model.destroy()


def test_the_solve_command_pins_blas_threads_before_numpy_loads():
    """`elastimap solve` imports numpy only after OpenMP/BLAS threads are pinned to 1 (solver/_threads.py):
    numpy's OpenBLAS starts no thread per core in a process that solves on one core."""
    code = (
        "import os, sys\n"
        "class Hook:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'numpy':\n"
        "            print('AT NUMPY', os.environ.get('OPENBLAS_NUM_THREADS'), os.environ.get('OMP_NUM_THREADS'))\n"
        "            sys.meta_path.remove(self)\n"
        "sys.meta_path.insert(0, Hook())\n"
        "from elastimap.cli import main\n"
        "try:\n"
        "    main(['solve', '--d', '8', '--h', '7', '--E', '50', '--mesh', 'tiny', '--json'])\n"
        "except SystemExit as e:\n"
        "    assert not e.code, e.code\n"
    )
    r = _python(code, drop=("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"))
    assert r.returncode == 0, r.stderr[-800:]
    assert "AT NUMPY 1 1" in r.stdout, r.stdout[-500:]


def test_the_first_solve_imports_the_stack_with_the_collector_paused_then_freezes_it():
    """``api._import_the_stack``: the import objects go to the collector's permanent generation, the
    collector runs again afterwards (a cycle made later is collected), and a process that imported
    ``solver.fem`` itself is left as it was."""
    code = (
        "import gc, sys\nfrom elastimap.solver import solve\nfrom elastimap.solver.params import Discretisation, SolveParams\n"
        "FIRST\n"
        "p = SolveParams(disc=Discretisation(mesh='tiny')).with_inclusion(d=8.0, h=7.0, E=50.0)\n"
        "r = solve(p)\nfrozen = gc.get_freeze_count()\n"
        "import weakref\nclass Node: pass\na = Node(); a.me = a; alive = weakref.ref(a); del a\ngc.collect()\n"
        "print('STATE', gc.isenabled(), frozen > 10000, alive() is None, 'elastimap.solver.fem' in sys.modules, r.O2 > 0)\n"
    )
    r = _python(code.replace("FIRST\n", ""))
    assert r.returncode == 0, r.stderr[-800:]
    assert "STATE True True True True True" in r.stdout, r.stdout[-500:]
    r = _python(code.replace("FIRST\n", "import elastimap.solver.fem\n"))
    assert r.returncode == 0, r.stderr[-800:]
    assert "STATE True False True True True" in r.stdout, r.stdout[-500:]


def test_the_sampler_finds_the_cells_dolfinx_finds_from_all_candidates():
    """``sampler.near_candidates`` drops only cells farther than its margin: the colliding cells of
    every pixel (hence the cell each is evaluated in) are DOLFINx's from the whole candidate list."""
    from elastimap.solver.geometry import build_mesh
    from elastimap.solver.sampler import ImageSampler, near_candidates
    from elastimap.solver.space import Space

    # isort: split
    from dolfinx import geometry  # after the solver's modules (solver/_boot.py)

    cases = [("tiny", "quarter", 8.0, 7.0), ("coarse", "quarter", 3.0, 12.0), ("tiny", "full", 12.0, 9.0)]
    for mesh, symmetry, d, h in cases:
        p = SolveParams(disc=Discretisation(mesh=mesh, symmetry=symmetry)).with_inclusion(d=d, h=h, E=50.0)
        space = Space(build_mesh(p), p)
        sampler = ImageSampler(space, p)
        tree = geometry.bb_tree(space.mesh, 3, entities=space.probe_cells)
        every = geometry.compute_collisions_points(tree, sampler.points)
        full = geometry.compute_colliding_cells(space.mesh, every, sampler.points)
        assert len(every.array) > 2 * len(full.array)  # there is something to prune
        pruned = geometry.compute_colliding_cells(
            space.mesh, near_candidates(space.mesh, every, sampler.points), sampler.points
        )
        assert np.array_equal(pruned.array, full.array) and np.array_equal(pruned.offsets, full.offsets)
        assert np.array_equal(sampler.cells, [full.links(i)[0] for i in range(len(sampler.points))])


def test_ucx_memory_hooks_are_off_unless_the_environment_says_otherwise():
    """``solver/_boot.py`` sets ``UCX_MEM_EVENTS=no`` before ``mpi4py.MPI`` loads UCX, where the
    environment does not set it; a given value is kept."""
    code = "import os\nimport elastimap.solver._boot\nprint('UCX', os.environ['UCX_MEM_EVENTS'])\n"
    r = _python(code, drop=("UCX_MEM_EVENTS",))
    assert r.returncode == 0, r.stderr[-800:]
    assert "UCX no" in r.stdout, r.stdout[-500:]
    r = _python(code, UCX_MEM_EVENTS="yes")
    assert r.returncode == 0, r.stderr[-800:]
    assert "UCX yes" in r.stdout, r.stdout[-500:]
