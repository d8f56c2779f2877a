"""The studies: how the shipped identifiability map, the deployed image model, the calibrated
intervals and the tables of docs/identifiability.md and docs/camera.md were made.

Each study is a module here with a click command ``main`` that stands alone (its docstring states
the problem and shows how to run it), run as ``elastimap study <name> ...`` or
``python -m elastimap.workflows.studies.<name> ...``.  :data:`STUDIES` is the one list of them:
``elastimap study --help`` shows it, and the tests check that every module here is in it.

The library they study is :mod:`elastimap.identify` (bounds, the map, the image model, the
physics fit); inference imports that library, never these studies.
"""

#: study name (= its module) -> the one line ``elastimap study --help`` shows.
STUDIES = {
    "global_cv": "Cross-validated error of d, h, E per measurement set (gradient boosting).",
    "fd_check": "Cramér–Rao bounds from real finite-difference Jacobians at two points.",
    "fdgrid": "Real finite-difference Jacobians on a grid of design points (cached solves).",
    "crbmap": "Cramér–Rao identifiability maps; --install writes the map inference uses.",
    "cameramap": "The map's camera-frames set (nominal camera's noise); install adds it to the map.",
    "mapcheck": "Compare the identifiability map with the real-FD bounds.",
    "image_model": "Validate the image model (image PCA -> MLP); --save-model trains the deployed one.",
    "region_score": "Held-out errors and interval coverage inside / outside the identifiable region.",
    "levelbias": "Each mesh level's image error against a finer world and the (d, h, E) shift it causes.",
    "valleyfit": "Re-fit frames-benchmark lesions with one ingredient changed (image, start, maps, fit).",
    "interval_calibration": "The calibrated interval scales of the physics fit from frames-benchmark records.",
    "modelform": "The fit's error budget with and without the learnt model-form error, on another model's phantoms.",
    "pressprior": "The product's fit of a variant world's frames without and with the flat field's press term.",
    "moduli_per_mesh": "A sweep with several moduli per mesh against a Latin hypercube as training data.",
}


def command_specs() -> dict[str, tuple[str, str]]:
    """``{name: ("module:main", help line)}`` for :class:`elastimap.cli_util.LazyGroup`."""
    return {name: (f"elastimap.workflows.studies.{name}:main", line) for name, line in STUDIES.items()}
