"""Identifiability of (d, h, E) and the image-based inverse: the library inference uses.

* :mod:`.local` -- local bounds: Fisher information and Cramér–Rao relative std from Jacobians;
* :mod:`.region` -- the identifiability map inference reads (:data:`.region.DEFAULT_MAP`);
* :mod:`.measure` -- measurement sets, noise, the image representation (shape PCA);
* :mod:`.image_model` -- the image model (shape PCA -> the paper's MLP) and its validation;
* :mod:`.refine` -- the physics fit: maximum likelihood through the forward model;
* :mod:`.solves` -- cached forward solves for the fit and the bounds.

The studies that produced the shipped map and the tables of docs/identifiability.md live in
:mod:`elastimap.workflows.studies`; this package imports neither them nor the camera.
"""
