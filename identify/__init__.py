"""The inverse's library: from a difference image (or features) to (d, h, E) and how far to trust it.

* :mod:`.fit` -- the physics fit (:class:`~.fit.ImageFit`, :class:`~.fit.FitConfig`,
  :class:`~.fit.FitResult`, :func:`~.fit.fit_image`, :func:`~.fit.fit_forward`): maximum likelihood
  through the forward model;
* :mod:`.forward_maps` -- the forward maps the fit uses (morphed meshes, mesh levels, defect correction);
* :mod:`.coords` -- the fit's coordinates (depth fraction, Eshelby's contrast of E);
* :mod:`.intervals` -- the fit's calibrated 95 % intervals (scales read from ``maps/intervals.json``);
* :mod:`.bounds` -- local bounds: Fisher information and Cramér–Rao relative std from Jacobians;
* :mod:`.idmap` -- the identifiability map inference reads (:data:`.idmap.DEFAULT_MAP`);
* :mod:`.measure` -- measurement sets, noise, the image representation (shape PCA);
* :mod:`.image_model` -- the image model (shape PCA -> the paper's MLP) and its validation.

The studies that produced the shipped map, the interval scales and the tables of
docs/identifiability.md live in :mod:`elastimap.workflows.studies`; this package imports neither
them nor the camera.
"""
