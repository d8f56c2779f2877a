"""The identifiability studies: how the shipped map and the tables of docs/identifiability.md were made.

Each module is a click command ``main``, run as ``python -m elastimap.workflows.studies.<name>``
or ``elastimap identify <name>``:

=================  =================================================================================
``global_cv``      cross-validated error of d, h, E per measurement set (gradient boosting)
``fd_check``       Cramér–Rao bounds from real finite-difference Jacobians at two points
``fdgrid``         real finite-difference Jacobians on a coarse grid (cached solves)
``crbmap``         Cramér–Rao maps from a GP surrogate, FD-scaled; ``--install`` writes the map
                   inference reads (``identify/maps/default.npz``)
``cameramap``      the map's ``camera`` set: Cramér–Rao bounds under the nominal camera's noise,
                   from the morphed map's exact derivative; ``install`` adds it to the shipped map
``mapcheck``       the map against the real-FD grid
``imagenet``       HOV / LOOCV of the image-based inverse; ``--save-model`` trains the deployed one
``region_score``   held-out errors and interval coverage inside / outside the identifiable region
=================  =================================================================================

The library they study is :mod:`elastimap.identify` (bounds, the map, the image model, the
physics fit); inference imports that library, never these studies.
"""
