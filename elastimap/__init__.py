"""elastimap: elasticity imaging of a tissue inclusion, from forward model to inference.

``elastimap`` is the only top-level name the project installs; every stage ("room") is a
subpackage installed from its own top-level folder (README, "Layout"):
``elastimap.solver`` (gmsh geometry, DOLFINx solve, image and features), ``elastimap.dataset``
(Parquet schema, reading, plots, the calibration-phantom table), ``elastimap.sweep`` (batch runs),
``elastimap.training`` (the MLP inverse), ``elastimap.identify`` (identifiability, the image model,
the FEM fit), ``elastimap.camera`` (optical sensor side), ``elastimap.gap`` (sim-to-real diagnosis)
and ``elastimap.workflows`` (pipelines and the identifiability studies).

This folder itself is the core every room may import, and it imports no room:
``errors`` (:class:`~elastimap.errors.UserError`), ``constraints`` (declared parameter rules,
``check_range``), ``cli_util`` (the CLI runner, shared options, lazy groups), ``outputs`` (output
paths checked before any work), ``provenance`` (the code version and host stamped on results);
plus the umbrella command ``elastimap`` (``cli.py``), which imports the rooms only when one runs.
``tests/contracts/test_architecture.py`` checks this layering.
"""

__version__ = "0.1.0"
